"""An error-state Kalman filter for a vehicle carrying the board's IMU: the float64 reference (on the device with
`algorithm.mode: eskf`, in the native module's float32 C; docs/eskf.md).

Nominal state (EskfState): position p and velocity v in the run's local ENU frame (m, m/s), the attitude quaternion
q = [w, x, y, z] turning body vectors into ENU, the gyro bias bg (rad/s) and the accelerometer bias ba (m/s^2),
both in the body frame, the mounting C (3 x 3, body -> vehicle: x forward, y left, z up), the gyro's turn-rate error
sg (the body-frame rate error per rad/s of turn about Up: the MPU-6050's scale and cross-axis errors on the axis a
vehicle turns about) and the receiver's position error ge (ENU m, first-order Gauss-Markov, as codegen/sim/neo6m.py
models the NEO-6M). Error state, N_ERR = 23 values in this order (ERR_*): dp (3), dv (3), dtheta (3, a small
rotation in the ENU frame: R_true = (I + [dtheta]x) R), dbg (3), dba (3), dmu (2, the mounting's pitch and yaw
error: C_true = (I - [(0, mu_p, mu_y)]x) C), dsg (3), dge (3). P is its covariance.

Per sample (`mechanise`): the strapdown step, flat-earth ENU, gravity STANDARD_GRAVITY:
    f = f_m - ba,  w' = w_m - bg,  turn = (R w')_U,  w = w' - turn sg,  a = R(q) f - [0, 0, g]
    p += v dt + a dt^2 / 2,  v += a dt,  q <- q (x) [1, w dt / 2] (normalised)
and the sums the covariance's transition needs over the interval: A = sum R dt, B = sum R turn dt, dV = sum R f dt.
Every cov_dt_s (`propagate`): P <- Phi P Phi^T + Q with (columns dp dv dtheta dbg dba dmu dsg dge)
    Phi = I + | 0  T I  -T/2 [dV]x  0   -T/2 A  0  0   0 |   (rows dp)
              | 0  0    -[dV]x      0   -A      0  0   0 |   (rows dv)
              | 0  0     0         -A    0      0  -B  0 |   (rows dtheta)
written out by block (`propagate_covariance`); tests/test_eskf.py holds it to the generic Phi P Phi^T + Q. The
receiver's error steps at each fix: its rows and columns times exp(-dt / gps_tau_s) (`gps_error_step`).
Measurements, each a sequence of scalar updates P <- P - u u^T / s (u = P h^T, s = h u + r: the Joseph form's value
for the optimal gain; the covariance is checked after every step, `covariance_ok`), then the error injected into
the nominal state and reset to zero (`inject`):
- at each GPS fix: the position (E, N, U) as p + ge and the horizontal Doppler velocity (speed and course, as NMEA
  gives them);
- every nhc_dt_s while moving: the non-holonomic constraint, the vehicle's lateral and vertical velocity 0 (noise
  with the lever arm's swing at the body rate; a row beyond nhc_gate sigmas left out);
- every nhc_dt_s at rest (|f|'s shaking, the smoothed rate and horizontal specific force below their limits, the
  last fix slow, and the filter's own velocity not excluding 0 at zupt_gate): zero velocity (3) and zero rate (the
  smoothed gyro reading is the bias, 3).
No heading is measured: yaw is observed through the GPS velocity's changes against the rotated specific force.

Start (`calibrate`, `align`): calibration gives the tilt (yaw 0), the gyro bias and the accelerometer bias along
the mean specific force (its length less g), at rest or (a run that starts driving) from the mean of its first
calibration_s. Yaw is unknown: until the filter starts, the attitude is integrated in that wander frame and each
fix interval's GPS velocity change dv is fitted by least squares as z du + c s (`alignment_fit`): du the rotated
specific force's integral, s the body heading's (a calibration in motion took the mean acceleration for gravity, a
body-fixed horizontal offset b = -c / z that turns with the vehicle). The interval that spans the calibration
(`calibration_interval`: du 0 by construction) ties z to that offset, so a start on the move is found within
seconds. Once the fit's yaw is as sure as the prior assumes, the attitude is levelled by b and turned by z's angle,
the filter starts from the fix and its velocity, and the mounting is set from the body-frame velocity.

`estimate` is the benchmark's method contract (codegen.sim.methods): one pass over the run with every fix, the state
kept after each; each outage continues from the state after its last fix with the IMU alone. An outage that starts
before the filter started extrapolates the last fix along its velocity (the constant-velocity baseline).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from codegen.kernel.reference import STANDARD_GRAVITY, KernelConfig, remap_axes, tilt_from_gravity

N_ERR = 23
N_AL_SUMS = 10  # the yaw fit's sums: intervals, |du|^2, |s|^2, du*s, du*dv, s*dv (re, im), |dv|^2
ERR_P, ERR_V, ERR_TH, ERR_BG, ERR_BA, ERR_MU, ERR_SG, ERR_GE = 0, 3, 6, 9, 12, 15, 17, 20
COV_MAX = 1e30  # a covariance entry beyond this in magnitude (or not a number) is broken (float32 ends at 3.4e38)
PSD_TOL = 1e-9  # the smallest eigenvalue may be this much below 0, relative to the largest (rounding)
ERROR_NAMES = ("pE", "pN", "pU", "vE", "vN", "vU", "thE", "thN", "thU", "bgx", "bgy", "bgz", "bax", "bay", "baz",
               "mu_pitch", "mu_yaw", "sgx", "sgy", "sgz", "geE", "geN", "geU")


@dataclass(frozen=True)
class EskfConfig:
    """The filter's parameters; noise densities per sqrt(Hz), random walks per sqrt(s). Defaults tuned on the
    simulated car's tuning seeds (docs/eskf.md)."""

    cov_dt_s: float = 0.2  # s between covariance propagations (0.1 costs the ESP32 0.15 M instructions per window)
    nhc_dt_s: float = 0.4  # s between pseudo-measurements (non-holonomic or zero velocity; 0.2 was less accurate on
    # the tuning seeds, the constraint's errors being correlated over that time: benchmarks/eskf_cadence.py --tuning)
    accel_noise: float = 0.05  # m/s^2/sqrt(Hz): white specific-force noise, the vehicle's shaking included
    gyro_noise: float = 0.002  # rad/s/sqrt(Hz)
    accel_bias_walk: float = 2e-4  # m/s^2/sqrt(s)
    gyro_bias_walk: float = 2e-5  # rad/s/sqrt(s)
    mount_walk: float = 2e-4  # rad/sqrt(s)
    turn_scale_walk: float = 1e-5  # 1/sqrt(s)
    gps_pos_sigma: float = 2.12  # m per horizontal axis: the NEO-6M's open-sky error, Gauss-Markov (2.5 m CEP)
    gps_up_sigma: float = 3.2  # m
    gps_tau_s: float = 60.0  # s: its correlation time
    gps_white_sigma: float = 0.3  # m per axis: what is not correlated
    gps_vel_sigma: float = 0.15  # m/s per horizontal axis
    gps_slow_sigma: float = 0.4  # m/s: below the course's speed the velocity is reported as 0
    nhc_sigma: float = 0.6  # m/s: lateral and vertical velocity of the vehicle (lever arm, slip, roll, pedalling;
    # 0.2 held the bike's rocking too tightly: tuning seeds 100-104 bike 60 s median 55 -> 13 m, car 7.8 -> 7.9 m)
    saturation_excess_ms2: float = 20.0  # m/s^2: what a clipped sample (the +-2 g range's end) may have lost
    nhc_lever_m: float = 1.0  # m: the device's distance from the vehicle's axles, for the constraint's noise
    nhc_gate: float = 3.0  # sigmas: a lateral or vertical velocity beyond this is no sliding (a lever arm's swing)
    nhc_min_speed: float = 1.0  # m/s: the constraint's mounting terms need motion
    zupt_sigma: float = 0.02  # m/s
    zupt_gate: float = 16.3  # the velocity's normalised square below which it may be 0 (chi-square, 3 dof, 99.9 %)
    zaru_sigma: float = 0.002  # rad/s: the smoothed rate at rest against the bias
    rest_accel_g: float = 0.02  # |f| standard deviation below which the vehicle may be at rest (an idling engine)
    rest_gyro_dps: float = 1.0  # smoothed rate below which it may be at rest
    rest_time_s: float = 0.5  # both this long
    rest_speed_ms: float = 1.5  # and the last fix's speed below this (while fixes arrive)
    rest_horizontal_ms2: float = 0.3  # and the smoothed horizontal specific force below this (a start is no rest)
    stat_tau_s: float = 0.5  # s: the shaking's and the rate's smoothing
    # the start
    align_fixes: float = 5.0  # fix intervals the yaw fit needs at least (and 3)
    align_yaw_sigma_deg: float = 10.0  # the fitted yaw's 1-sigma at most this (the prior's, init_yaw_sigma_deg)
    align_scale: float = 1.25  # the fit's |z| (GPS velocity change over the IMU's) within [1 / this, this]
    align_speed_ms: float = 2.0  # m/s: the filter starts while moving at least this fast (the mounting)
    init_yaw_sigma_deg: float = 10.0
    init_tilt_sigma_deg: float = 0.3  # beside the accelerometer bias's share (_prior)
    init_tilt_moving_deg: float = 2.0  # after a calibration in motion
    init_gyro_bias_dps: float = 0.1  # after a calibration at rest
    init_gyro_bias_moving_dps: float = 0.5  # after a calibration in motion
    init_accel_bias_ms2: float = 0.3
    init_mount_sigma_deg: float = 5.0
    init_turn_scale: float = 0.03  # the MPU-6050's sensitivity (+-3 %) and cross-axis (+-2 %) errors


