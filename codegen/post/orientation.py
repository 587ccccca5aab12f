"""Orientation of the sensor in East-North-Up from accelerations and GPS-Doppler velocities (method steps 4-6).

Per GPS interval k (epochs t_k, t_k+1):
    A_k  = (v_k+1 - v_k) / dt_k                  GPS acceleration, ENU
    a_k  = mean specific force over the interval, sensor frame (bias-corrected)
    model: R_k a_k = A_k + g z                   R_k turns sensor vectors into ENU vectors

One vector pair leaves the rotation about that vector free, so each interval is solved together with its neighbours
(`half_window` on each side). Within that window the device is taken to turn with the track: a neighbour's target
is turned back by the change of the track's yaw chi = atan2(v_N, v_E) (exact for a device fixed in a vehicle, close
for one carried facing forward). The angles are Euler ZYX: R = Rz(yaw) Ry(pitch) Rx(roll), yaw counter-clockwise
from East (a device facing along the track has yaw = pi/2 - COG).

Levenberg-Marquardt (scipy least_squares method='lm', MINPACK) finds the angles; Wahba's closed form
(Rotation.align_vectors) on the same weighted vectors cross-checks it. Orientation between intervals is Slerp.
A constant sensor-frame accelerometer bias and the mounting relative to the track are estimated first over the
whole run (`fit_mounting`), because a horizontal bias looks exactly like tilt inside any one window.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

from codegen.board.model import STANDARD_GRAVITY
from codegen.kernel.reference import integrate_zoh

UP = np.array([0.0, 0.0, 1.0])
ACCEL_MEAN_NOISE = 0.01  # m/s^2, 1-sigma floor for an interval's mean accelerometer vector

FLAG_YAW_HELD = "yaw-held"  # too little horizontal acceleration in the window: yaw carried over
FLAG_STATIONARY = "stationary"  # no usable track direction
FLAG_POOR_FIT = "poor-fit"  # vectors inconsistent with one rotation (device turning within the window, bad data)
FLAG_LM_WAHBA = "lm-wahba"  # LM and closed form disagree by more than the tolerance
FLAG_NO_IMU = "no-imu"  # interval without IMU samples
FLAG_GIMBAL = "gimbal"  # pitch within 5 deg of +-90: the rotation is fine, roll and yaw are not separable
GIMBAL_MARGIN = np.radians(5.0)
FLAG_GPS_GAP = "gps-gap"  # epochs missing: the interval is too long to stand for one orientation
GPS_GAP_FACTOR = 3.0  # an interval longer than this many typical intervals is a gap
CLIMB_UNKNOWN = 1.0  # m/s: the climb-rate sigma the readers give a log without a climb rate
GRADE_MIN_SPEED = 3.0  # m/s: faster than a walker: a vehicle, whose body pitches with the road's grade
GRADE_SMOOTHING_S = 5.0  # s, 1-sigma of the Gaussian the climb rate and speed are smoothed over before their ratio


@dataclass
class OrientationOptions:
    half_window: int = 10  # intervals on each side solved together
    min_horizontal_accel: float = 0.5  # m/s^2, RMS over the window; below it yaw is held
    min_speed: float = 0.5  # m/s, below it the track direction is not used
    lm_wahba_tolerance_deg: float = 0.1
    poor_fit_chi2: float = 9.0  # reduced chi-square above which an interval is flagged
    estimate_bias: bool = True
    bias_prior: float = 0.05 * STANDARD_GRAVITY  # m/s^2, 1-sigma prior of each bias component (MPU-6050: +-50 mg)
    bias_max_chi2: float = 2.0  # a mounting fit worse than this cannot separate bias from tilt: bias not estimated


def sample_edges(t: np.ndarray) -> np.ndarray:
    """(N+1,) edges of the span each sample stands for: halfway to its neighbours (a sample is the value at its
    time, so holding it from t_i to t_i+1 would lag the signal by half a sample)."""
    if len(t) == 1:
        return np.array([t[0] - 0.5e-3, t[0] + 0.5e-3])
    mid = 0.5 * (t[1:] + t[:-1])
    return np.concatenate([[t[0] - (mid[0] - t[0])], mid, [t[-1] + (t[-1] - mid[-1])]])


def cumulative_integral(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge times (N+1,) and the zero-order-hold integral of x (each sample held over its span) at the edges."""
    edges = sample_edges(t)
    vel, _ = integrate_zoh(x, np.diff(edges), np.zeros(3))
    return edges, vel


def interval_means(nodes: np.ndarray, cum: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Mean of the held signal over [t0, t1] for each interval (exact for zero-order hold)."""
    c0 = np.stack([np.interp(t0, nodes, cum[:, i]) for i in range(3)], axis=1)
    c1 = np.stack([np.interp(t1, nodes, cum[:, i]) for i in range(3)], axis=1)
    return (c1 - c0) / (t1 - t0)[:, None]


@dataclass
class Intervals:
    t0: np.ndarray
    t1: np.ndarray
    gps_accel: np.ndarray  # (K,3) ENU m/s^2
    sigma: np.ndarray  # (K,) m/s^2, 1-sigma per component of (A - R a)
    acc_mean: np.ndarray  # (K,3) sensor frame m/s^2 (not bias corrected)
    track_yaw: np.ndarray  # (K,) rad, carried over where slow
    moving: np.ndarray  # (K,) bool, speed >= min_speed
    usable: np.ndarray  # (K,) bool, IMU covers the interval
    track: "Track" = None
    gap: np.ndarray = None  # (K,) bool, a GPS gap (not usable)
    grade: np.ndarray = None  # (K,) rad, the track's climb angle where a vehicle follows it (track_grade), else 0

    @property
    def mid(self) -> np.ndarray:
        return 0.5 * (self.t0 + self.t1)

    def __len__(self) -> int:
        return len(self.t0)


class Track:
    """The track's yaw chi(t) = atan2(v_N, v_E) from a cubic spline through the GPS velocities, unwrapped, and held at
    its last value while slower than `min_speed` (a standing device has no track direction)."""

    def __init__(self, gps_t: np.ndarray, gps_vel: np.ndarray, min_speed: float):
        # one spline per stretch without gaps: a spline bridging a gap swings, and spoils the epochs next to it
        step = np.diff(gps_t)
        breaks = np.flatnonzero(step > GPS_GAP_FACTOR * np.median(step)) + 1 if len(step) else np.array([], int)
        self.starts = np.concatenate([[0], breaks])
        self.ends = np.concatenate([breaks, [len(gps_t)]])
        self.pieces = []
        for a, b in zip(self.starts, self.ends):
            t, v = gps_t[a:b], gps_vel[a:b, :2]
            if len(t) >= 3:
                self.pieces.append((t[0], t[-1], CubicSpline(t, v, bc_type="natural")))
            else:
                self.pieces.append((t[0], t[-1], (t, v)))
        self.piece_start = gps_t[self.starts]
        self.min_speed = min_speed

    def velocity(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        which = np.clip(np.searchsorted(self.piece_start, t, side="right") - 1, 0, len(self.pieces) - 1)
        out = np.empty((len(t), 2))
        for i in np.unique(which):
            sel = which == i
            t0, t1, f = self.pieces[i]
            tt = np.clip(t[sel], t0, t1)
            if callable(f):
                out[sel] = f(tt)
            else:
                ts, vs = f
                out[sel] = np.stack([np.interp(tt, ts, vs[:, 0]), np.interp(tt, ts, vs[:, 1])], axis=1)
        return out

    def yaw(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """chi(t) (rad, unwrapped, held where slow) and the moving mask, for increasing t."""
        v = self.velocity(t)
        speed = np.hypot(v[:, 0], v[:, 1])
        moving = speed >= self.min_speed
        raw = np.arctan2(v[:, 1], v[:, 0])
        if not moving.any():
            return np.zeros_like(raw), moving
        index = np.where(moving, np.arange(len(raw)), 0)
        np.maximum.accumulate(index, out=index)
        index[: np.argmax(moving)] = np.argmax(moving)
        held = raw[index]
        return np.unwrap(held), moving


def track_grade(gps_t: np.ndarray, gps_vel: np.ndarray, gps_sigma_vel: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The track's climb angle (rad) at the times `at`: atan2(climb rate, speed), both smoothed over
    GRADE_SMOOTHING_S first (a road's grade changes over hundreds of metres; one epoch's GPS climb rate, from
    altitude differences, is off by ~0.5 m/s). Only where faster than GRADE_MIN_SPEED: a vehicle's body pitches
    with the road, a walker's hand does not follow the path's slope. 0 where the log has no climb rate (its sigma
    is CLIMB_UNKNOWN or more)."""
    known = (gps_sigma_vel[:, 2] < CLIMB_UNKNOWN).astype(float)
    if len(gps_t) < 2 or not known.any():
        return np.zeros(len(at))
    width = GRADE_SMOOTHING_S / float(np.median(np.diff(gps_t)))  # epochs
    weight = gaussian_filter1d(known, width, mode="nearest")
    climb = gaussian_filter1d(known * gps_vel[:, 2], width, mode="nearest") / np.maximum(weight, 1e-12)
    speed = gaussian_filter1d(np.hypot(gps_vel[:, 0], gps_vel[:, 1]), width, mode="nearest")
    grade = np.where((speed >= GRADE_MIN_SPEED) & (weight > 1e-6), np.arctan2(climb, np.maximum(speed, 1e-9)), 0.0)
    return np.interp(at, gps_t, grade)


def rot_grade(grade: np.ndarray) -> np.ndarray:
    """(K, 3, 3): the track frame (x along the horizontal track, z up) pitched nose up by `grade` rad."""
    c, s = np.cos(grade), np.sin(grade)
    z, o = np.zeros_like(grade), np.ones_like(grade)
    return np.stack([np.stack([c, z, -s], -1), np.stack([z, o, z], -1), np.stack([s, z, c], -1)], -2)


def build_intervals(imu_t, acc, gps_t, gps_vel, gps_sigma_vel, min_speed: float) -> Intervals:
    t0, t1 = gps_t[:-1], gps_t[1:]
    dt = t1 - t0
    gps_accel = np.diff(gps_vel, axis=0) / dt[:, None]
    # one weight per interval, from the horizontal velocities: the angles are fixed by the horizontal residuals (a
    # tilt lets g into them), and a log without a climb rate (NMEA, GPX) would otherwise drown them in its vertical
    # sigma, leaving the bias to its prior
    sigma_a = np.sqrt(np.mean(gps_sigma_vel[:-1, :2] ** 2 + gps_sigma_vel[1:, :2] ** 2, axis=1)) / dt
    sigma = np.sqrt(sigma_a**2 + ACCEL_MEAN_NOISE**2)
    usable = (t0 >= imu_t[0]) & (t1 <= imu_t[-1])
    gap = dt > GPS_GAP_FACTOR * np.median(dt)
    usable &= ~gap
    nodes, cum = cumulative_integral(imu_t, acc)
    acc_mean = interval_means(nodes, cum, t0, t1)
    track = Track(gps_t, gps_vel, min_speed)
    chi, moving = track.yaw(0.5 * (t0 + t1))
    grade = track_grade(gps_t, gps_vel, gps_sigma_vel, 0.5 * (t0 + t1))
    return Intervals(t0, t1, gps_accel, sigma, acc_mean, chi, moving, usable, track, gap, grade)


def turn_compensated_means(iv: Intervals, imu_t: np.ndarray, acc: np.ndarray, up_sensor: np.ndarray) -> np.ndarray:
    """Interval means of the sensor vectors turned back to the orientation at the interval's midpoint.

    A device that turns with the track by dchi(t) = chi(t) - chi_k during interval k has R(t) = Rz(dchi) R_k
    = R_k Rot(u, dchi) with u = R_k^T z, the up axis in the sensor frame; so R_k mean(Rot(u, dchi) s) = A_k + g z
    holds exactly where R_k mean(s) = A_k + g z only holds for a straight track. up_sensor: (K,3) u per interval.
    """
    k_of = np.clip(np.searchsorted(iv.t1, imu_t, side="right"), 0, len(iv) - 1)
    chi_t, _ = iv.track.yaw(imu_t)
    d = wrap(chi_t - iv.track_yaw[k_of])
    u = up_sensor[k_of]
    c, s_ = np.cos(d)[:, None], np.sin(d)[:, None]
    turned = acc * c + np.cross(u, acc) * s_ + u * np.sum(u * acc, axis=1, keepdims=True) * (1.0 - c)
    nodes, cum = cumulative_integral(imu_t, turned)
    return interval_means(nodes, cum, iv.t0, iv.t1)


def euler_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): sensor -> ENU."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def rot_z(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(np.shape(angle) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def euler_jacobian(roll: float, pitch: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """R and its derivatives dR/droll, dR/dpitch, dR/dyaw stacked as (3,3,3)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    drx = np.array([[0.0, 0.0, 0.0], [0.0, -sr, -cr], [0.0, cr, -sr]])
    dry = np.array([[-sp, 0.0, cp], [0.0, 0.0, 0.0], [-cp, 0.0, -sp]])
    drz = np.array([[-sy, -cy, 0.0], [cy, -sy, 0.0], [0.0, 0.0, 0.0]])
    ryx = ry @ rx
    return rz @ ryx, np.stack([rz @ ry @ drx, rz @ dry @ rx, drz @ ryx])