class EskfState:
    """The filter's whole state (float64 here; a C struct of floats with P[N_ERR][N_ERR] on a device)."""

    __slots__ = ("pe", "pn", "pu", "ve", "vn", "vu", "qw", "qx", "qy", "qz", "bgx", "bgy", "bgz", "bax", "bay",
                 "baz", "c", "p", "aligned", "acc_t", "acc_a", "acc_dv", "since_nhc", "mean_f", "var_f", "wsx",
                 "wsy", "wsz", "rest_s", "al_du", "al_u", "al_s", "al_sums", "al_prev", "gps_speed",
                 "cov_repairs", "gyro_moving", "ahe", "ahn", "sgx", "sgy", "sgz", "acc_b", "gee", "gen", "geu", "t_fix", "rate2", "sat_dv")

    def __init__(self):
        for name in self.__slots__:
            setattr(self, name, 0.0)
        self.qw = 1.0
        self.c = np.eye(3)
        self.p = np.zeros((N_ERR, N_ERR))
        self.acc_a = np.zeros((3, 3))
        self.acc_b = np.zeros((3, 3))
        self.acc_dv = np.zeros(3)
        self.al_du = np.zeros(2)
        self.al_u = np.array([1.0, 0.0])
        self.al_s = np.zeros(2)
        self.al_sums = np.zeros(N_AL_SUMS)
        self.al_prev = None
        self.aligned = False
        self.gyro_moving = False

    def copy(self) -> "EskfState":
        other = EskfState.__new__(EskfState)
        for name in self.__slots__:
            value = getattr(self, name)
            setattr(other, name, value.copy() if isinstance(value, np.ndarray) else value)
        return other

    def rotation(self) -> np.ndarray:
        return _rotation(self.qw, self.qx, self.qy, self.qz)


def _rotation(qw, qx, qy, qz) -> np.ndarray:
    return np.array([
        [1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy)],
        [2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx)],
        [2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy)]])