def _window_problem(sj: np.ndarray, tj: np.ndarray, wj: np.ndarray, yaw_fixed: Optional[float]):
    """Residual and Jacobian functions of ||R(roll, pitch, yaw) s_j - t_j|| w_j for least_squares."""
    w = wj[:, None]

    def angles(p):
        return (p[0], p[1], yaw_fixed) if yaw_fixed is not None else (p[0], p[1], p[2])

    def residual(p):
        return (((euler_matrix(*angles(p)) @ sj.T).T - tj) * w).ravel()

    def jacobian(p):
        _, d = euler_jacobian(*angles(p))
        cols = np.einsum("mij,kj->kim", d, sj) * w[:, :, None]  # (k, 3, 3 params)
        cols = cols.reshape(-1, 3)
        return cols[:, :2] if yaw_fixed is not None else cols

    return residual, jacobian


def parameter_sigma(jac: np.ndarray, chi2: float) -> np.ndarray:
    """1-sigma of least-squares parameters from the Jacobian at the solution (scaled by the fit's reduced chi-square
    when it is above 1). A parameter the data do not fix (a singular or numerically indefinite normal matrix: its
    inverse has a diagonal that is not positive) has an infinite 1-sigma: it is unknown, not known to be 0."""
    n = jac.shape[1]
    try:
        cov = np.linalg.inv(jac.T @ jac) * max(chi2, 1.0)
    except np.linalg.LinAlgError:
        return np.full(n, np.inf)
    diag = np.diag(cov)
    good = np.isfinite(diag) & (diag > 0)
    return np.where(good, np.sqrt(np.where(good, diag, 1.0)), np.inf)


def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------------------------------------ whole-run mounting

@dataclass
class Mounting:
    euler: np.ndarray  # (3,) roll, pitch, yaw-relative-to-track, rad
    bias: np.ndarray  # (3,) sensor-frame accelerometer bias, m/s^2
    sigma_euler: np.ndarray
    sigma_bias: np.ndarray
    chi2: float  # reduced chi-square of the fit (1 when the device is rigidly mounted and sigmas are right)
    used: int
    bias_rejected: bool = False  # a bias was sought but the fit was too poor to trust it (bias set to zero)


def fit_mounting(iv: Intervals, estimate_bias: bool = True, bias_prior: float = 0.05 * STANDARD_GRAVITY,
                 bias_max_chi2: float = float("inf")) -> Optional[Mounting]:
    """Mounting M relative to the vehicle and bias b: Rz(chi_k) Ry(grade_k) M (a_k - b) = A_k + g z over all moving
    intervals, the vehicle frame following the track's direction and, at a vehicle's speeds, its grade (a car
    pitches with the road; a level track frame leaves the grade in the misfit).

    The bias has a zero-mean prior of `bias_prior` per component: where the motion cannot tell a bias from a tilt
    (no turns) it stays near zero instead of soaking up the misfit. The bias is only observable through the rigid
    mounting; when that model fits worse than `bias_max_chi2` the bias is not estimated at all (set to zero)."""
    sel = iv.usable & iv.moving
    if sel.sum() < 6:
        return None
    a, target, chi = iv.acc_mean[sel], iv.gps_accel[sel] + STANDARD_GRAVITY * UP, iv.track_yaw[sel]
    w = 1.0 / iv.sigma[sel]
    rz = rot_z(chi)
    if iv.grade is not None:
        rz = rz @ rot_grade(iv.grade[sel])

    def residual(p):
        m = euler_matrix(*p[:3])
        b = p[3:] if estimate_bias else np.zeros(3)
        pred = np.einsum("kij,jl,kl->ki", rz, m, a - b)
        fit = ((pred - target) * w[:, None]).ravel()
        return np.concatenate([fit, b / bias_prior]) if estimate_bias else fit

    # start from the tilt of the mean vector, yaw 0 (facing along the track)
    mean_a = a.mean(axis=0)
    roll0 = np.arctan2(mean_a[1], mean_a[2])
    pitch0 = np.arctan2(-mean_a[0], np.hypot(mean_a[1], mean_a[2]))
    best = None
    for yaw0 in np.radians([0.0, 90.0, 180.0, -90.0]):
        p0 = np.array([roll0, pitch0, yaw0] + ([0.0, 0.0, 0.0] if estimate_bias else []))
        res = least_squares(residual, p0, method="lm", x_scale=1.0)
        if best is None or res.cost < best.cost:
            best = res
    n = best.x.size
    dof = max(best.fun.size - n, 1)
    chi2 = 2 * best.cost / dof
    sig = parameter_sigma(best.jac, chi2)
    if estimate_bias and chi2 > bias_max_chi2:
        fixed = fit_mounting(iv, False)
        fixed.bias_rejected = True
        return fixed
    euler = np.array([wrap(best.x[0]), wrap(best.x[1]), wrap(best.x[2])])
    bias = best.x[3:] if estimate_bias else np.zeros(3)
    return Mounting(euler, bias, sig[:3], sig[3:] if estimate_bias else np.zeros(3), chi2, int(sel.sum()))