def skew(a) -> np.ndarray:
    """[a]x: skew(a) @ b = a x b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


# --------------------------------------------------------------------------------------------- start
def calibrate(st: EskfState, samples, kcfg: KernelConfig) -> bool:
    """Tilt from the mean specific force (yaw 0: the wander frame until `align`), gyro bias = the mean rate, and
    the accelerometer bias along that mean: what its length differs from g by (an offset or scale error on the axis
    that points Up, which would otherwise read as a vertical acceleration until the constraints learnt it).
    Returns True when the device moved during it (the kernel's threshold): the bias then holds the road's mean
    turn rate and the tilt its mean acceleration, and the filter starts less sure of both."""
    body = remap_axes(samples, kcfg.axis_map)
    mean = body.mean(axis=0)
    q = tilt_from_gravity(mean[:3])
    st.qw, st.qx, st.qy, st.qz = (float(v) for v in q)
    st.bgx, st.bgy, st.bgz = (float(v) * kcfg.gyro_rads_per_lsb for v in mean[3:])
    norm = float(np.linalg.norm(mean[:3]))
    st.mean_f = norm * kcfg.accel_ms2_per_lsb
    along = (st.mean_f - STANDARD_GRAVITY) / norm  # per count of the mean
    st.bax, st.bay, st.baz = (float(v) * along for v in mean[:3])
    std_g = body[:, :3].std(axis=0) / kcfg.accel_lsb_per_g
    st.gyro_moving = bool(np.any(std_g > kcfg.motion_threshold_g))
    return st.gyro_moving


def _prior(st: EskfState, cfg: EskfConfig) -> np.ndarray:
    """The covariance the filter starts with (and returns to when a step breaks it). Calibration folded the
    accelerometer's bias into the tilt (the level it found makes R f - g vanish): the tilt error is -[g e_U]x^-1 of
    the bias's horizontal part, (dth_E, dth_N) = G dba with G = [-R_N; R_E] / g, plus its own init_tilt_sigma_deg."""
    d = np.zeros(N_ERR)
    d[ERR_P:ERR_P + 3] = (2.0 * cfg.gps_pos_sigma) ** 2
    d[ERR_P + 2] = cfg.gps_up_sigma ** 2
    d[ERR_V:ERR_V + 3] = (2.0 * cfg.gps_vel_sigma) ** 2
    tilt = math.radians(cfg.init_tilt_moving_deg if st.gyro_moving else cfg.init_tilt_sigma_deg) ** 2
    d[ERR_TH:ERR_TH + 3] = (tilt, tilt, math.radians(cfg.init_yaw_sigma_deg) ** 2)
    d[ERR_BG:ERR_BG + 3] = math.radians(cfg.init_gyro_bias_dps) ** 2
    d[ERR_BA:ERR_BA + 3] = cfg.init_accel_bias_ms2 ** 2
    d[ERR_MU:ERR_MU + 2] = math.radians(cfg.init_mount_sigma_deg) ** 2
    d[ERR_SG:ERR_SG + 3] = cfg.init_turn_scale ** 2
    d[ERR_GE:ERR_GE + 3] = (cfg.gps_pos_sigma ** 2, cfg.gps_pos_sigma ** 2, cfg.gps_up_sigma ** 2)
    p = np.diag(d)
    r = st.rotation()
    if st.gyro_moving:  # a calibration in motion: the road's turn rate about Up went into the bias, the roll and
        # pitch rates averaged out
        extra = math.radians(cfg.init_gyro_bias_moving_dps) ** 2 - d[ERR_BG]
        p[ERR_BG:ERR_BG + 3, ERR_BG:ERR_BG + 3] += extra * np.outer(r[2], r[2])
    g = np.vstack([-r[1], r[0]]) / STANDARD_GRAVITY
    pb = p[ERR_BA:ERR_BA + 3, ERR_BA:ERR_BA + 3]
    p[ERR_TH:ERR_TH + 2, ERR_TH:ERR_TH + 2] += g @ pb @ g.T
    p[ERR_TH:ERR_TH + 2, ERR_BA:ERR_BA + 3] = g @ pb
    p[ERR_BA:ERR_BA + 3, ERR_TH:ERR_TH + 2] = (g @ pb).T
    return p


def calibration_interval(st: EskfState, vel_en, seconds: float) -> None:
    """The fix interval that spans the calibration: `vel_en`, the GPS velocity (E, N) of a fix `seconds` before the
    calibration's end. Over the calibration the wander frame's velocity change is 0 by construction (its mean
    specific force was taken for gravity), so that interval's GPS velocity change is all offset: the mean
    acceleration of a calibration in motion, seen by the GPS, and in the IMU as the offset b that follows. The next
    fix closes it (`_alignment_sums`)."""
    st.al_prev = (float(vel_en[0]), float(vel_en[1]))
    st.al_s = np.array([float(seconds), 0.0])



def calibration_fix(gps, t_start: float, t_end: float) -> int | None:
    """The fix whose interval spans a calibration from t_start to t_end (s): the last valid one at or before its
    start, else the first during it (the device's: the fix it last read when the calibration began), or None."""
    valid = np.flatnonzero(gps.valid & (gps.t <= t_end))
    if not len(valid):
        return None
    before = valid[gps.t[valid] <= t_start]
    return int(before[-1] if len(before) else valid[0])


def _alignment_sums(st: EskfState, vel_en) -> None:
    """Add the fix interval that ends now to the yaw fit's sums (AL_*): du, the wander frame's velocity change since
    the previous fix; s, the integral of the body's heading since the calibration (a unit complex number) over it;
    dv, the GPS's velocity change. Complex numbers as east + i north."""
    if st.al_prev is not None:
        du = complex(st.al_du[0], st.al_du[1])
        sh = complex(st.al_s[0], st.al_s[1])
        dv = complex(vel_en[0] - st.al_prev[0], vel_en[1] - st.al_prev[1])
        ds, ddv, sdv = du.conjugate() * sh, du.conjugate() * dv, sh.conjugate() * dv
        st.al_sums += (1.0, abs(du) ** 2, abs(sh) ** 2, ds.real, ds.imag, ddv.real, ddv.imag, sdv.real, sdv.imag,
                       abs(dv) ** 2)
    st.al_prev = (float(vel_en[0]), float(vel_en[1]))
    st.al_du = np.zeros(2)
    st.al_s = np.zeros(2)


def alignment_fit(sums) -> tuple[complex, complex, float] | None:
    """The least-squares fit dv = z du + c s over the fix intervals (`_alignment_sums`): z turns the wander frame
    onto ENU (its angle the yaw, its modulus near 1), c = -z b with b the body-fixed horizontal specific-force offset
    that a calibration in motion (the mean acceleration taken for gravity) or an accelerometer bias leaves, as it
    read at the calibration's heading. Returns (z, c, the yaw's 1-sigma in rad), or None while the fit is not
    determined (fewer than three intervals, no velocity change)."""
    n, sdd, sss, dsr, dsi, dvr, dvi, svr, svi, svv = (float(v) for v in sums)
    sds, sdv, ssv = complex(dsr, dsi), complex(dvr, dvi), complex(svr, svi)
    det = sdd * sss - abs(sds) ** 2
    if n < 3.0 or not det > 1e-12 * max(sdd * sss, 1e-30):
        return None
    z = (sss * sdv - sds * ssv) / det
    c = (sdd * ssv - sds.conjugate() * sdv) / det
    rss = max(svv - (sdv.conjugate() * z + ssv.conjugate() * c).real, 0.0)
    var = rss / (2.0 * n - 4.0)  # per real component
    if abs(z) <= 0.0:
        return None
    return z, c, math.sqrt(var * sss / det) / abs(z)


def align(st: EskfState, t_fix: float, fix_enu, vel_en, cfg: EskfConfig) -> bool:
    """At a fix before the filter runs: add the interval to the yaw fit (`alignment_fit`); once it has
    align_fixes intervals, its yaw's 1-sigma is at most align_yaw_sigma_deg, its scale is plausible and the vehicle
    moves, level the attitude by the fitted offset, turn it by the fitted yaw and start the filter at this fix.
    Returns True when it started now."""
    _alignment_sums(st, vel_en)
    speed = math.hypot(vel_en[0], vel_en[1])
    fit = alignment_fit(st.al_sums)
    if fit is None or st.al_sums[0] < cfg.align_fixes or speed < cfg.align_speed_ms:
        return False
    z, c, yaw_sigma = fit
    if yaw_sigma > math.radians(cfg.align_yaw_sigma_deg) or not 1.0 / cfg.align_scale <= abs(z) <= cfg.align_scale:
        return False
    offset = -c / z * complex(st.al_u[0], st.al_u[1])  # the offset as it reads now, in the wander frame
    _turn(st, offset.imag / STANDARD_GRAVITY, -offset.real / STANDARD_GRAVITY, math.atan2(z.imag, z.real))
    start(st, t_fix, fix_enu, vel_en, cfg)
    return True


def _turn(st: EskfState, th_e: float, th_n: float, yaw: float) -> None:
    """q <- [cos(yaw/2), 0, 0, sin(yaw/2)] (x) [1, th/2] (x) q: a small levelling rotation (th_e, th_n about East
    and North of the wander frame, so that its horizontal specific-force offset vanishes), then the yaw."""
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    hx, hy = 0.5 * th_e, 0.5 * th_n
    qw, qx, qy, qz = qw - hx * qx - hy * qy, qx + hx * qw + hy * qz, qy + hy * qw - hx * qz, qz + hx * qy - hy * qx
    inv = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qw, qx, qy, qz = qw * inv, qx * inv, qy * inv, qz * inv
    cz, sz = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    st.qw, st.qx, st.qy, st.qz = cz * qw - sz * qz, cz * qx - sz * qy, cz * qy + sz * qx, cz * qz + sz * qw


def start(st: EskfState, t_fix: float, fix_enu, vel_en, cfg: EskfConfig) -> None:
    """The filter starts at a fix (t_fix s, ENU m, horizontal velocity m/s) with the attitude it has: the mounting
    from the body-frame velocity, the covariance its prior."""
    st.pe, st.pn, st.pu = (float(x) for x in fix_enu)
    st.ve, st.vn, st.vu = float(vel_en[0]), float(vel_en[1]), 0.0
    _mounting_from_velocity(st)
    st.p = _prior(st, cfg)
    st.t_fix = t_fix
    st.acc_t = st.since_nhc = 0.0
    st.acc_a = np.zeros((3, 3))
    st.acc_b = np.zeros((3, 3))
    st.acc_dv = np.zeros(3)
    st.aligned = True


def _mounting_from_velocity(st: EskfState) -> None:
    """The mounting C (body -> vehicle) from the body-frame velocity (the vehicle's x axis) and the body-frame Up
    (its z axis, made orthogonal to x): the vehicle stands level across its track. Standing, C is kept."""
    r = st.rotation()
    x = r.T @ np.array([st.ve, st.vn, st.vu])
    if np.linalg.norm(x) < 1e-6:
        return
    x /= np.linalg.norm(x)
    up = r.T[:, 2]
    z = up - (up @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    st.c = np.vstack([x, y, z])


# --------------------------------------------------------------------------------------------- per sample
def mechanise(st: EskfState, acc, gyr, dts, kcfg: KernelConfig, cfg: EskfConfig) -> None:
    """The strapdown step over samples (acc, gyr: lists of body-frame [x, y, z] in m/s^2 and counts; dts: s), with
    the covariance propagated every cov_dt_s and the pseudo-measurements every nhc_dt_s (`covariance_step`)."""
    g = STANDARD_GRAVITY
    gscale = kcfg.gyro_rads_per_lsb
    rest_var = (cfg.rest_accel_g * g) ** 2
    rest_w2 = math.radians(cfg.rest_gyro_dps) ** 2
    inv_stat = 1.0 / cfg.stat_tau_s
    horizontal2 = cfg.rest_horizontal_ms2 * cfg.rest_horizontal_ms2
    saturated = 32767.0 * kcfg.accel_ms2_per_lsb  # m/s^2: the range's end (int16)
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    for k in range(len(dts)):
        dt = dts[k]
        if abs(acc[k][0]) >= saturated or abs(acc[k][1]) >= saturated or abs(acc[k][2]) >= saturated:
            st.sat_dv += cfg.saturation_excess_ms2 * dt  # what the clipped sample may have left out
        fx = acc[k][0] - st.bax
        fy = acc[k][1] - st.bay
        fz = acc[k][2] - st.baz
        wx = gyr[k][0] * gscale - st.bgx
        wy = gyr[k][1] * gscale - st.bgy
        wz = gyr[k][2] * gscale - st.bgz
        # the turn-rate error: the rate about Up times sg (the gyro's scale and cross-axis error on that axis)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        turn = r20 * wx + r21 * wy + r22 * wz
        wx -= turn * st.sgx
        wy -= turn * st.sgy
        wz -= turn * st.sgz
        # rest statistics over stat_tau_s: |f|'s variance, the smoothed rate and horizontal specific force
        alpha = min(dt * inv_stat, 1.0)
        nf = math.sqrt(fx * fx + fy * fy + fz * fz)
        st.mean_f += alpha * (nf - st.mean_f)
        d = nf - st.mean_f
        st.var_f += alpha * (d * d - st.var_f)
        st.wsx += alpha * (wx - st.wsx)
        st.wsy += alpha * (wy - st.wsy)
        st.wsz += alpha * (wz - st.wsz)
        # R(q), body -> ENU
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        se = r00 * fx + r01 * fy + r02 * fz
        sn = r10 * fx + r11 * fy + r12 * fz
        su = r20 * fx + r21 * fy + r22 * fz
        st.ahe += alpha * (se - st.ahe)
        st.ahn += alpha * (sn - st.ahn)
        if (st.var_f < rest_var and st.wsx * st.wsx + st.wsy * st.wsy + st.wsz * st.wsz < rest_w2
                and st.ahe * st.ahe + st.ahn * st.ahn < horizontal2):
            st.rest_s += dt
        else:
            st.rest_s = 0.0
        if st.aligned:
            ae, an, au = se, sn, su - g
            st.pe += (st.ve + 0.5 * ae * dt) * dt
            st.pn += (st.vn + 0.5 * an * dt) * dt
            st.pu += (st.vu + 0.5 * au * dt) * dt
            st.ve += ae * dt
            st.vn += an * dt
            st.vu += au * dt
            a = st.acc_a
            a[0, 0] += r00 * dt
            a[0, 1] += r01 * dt
            a[0, 2] += r02 * dt
            a[1, 0] += r10 * dt
            a[1, 1] += r11 * dt
            a[1, 2] += r12 * dt
            a[2, 0] += r20 * dt
            a[2, 1] += r21 * dt
            a[2, 2] += r22 * dt
            b = st.acc_b
            td = turn * dt
            b[0, 0] += r00 * td
            b[0, 1] += r01 * td
            b[0, 2] += r02 * td
            b[1, 0] += r10 * td
            b[1, 1] += r11 * td
            b[1, 2] += r12 * td
            b[2, 0] += r20 * td
            b[2, 1] += r21 * td
            b[2, 2] += r22 * td
            dv = st.acc_dv
            dv[0] += se * dt
            dv[1] += sn * dt
            dv[2] += su * dt
            st.acc_t += dt
        else:  # the yaw fit's sums: the velocity change, and the heading turned by the rate about Up
            st.al_du[0] += se * dt
            st.al_du[1] += sn * dt
            ue, un = st.al_u
            td = turn * dt
            ue, un = ue - un * td, un + ue * td
            inv = 1.0 / math.sqrt(ue * ue + un * un)
            st.al_u[0], st.al_u[1] = ue * inv, un * inv
            st.al_s[0] += st.al_u[0] * dt
            st.al_s[1] += st.al_u[1] * dt
        # q <- q (x) [1, w dt / 2], normalised
        hx, hy, hz = 0.5 * wx * dt, 0.5 * wy * dt, 0.5 * wz * dt
        nw = qw - hx * qx - hy * qy - hz * qz
        nx = qx + hx * qw + hz * qy - hy * qz
        ny = qy + hy * qw - hz * qx + hx * qz
        nz = qz + hz * qw + hy * qx - hx * qy
        inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        qw, qx, qy, qz = nw * inv, nx * inv, ny * inv, nz * inv
        st.qw, st.qx, st.qy, st.qz = qw, qx, qy, qz
        st.rate2 = wx * wx + wy * wy + wz * wz
        if st.aligned and st.acc_t >= cfg.cov_dt_s:
            covariance_step(st, cfg)
            qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz


def covariance_step(st: EskfState, cfg: EskfConfig) -> None:
    """The covariance propagated over the interval just integrated, then (every nhc_dt_s) zero velocity and rate at
    rest, else the non-holonomic constraint while moving."""
    propagate(st, cfg)
    st.since_nhc += cfg.cov_dt_s
    if st.since_nhc + 1e-9 < cfg.nhc_dt_s:
        return
    st.since_nhc = 0.0
    speed = math.sqrt(st.ve * st.ve + st.vn * st.vn + st.vu * st.vu)
    if st.rest_s >= cfg.rest_time_s and st.gps_speed < cfg.rest_speed_ms and zero_velocity_gate(st, cfg):
        zero_velocity_update(st, cfg)
    elif speed > cfg.nhc_min_speed:
        nhc_update(st, cfg)


# --------------------------------------------------------------------------------------------- covariance
def transition(a: np.ndarray, b: np.ndarray, dv: np.ndarray, t: float) -> np.ndarray:
    """Phi over an interval of t s with A = sum R dt, B = sum R turn dt and dV = sum R f dt (the generic, dense
    form)."""
    phi = np.eye(N_ERR)
    sk = skew(dv)
    phi[ERR_P:ERR_P + 3, ERR_V:ERR_V + 3] = t * np.eye(3)
    phi[ERR_P:ERR_P + 3, ERR_TH:ERR_TH + 3] = -0.5 * t * sk
    phi[ERR_P:ERR_P + 3, ERR_BA:ERR_BA + 3] = -0.5 * t * a
    phi[ERR_V:ERR_V + 3, ERR_TH:ERR_TH + 3] = -sk
    phi[ERR_V:ERR_V + 3, ERR_BA:ERR_BA + 3] = -a
    phi[ERR_TH:ERR_TH + 3, ERR_BG:ERR_BG + 3] = -a
    phi[ERR_TH:ERR_TH + 3, ERR_SG:ERR_SG + 3] = -b
    return phi


def process_noise(t: float, cfg: EskfConfig, clipped_dv: float = 0.0) -> np.ndarray:
    """Q over t s: white specific force and rate, random-walk biases and mounting (isotropic: frame-free); and the
    velocity the accelerometer's clipped samples may have lost, up to clipped_dv m/s per axis."""
    q = np.zeros((N_ERR, N_ERR))
    qa = cfg.accel_noise ** 2
    for i in range(3):
        q[ERR_P + i, ERR_P + i] = qa * t ** 3 / 3.0
        q[ERR_P + i, ERR_V + i] = q[ERR_V + i, ERR_P + i] = qa * t * t / 2.0
        q[ERR_V + i, ERR_V + i] = qa * t + clipped_dv * clipped_dv
        q[ERR_TH + i, ERR_TH + i] = cfg.gyro_noise ** 2 * t
        q[ERR_BG + i, ERR_BG + i] = cfg.gyro_bias_walk ** 2 * t
        q[ERR_BA + i, ERR_BA + i] = cfg.accel_bias_walk ** 2 * t
    for i in range(2):
        q[ERR_MU + i, ERR_MU + i] = cfg.mount_walk ** 2 * t
    for i in range(3):
        q[ERR_SG + i, ERR_SG + i] = cfg.turn_scale_walk ** 2 * t
    return q


def _cross_rows(dv: np.ndarray, m: np.ndarray) -> np.ndarray:
    """[dv]x @ m for m with 3 rows, written out (6 multiplies per column)."""
    return np.vstack([dv[1] * m[2] - dv[2] * m[1], dv[2] * m[0] - dv[0] * m[2], dv[0] * m[1] - dv[1] * m[0]])


def propagate_covariance(p: np.ndarray, a: np.ndarray, b: np.ndarray, dv: np.ndarray, t: float,
                         cfg: EskfConfig, clipped_dv: float = 0.0) -> np.ndarray:
    """Phi P Phi^T + Q by blocks: the rows of Phi P first (only dp, dv, dtheta change), then its columns (the same
    operations on M^T), then Q's few entries. Equal to transition(...) @ p @ transition(...).T + process_noise(...)
    (tests/test_eskf.py)."""
    def rows(m):
        out = m.copy()
        th = m[ERR_TH:ERR_TH + 3]
        ba = m[ERR_BA:ERR_BA + 3]
        dvth = _cross_rows(dv, th) + a @ ba  # [dV]x dtheta + A dba
        out[ERR_P:ERR_P + 3] += t * m[ERR_V:ERR_V + 3] - 0.5 * t * dvth
        out[ERR_V:ERR_V + 3] -= dvth
        out[ERR_TH:ERR_TH + 3] -= a @ m[ERR_BG:ERR_BG + 3] + b @ m[ERR_SG:ERR_SG + 3]
        return out

    m = rows(rows(p).T)  # Phi (Phi P)^T = (Phi P Phi^T)^T, symmetric
    m = 0.5 * (m + m.T)
    qa = cfg.accel_noise ** 2
    for i in range(3):
        m[ERR_P + i, ERR_P + i] += qa * t ** 3 / 3.0
        m[ERR_P + i, ERR_V + i] += qa * t * t / 2.0
        m[ERR_V + i, ERR_P + i] += qa * t * t / 2.0
        m[ERR_V + i, ERR_V + i] += qa * t + clipped_dv * clipped_dv
        m[ERR_TH + i, ERR_TH + i] += cfg.gyro_noise ** 2 * t
        m[ERR_BG + i, ERR_BG + i] += cfg.gyro_bias_walk ** 2 * t
        m[ERR_BA + i, ERR_BA + i] += cfg.accel_bias_walk ** 2 * t
    for i in range(2):
        m[ERR_MU + i, ERR_MU + i] += cfg.mount_walk ** 2 * t
    for i in range(3):
        m[ERR_SG + i, ERR_SG + i] += cfg.turn_scale_walk ** 2 * t
    return m


_observer = None


def observe_covariances(callback):
    """Call `callback(st, step)` (step: "prior", "predict", "update") after every step, before its covariance is
    checked; None stops it. For tests; returns the previous callback."""
    global _observer
    previous, _observer = _observer, callback
    return previous


def covariance_ok(p: np.ndarray) -> bool:
    """Symmetric (to rounding) positive semi-definite, every entry a number within +-COV_MAX."""
    if not np.all(np.isfinite(p)) or np.max(np.abs(p)) > COV_MAX:
        return False
    scale = max(float(np.max(np.abs(p))), 1e-300)
    if np.max(np.abs(p - p.T)) > 1e-12 * scale:
        return False
    return float(np.linalg.eigvalsh(p)[0]) >= -PSD_TOL * scale


def _checked(st: EskfState, step: str, cfg: EskfConfig) -> bool:
    """After a step: the covariance usable? If not, it returns to the prior (the nominal state kept), counted in
    cov_repairs, and False says the caller uses nothing of this step."""
    if _observer is not None:
        _observer(st, step)
    if covariance_ok(st.p):
        return True
    st.cov_repairs += 1.0
    st.p = _prior(st, cfg)
    return False


def propagate(st: EskfState, cfg: EskfConfig) -> None:
    """P over the interval integrated since the last propagation; the interval's sums restart."""
    if st.acc_t <= 0.0:
        return
    st.p = propagate_covariance(st.p, st.acc_a, st.acc_b, st.acc_dv, st.acc_t, cfg, st.sat_dv)
    st.acc_t = st.sat_dv = 0.0
    st.acc_a = np.zeros((3, 3))
    st.acc_b = np.zeros((3, 3))
    st.acc_dv = np.zeros(3)
    _checked(st, "predict", cfg)


# --------------------------------------------------------------------------------------------- measurements
def scalar_update(p: np.ndarray, dx: np.ndarray, h: np.ndarray, y: float, r: float):
    """One scalar measurement y = h dx + noise (variance r) against the error state dx accumulated so far: returns
    (P - u u^T / s, dx + u (y - h dx) / s) with u = P h^T, s = h u + r, or None if s is not positive."""
    u = p @ h
    s = float(h @ u) + r
    if not (0.0 < s <= COV_MAX):
        return None
    p = p - np.outer(u, u) / s
    return 0.5 * (p + p.T), dx + u * ((y - float(h @ dx)) / s)


def update(st: EskfState, hs, ys, rs, cfg: EskfConfig, gate: float = 0.0) -> bool:
    """Scalar updates in sequence (rows hs (m, N_ERR), residuals ys against the nominal state, variances rs), then
    the error fed into the nominal state; with a gate (sigmas), a row whose innovation is beyond it is left out.
    Returns False (nothing fed back) if the covariance went wrong."""
    dx = np.zeros(N_ERR)
    p = st.p
    for h, y, r in zip(hs, ys, rs):
        if gate > 0.0:
            innovation = y - float(h @ dx)
            if innovation * innovation > gate * gate * (float(h @ p @ h) + r):
                continue
        out = scalar_update(p, dx, h, y, r)
        if out is None:
            st.cov_repairs += 1.0
            st.p = _prior(st, cfg)
            return False
        p, dx = out
    st.p = p
    if not _checked(st, "update", cfg):
        return False
    inject(st, dx)
    return True


def inject(st: EskfState, dx: np.ndarray) -> None:
    """Nominal state <- nominal (+) dx: positions, velocities and biases add; the attitude turns by dtheta in ENU
    (q <- [1, dtheta / 2] (x) q); the mounting by (0, mu_p, mu_y) in the vehicle frame (C <- (I - [mu]x) C)."""
    st.pe += dx[0]
    st.pn += dx[1]
    st.pu += dx[2]
    st.ve += dx[3]
    st.vn += dx[4]
    st.vu += dx[5]
    hx, hy, hz = 0.5 * dx[6], 0.5 * dx[7], 0.5 * dx[8]
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    nw = qw - hx * qx - hy * qy - hz * qz
    nx = qx + hx * qw + hy * qz - hz * qy
    ny = qy + hy * qw + hz * qx - hx * qz
    nz = qz + hz * qw + hx * qy - hy * qx
    inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    st.qw, st.qx, st.qy, st.qz = nw * inv, nx * inv, ny * inv, nz * inv
    st.bgx += dx[9]
    st.bgy += dx[10]
    st.bgz += dx[11]
    st.bax += dx[12]
    st.bay += dx[13]
    st.baz += dx[14]
    st.sgx += dx[17]
    st.sgy += dx[18]
    st.sgz += dx[19]
    st.gee += dx[20]
    st.gen += dx[21]
    st.geu += dx[22]
    if dx[15] != 0.0 or dx[16] != 0.0:
        c = (np.eye(3) - skew((0.0, dx[15], dx[16]))) @ st.c
        u, _, vt = np.linalg.svd(c)  # back onto a rotation (the first-order step leaves it slightly off)
        st.c = u @ vt


def gps_error_step(p: np.ndarray, t: float, cfg: EskfConfig) -> tuple[np.ndarray, float]:
    """The receiver's position error (first-order Gauss-Markov, gps_tau_s) over t s: its rows and columns of P
    scaled by phi = exp(-t / tau), its variances topped up to the stationary ones. Returns (P, phi)."""
    phi = math.exp(-t / cfg.gps_tau_s)
    p = p.copy()
    ge = slice(ERR_GE, ERR_GE + 3)
    p[ge, :] *= phi
    p[:, ge] *= phi
    for i, sigma in enumerate((cfg.gps_pos_sigma, cfg.gps_pos_sigma, cfg.gps_up_sigma)):
        p[ERR_GE + i, ERR_GE + i] += sigma * sigma * (1.0 - phi * phi)
    return p, phi


def gps_update(st: EskfState, t_fix: float, fix_enu, vel_en, cfg: EskfConfig) -> None:
    """A fix at t_fix s: the covariance brought to its time (the IMU's interval, the receiver's error since the last
    fix), then its position (E, N, U: the position plus the receiver's error) and horizontal velocity."""
    propagate(st, cfg)
    st.p, phi = gps_error_step(st.p, t_fix - st.t_fix, cfg)
    st.gee *= phi
    st.gen *= phi
    st.geu *= phi
    st.t_fix = t_fix
    _checked(st, "predict", cfg)
    speed = math.hypot(vel_en[0], vel_en[1])
    st.gps_speed = speed
    vs = cfg.gps_vel_sigma if speed > 0.0 else cfg.gps_slow_sigma
    hs = np.zeros((5, N_ERR))
    for i in range(3):
        hs[i, ERR_P + i] = hs[i, ERR_GE + i] = 1.0
    hs[3, ERR_V] = hs[4, ERR_V + 1] = 1.0
    ys = (fix_enu[0] - st.pe - st.gee, fix_enu[1] - st.pn - st.gen, fix_enu[2] - st.pu - st.geu,
          vel_en[0] - st.ve, vel_en[1] - st.vn)
    rw = cfg.gps_white_sigma ** 2
    rs = (rw, rw, rw, vs * vs, vs * vs)
    update(st, hs, ys, rs, cfg)


def nhc_rows(st: EskfState) -> tuple[np.ndarray, np.ndarray]:
    """The non-holonomic constraint's two rows (lateral, vertical) and predicted values: v_vehicle = C R^T v,
        d v_veh = C R^T dv + C R^T [v]x dtheta + [v_veh]x (0, mu_p, mu_y)."""
    r = st.rotation()
    v = np.array([st.ve, st.vn, st.vu])
    cr = st.c @ r.T
    vv = cr @ v
    h = np.zeros((2, N_ERR))
    h[:, ERR_V:ERR_V + 3] = cr[1:3]
    h[:, ERR_TH:ERR_TH + 3] = cr[1:3] @ skew(v)
    h[:, ERR_MU:ERR_MU + 2] = skew(vv)[1:3, 1:3]
    return h, vv[1:3]


def nhc_update(st: EskfState, cfg: EskfConfig) -> None:
    """The vehicle neither slides sideways nor leaves the road: its lateral and vertical velocity are 0, to within
    nhc_sigma and what the device's lever arm (nhc_lever_m, not a state) swings at the body rate now."""
    h, pred = nhc_rows(st)
    r = cfg.nhc_sigma ** 2 + cfg.nhc_lever_m ** 2 * st.rate2
    update(st, h, -pred, (r, r), cfg, cfg.nhc_gate)


def zero_velocity_gate(st: EskfState, cfg: EskfConfig) -> bool:
    """Can the filter's velocity be 0? Its normalised square v^T (P_vv + r I)^-1 v within zupt_gate: a smooth cruise
    is as still as a stand to the detector, but the filter knows it moves; a stop after an outage's drift is not
    excluded by it."""
    s = st.p[ERR_V:ERR_V + 3, ERR_V:ERR_V + 3] + cfg.zupt_sigma ** 2 * np.eye(3)
    v = np.array([st.ve, st.vn, st.vu])
    return float(v @ np.linalg.solve(s, v)) < cfg.zupt_gate


def zero_velocity_update(st: EskfState, cfg: EskfConfig) -> None:
    """At rest: the velocity is 0 (3 rows) and the smoothed rate (the bias-corrected gyro, ws) is the bias's error
    (3 rows: w_m - bg - dbg = 0)."""
    hs = np.zeros((6, N_ERR))
    for i in range(3):
        hs[i, ERR_V + i] = 1.0
        hs[3 + i, ERR_BG + i] = 1.0
    ys = (-st.ve, -st.vn, -st.vu, st.wsx, st.wsy, st.wsz)
    rs = (cfg.zupt_sigma ** 2,) * 3 + (cfg.zaru_sigma ** 2,) * 3
    if update(st, hs, ys, rs, cfg):
        # the bias correction leaves the samples from now on: the smoothed rate follows
        st.wsx = st.wsy = st.wsz = 0.0


# --------------------------------------------------------------------------------------------- the benchmark method
def _samples(run, kcfg: KernelConfig):
    body = remap_axes(run.counts, kcfg.axis_map)
    return (body[:, :3] * kcfg.accel_ms2_per_lsb).tolist(), body[:, 3:].tolist()


def _pass(run, cfg: EskfConfig):
    """The device's stream over the whole run with every fix. Returns (t, dts, acc, gyr, snapshots: fix index ->
    (sample index, state after the fix), kcfg)."""
    kcfg = KernelConfig.from_board(run.board)
    t = run.t_us * 1e-6
    dts = (np.diff(run.t_us) * 1e-6).tolist()
    acc, gyr = _samples(run, kcfg)
    n_cal = int(np.searchsorted(t, run.board.algorithm.calibration_s))
    st = EskfState()
    calibrate(st, run.counts[:n_cal], kcfg)
    gps = run.gps
    vel = gps.device_velocity()
    snaps = {}
    k = n_cal
    spanning = calibration_fix(gps, float(t[0]), float(t[n_cal]))
    if spanning is not None:
        calibration_interval(st, vel[spanning], float(t[n_cal] - gps.t[spanning]))
    for j in np.flatnonzero(gps.valid & (gps.t >= t[n_cal])):
        stop = min(int(np.searchsorted(t, gps.t[j], side="left")), len(dts))
        if stop > k:
            mechanise(st, acc[k:stop], gyr[k:stop], dts[k:stop], kcfg, cfg)
            k = stop
        fix = gps.enu[j]
        if st.aligned:
            gps_update(st, float(gps.t[j]), fix, vel[j], cfg)
        else:
            align(st, float(gps.t[j]), fix, vel[j], cfg)
        snaps[int(j)] = (k, st.copy())
    return t, dts, acc, gyr, snaps, kcfg


def estimate(run, starts, times, cfg: EskfConfig | None = None):
    """The registry's method contract (codegen.sim.methods): positions at `times` for outages from `starts`, using
    only the fixes before each start (the state right after the last of them)."""
    cfg = EskfConfig() if cfg is None else cfg
    key = ("eskf_pass", cfg)
    if key not in run.cache:
        run.cache[key] = _pass(run, cfg)
    t, dts, acc, gyr, snaps, kcfg = run.cache[key]
    idx = run.gps.last_valid_before(starts)
    vel = run.gps.device_velocity()
    out = np.empty(times.shape + (2,))
    for i, j in enumerate(idx):
        k, snap = snaps[int(j)]
        if not snap.aligned:  # the filter has not started: the last fix along its velocity
            out[i] = run.gps.enu[j, :2] + vel[j] * (times[i] - run.gps.t[j])[:, None]
            continue
        st = snap.copy()
        st.gps_speed = 0.0
        ends = np.searchsorted(t, times[i], side="right") - 1
        for h, end in enumerate(ends):
            end = min(int(end), len(dts))
            if end > k:
                mechanise(st, acc[k:end], gyr[k:end], dts[k:end], kcfg, cfg)
                k = end
            out[i, h] = (st.pe, st.pn)
    return out