# ------------------------------------------------------------------------------------------- per interval

@dataclass
class OrientationResult:
    t: np.ndarray  # (K,) interval midpoints, s
    euler: np.ndarray  # (K,3) roll, pitch, yaw, rad (NaN where unusable)
    sigma: np.ndarray  # (K,3) 1-sigma, rad (NaN where held)
    flags: list[list[str]]
    lm_vs_wahba_deg: np.ndarray  # (K,)
    horizontal_accel: np.ndarray  # (K,) |A_h| of the interval, m/s^2
    window_horizontal_accel: np.ndarray  # (K,) RMS |A_h| over the window
    chi2: np.ndarray  # (K,)
    mounting: Optional[Mounting]
    bias: np.ndarray  # (3,) sensor-frame bias removed before solving, m/s^2
    valid: np.ndarray = field(default=None)  # (K,) bool

    def rotations(self) -> Rotation:
        e = self.euler[self.valid]
        return Rotation.from_euler("ZYX", np.stack([e[:, 2], e[:, 1], e[:, 0]], axis=1))

    def slerp(self) -> Callable[[np.ndarray], Rotation]:
        times = self.t[self.valid]
        if len(times) == 1:
            rot = self.rotations()
            return lambda t: Rotation.concatenate([rot] * len(np.atleast_1d(t)))
        interp = Slerp(times, self.rotations())
        return lambda t: interp(np.clip(t, times[0], times[-1]))


def solve_orientations(iv: Intervals, options: OrientationOptions, bias: np.ndarray,
                       mounting: Optional[Mounting] = None, progress=None) -> OrientationResult:
    k_count = len(iv)
    a = iv.acc_mean - bias
    target = iv.gps_accel + STANDARD_GRAVITY * UP
    weight = 1.0 / iv.sigma
    horiz = np.hypot(iv.gps_accel[:, 0], iv.gps_accel[:, 1])
    euler = np.full((k_count, 3), np.nan)
    sigma = np.full((k_count, 3), np.nan)
    flags: list[list[str]] = [[] for _ in range(k_count)]
    lm_wahba = np.full(k_count, np.nan)
    window_h = np.full(k_count, np.nan)
    chi2s = np.full(k_count, np.nan)
    prev = None  # (roll, pitch, yaw, track_yaw) of the last solved interval
    usable_idx = np.flatnonzero(iv.usable)
    h = options.half_window
    segment = np.cumsum(iv.gap) if iv.gap is not None else np.zeros(k_count, dtype=int)  # windows stop at gaps
    for count, k in enumerate(usable_idx):
        if progress and count % max(1, len(usable_idx) // 10) == 0:
            progress("orientation", count / len(usable_idx))
        lo, hi = max(0, k - h), min(k_count, k + h + 1)
        js = np.arange(lo, hi)
        js = js[iv.usable[js] & (segment[js] == segment[k])]
        turn = iv.track_yaw[js] - iv.track_yaw[k]
        tj = np.einsum("kij,kj->ki", rot_z(-turn), target[js])  # targets in the track frame of interval k
        sj, wj = a[js], weight[js]
        window_h[k] = float(np.sqrt(np.mean(np.sum(tj[:, :2] ** 2, axis=1))))
        if prev is not None:
            init = np.array([prev[0], prev[1], prev[2] + (iv.track_yaw[k] - prev[3])])
        else:
            base = mounting.euler if mounting is not None else np.zeros(3)
            init = np.array([base[0], base[1], iv.track_yaw[k] + base[2]])
        hold_yaw = window_h[k] < options.min_horizontal_accel and prev is not None
        if not iv.moving[k] and prev is not None:
            flags[k].append(FLAG_STATIONARY)
        if hold_yaw:
            flags[k].append(FLAG_YAW_HELD)
            yaw_fixed = init[2]
            residual, jacobian = _window_problem(sj, tj, wj, yaw_fixed)
            res = least_squares(residual, init[:2], jac=jacobian, method="lm")
            solution = np.array([res.x[0], res.x[1], yaw_fixed])
        else:
            residual, jacobian = _window_problem(sj, tj, wj, None)
            res = least_squares(residual, init, jac=jacobian, method="lm")
            solution = res.x
        n = res.x.size
        dof = max(res.fun.size - n, 1)
        chi2 = 2 * res.cost / dof
        chi2s[k] = chi2
        sigma[k, :n] = parameter_sigma(res.jac, chi2)
        if chi2 > options.poor_fit_chi2:
            flags[k].append(FLAG_POOR_FIT)
        # closed-form cross-check on the same weighted vectors
        r_lm = Rotation.from_matrix(euler_matrix(*solution))
        with warnings.catch_warnings():  # nearly parallel vectors (standing still) are expected: yaw is held there
            warnings.simplefilter("ignore", UserWarning)
            r_w, _ = Rotation.align_vectors(tj, sj, weights=wj**2)
        if hold_yaw:
            up_lm, up_w = r_lm.inv().apply(UP), r_w.inv().apply(UP)
            lm_wahba[k] = np.degrees(np.arccos(np.clip(up_lm @ up_w, -1.0, 1.0)))
        else:
            lm_wahba[k] = np.degrees((r_lm * r_w.inv()).magnitude())
        if lm_wahba[k] > options.lm_wahba_tolerance_deg:
            flags[k].append(FLAG_LM_WAHBA)
        if abs(abs(wrap(solution[1])) - np.pi / 2) < GIMBAL_MARGIN:
            flags[k].append(FLAG_GIMBAL)
        euler[k] = [wrap(solution[0]), wrap(solution[1]), solution[2]]
        prev = (solution[0], solution[1], solution[2], iv.track_yaw[k])
    for k in np.flatnonzero(~iv.usable):
        flags[k].append(FLAG_GPS_GAP if iv.gap is not None and iv.gap[k] else FLAG_NO_IMU)
    valid = np.isfinite(euler[:, 0])
    euler[valid, 2] = wrap(euler[valid, 2])
    if progress:
        progress("orientation", 1.0)
    return OrientationResult(iv.mid, euler, sigma, flags, lm_wahba, horiz, window_h, chi2s, mounting,
                             np.asarray(bias, dtype=float), valid)
