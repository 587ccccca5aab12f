"""The fused real-time algorithm (`algorithm: fused`): the executable specification, float64.

Per sample (`process`, the named steps of PER_SAMPLE_STEPS in their order): tilt corrected towards gravity, motion
statistics (rest, walking, a vehicle's vibration), a travel direction turned by the gyro (a walker's slow swings held
back) and a speed along it (a walker's learned speed, a vehicle's integrated acceleration with its zero-velocity
updates and, in an outage, its lateral update: no sideways sliding, so a turn's centripetal acceleration shows the
speed error), the position in true ENU; at rest, every rest_update_s, the gyro bias and the tilt/offset filter
(`rest_update`). At each GPS fix (`position_update`, then `gps_update`): the fix smoothed with the Doppler and the
IMU, the heading alignment of the kernel frame to North, the travel direction, the speed, the along-track bias, the
walking speed, and a 5-state Kalman filter of the tilt and the accelerometer's offsets (`tilt_and_offset_update`).
docs/fused.md gives the equations and how the defaults were tuned; native_ext/dr_fused.c (static inline
dr_fused_<step>) and the fallback's fused_process (blocks labelled `step: <step>`) are the same steps, in the same
order, in float32.

The state is a flat vector of floats and the parameters a FusedConfig, both from the declaration
(codegen/kernel/layout.py) that also lays out the C kernel's caller-owned buffer and the fallback's offsets: FusedState
names its fields, STATE_FIELDS lists them in memory order.
"""

from __future__ import annotations

import math
from dataclasses import field, make_dataclass

import numpy as np

from codegen.kernel.layout import COVARIANCE_FILTERS, FILTER_STEPS, FUSED, FUSED_MEDIAN_MAX
from codegen.kernel.reference import (
    STANDARD_GRAVITY,
    KernelConfig,
    quat_to_matrix,
    remap_axes,
    tilt_from_gravity,
)

AT_REST, WALKING, TURNING, VEHICLE, SHAKEN, FAST, WALKED, DROVE = (
    next(f.value for f in FUSED.flags if f.name == name)
    for name in ("AT_REST", "WALKING", "TURNING", "VEHICLE", "SHAKEN", "FAST", "WALKED", "DROVE"))
PLATFORM_PEDESTRIAN, PLATFORM_VEHICLE = (FUSED.param("platform").code(name) for name in ("pedestrian", "vehicle"))
FILTER_TILT, FILTER_LATERAL, FILTER_POSITION, FILTER_SPEED = (
    COVARIANCE_FILTERS.index(n) for n in ("TILT", "LATERAL", "POSITION", "SPEED"))
STEP_START, STEP_PREDICT, STEP_UPDATE = (FILTER_STEPS.index(n) for n in ("START", "PREDICT", "UPDATE"))
COV_MAX = 1e30  # a covariance entry beyond this in magnitude (or not a number) is broken (float32 ends at 3.4e38)
SPEED_UNKNOWN_VAR = 1e4  # (m/s)^2: the speed's variance after a calibration that moved (a speed nobody measured)


def _from_board(cls, board) -> "FusedConfig":
    """The board's algorithm.fused_* values."""
    return cls(**{p.name: p.number(getattr(board.algorithm, FUSED.board_key(p))) for p in FUSED.params})


FusedConfig = make_dataclass(
    "FusedConfig",
    [(p.name, float, field(default=p.number(p.default))) for p in FUSED.params],
    frozen=True,
    namespace={
        "__doc__": "The fused method's parameters in their declared units (codegen/kernel/layout.py: board "
        "`algorithm.fused_<name>`, the C dr_fused_config_set's array in this order); a bool option is 1.0 or 0.0.",
        "from_board": classmethod(_from_board),
    },
)
FusedConfig.__module__ = __name__

# The state vector: every value's name in memory order (the C struct dr_fused_state, the fallback's offsets).
STATE_FIELDS = FUSED.element_names()
IDX = FUSED.element_offsets()
STATE_LEN = len(STATE_FIELDS)
OUT_LEN = 6
_INITIAL = {f.element_names()[i]: x for f, i, x in FUSED.initial_values()}


class FusedState:
    """The fused state as named floats (float64 here; float32 in the C kernel and the fallback)."""

    __slots__ = STATE_FIELDS

    def __init__(self):
        for name in STATE_FIELDS:
            setattr(self, name, _INITIAL.get(name, 0.0))

    def copy(self) -> "FusedState":
        other = FusedState.__new__(FusedState)
        for name in STATE_FIELDS:
            setattr(other, name, getattr(self, name))
        return other

    def vector(self) -> np.ndarray:
        return np.array([getattr(self, name) for name in STATE_FIELDS])


def calibrate(st: FusedState, samples, kcfg: KernelConfig) -> bool:
    """As the seed's calibration (tilt from the mean specific force, yaw 0; gyro bias = mean counts), and the
    motion statistics started at rest. Returns True when the device moved (kernel threshold)."""
    body = remap_axes(samples, kcfg.axis_map)
    mean = body.mean(axis=0)
    q = tilt_from_gravity(mean[:3])
    st.qw, st.qx, st.qy, st.qz = (float(v) for v in q)
    st.bgx, st.bgy, st.bgz = (float(v) for v in mean[3:])
    st.mean_f = float(np.linalg.norm(mean[:3])) * kcfg.accel_ms2_per_lsb
    st.var_f = 0.0
    st.vib_var = st.vib_tot = 0.0
    st.vib_lp1 = st.mean_f
    st.vib_lp2 = 0.0
    st.wsx = st.wsy = st.wsz = 0.0
    st.rest_s = 0.0
    st.speed = 0.0
    st.bax = st.bay = st.baz = 0.0
    std_g = body[:, :3].std(axis=0) / kcfg.accel_lsb_per_g
    moved = bool(np.any(std_g > kcfg.motion_threshold_g))
    # the speed is 0 if the device stood still; after a calibration that moved (a car calibrated while it drives)
    # it is not known, so the first fix must not take the whole speed it finds for an along-track bias, and the
    # gyro bias took the motion's mean rate: the tilt drifts until a rest
    st.sb_pss = SPEED_UNKNOWN_VAR if moved else 0.0
    st.sb_psb = st.sb_pbb = st.sk_t = 0.0
    st.keep_v = -1.0
    st.cal_moved = 1.0 if moved else 0.0
    return moved


def keep(st: FusedState) -> list[float]:
    """What a reset should not lose (codegen/kernel/layout.py's FUSED.kept, in its order): the attitude, the gyro's
    bias, the accelerometer's offsets and their block of the tilt/offset filter's covariance, the along-track bias
    and its variance, the walking speed. The app keeps them where a reset leaves them (the ESP32's RTC memory)."""
    return [float(getattr(st, name)) for name in FUSED.kept]


def restore(st: FusedState, kept, fcfg: FusedConfig) -> None:
    """After a calibration that moved (a board reset on the road): takes up what `keep` gave before the reset. The
    tilt/offset filter's tilt part starts again from the attitude (the board may have tilted while it was reset):
    the leak's block as the prior's, var R_h R_h^T, uncorrelated with the offsets it keeps. The calibration counts
    as a rest's (cal_moved 0); the speed stays unknown until the next fix."""
    for name, value in zip(FUSED.kept, kept):
        setattr(st, name, float(value))
    st.cal_moved = 0.0
    if st.p22 > 0.0:  # else the filter had not started: it starts at its first use
        var = (fcfg.kf_bias_init_g * STANDARD_GRAVITY) ** 2
        rows = quat_to_matrix(np.array([st.qw, st.qx, st.qy, st.qz]))[:2]
        st.p00, st.p01, st.p11 = (float(var * rows[i] @ rows[j]) for i, j in ((0, 0), (0, 1), (1, 1)))
        st.p02 = st.p03 = st.p04 = st.p12 = st.p13 = st.p14 = 0.0
        st.kf_t = st.turn = 0.0
        _covariance_checked(st, FILTER_TILT, STEP_START, fcfg)
    _covariance_checked(st, FILTER_SPEED, STEP_START, fcfg)


# The per-sample loop, as named steps in the order `process` calls them (docs/fused.md "Per sample"; dr_fused.c's
# static inline dr_fused_<step> and the fallback's labelled blocks `# step: <name>` are the same steps, same order).
PER_SAMPLE_STEPS = ("sample_in", "motion_statistics", "horizontal_force", "rest", "platform", "travel_direction",
                    "speed", "lateral_update", "fix_integrals", "advance_position", "tilt_correction",
                    "rest_update_due")


class _Loop:
    """What the per-sample steps share within one `process` call: the parameters in the form the loop reads, the
    platform's decisions carried from sample to sample (the flags), and the current sample's values."""

    __slots__ = (
        # the parameters in the loop's form
        "fcfg", "g", "gscale", "kp", "reject", "kp_dark", "deadband", "rest_var", "still_var", "idle_var",
        "inv_stand", "rest_w2", "walk_var", "vib_rate", "inv_vib", "platform", "inv_stat", "inv_speed", "inv_acc",
        "inv_ramp", "nhc_r", "median", "ring", "hold_rate", "turn_start", "turn_end",
        # the decisions carried between samples
        "was_walking", "vehicle", "driven", "fast", "walked", "drove", "turning",
        # this sample: its interval, specific force and rate, their statistics, R(q)'s rows, the horizontal force
        "dt", "fx", "fy", "fz", "wx", "wy", "wz", "nf", "d", "alpha", "shaken", "broadband",
        "r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22", "ae", "an", "rest", "walking", "r",
        # the speed the position moves by (a vehicle's: its integrated speed weighed against the one it keeps)
        "sp")

    def __init__(self, st: FusedState, kcfg: KernelConfig, fcfg: FusedConfig):
        g = STANDARD_GRAVITY
        self.fcfg = fcfg
        self.g = g
        self.gscale = kcfg.gyro_rads_per_lsb
        self.kp = 1.0 / fcfg.tilt_tau_s
        self.reject = fcfg.accel_reject_g * g
        self.kp_dark = 1.0 / fcfg.tilt_tau_dark_s if fcfg.tilt_tau_dark_s > 0.0 else 0.0
        self.deadband = kcfg.deadband_ms2
        self.rest_var = (fcfg.rest_accel_g * g) ** 2
        self.still_var = (fcfg.still_accel_g * g) ** 2
        self.idle_var = (fcfg.idle_accel_g * g) ** 2
        self.inv_stand = 1.0 / fcfg.stand_tau_s if fcfg.stand_tau_s > 0.0 else 0.0
        self.rest_w2 = math.radians(fcfg.rest_gyro_dps) ** 2
        self.walk_var = (fcfg.walk_accel_g * g) ** 2
        self.vib_rate = fcfg.vibration_hz * 2.0 * math.pi
        self.inv_vib = 1.0 / fcfg.vibration_tau_s
        self.platform = int(fcfg.platform)
        self.inv_stat = 1.0 / fcfg.stat_tau_s
        self.inv_speed = 1.0 / fcfg.speed_tau_s if fcfg.speed_tau_s > 0.0 else 0.0
        self.inv_acc = 1.0 / fcfg.accel_tau_s if fcfg.accel_tau_s > 0.0 else 0.0
        self.inv_ramp = 1.0 / fcfg.deadband_ramp_s if fcfg.deadband_ramp_s > 0.0 else 0.0
        self.nhc_r = fcfg.nhc_sigma_ms2 * fcfg.nhc_sigma_ms2  # the lateral residual's variance, averaged over 1 s
        self.median = kcfg.block if fcfg.median > 0.0 and kcfg.block > 1 else 0
        if self.median > FUSED_MEDIAN_MAX:
            raise ValueError(f"the median option takes algorithm.block <= {FUSED_MEDIAN_MAX}, not {self.median}")
        self.ring = [getattr(st, f"med{k}") for k in range(FUSED_MEDIAN_MAX)]
        self.hold_rate = 1.0 / fcfg.turn_hold_tau_s if fcfg.turn_hold_tau_s > 0.0 else 0.0
        self.turn_start = math.radians(fcfg.turn_start_dps)
        self.turn_end = math.radians(fcfg.turn_end_dps)
        flags = int(st.flags)
        self.was_walking = bool(flags & WALKING)
        self.vehicle = self.platform == PLATFORM_VEHICLE or bool(flags & VEHICLE)
        self.driven = bool(flags & SHAKEN)
        self.fast = bool(flags & FAST) and self.platform != PLATFORM_PEDESTRIAN
        self.walked = bool(flags & WALKED)
        self.drove = bool(flags & DROVE) and self.platform != PLATFORM_PEDESTRIAN
        self.turning = bool(flags & TURNING)
        self.sp = st.speed

    def flags(self) -> int:
        """The sample's flags (AT_REST | WALKING | ...), as the state keeps the last one's."""
        return ((AT_REST if self.rest else 0) | (WALKING if self.walking else 0) | (TURNING if self.turning else 0)
                | (VEHICLE if self.vehicle else 0) | (SHAKEN if self.driven else 0) | (FAST if self.fast else 0)
                | (WALKED if self.walked else 0) | (DROVE if self.drove else 0))


def process(st: FusedState, samples, dt_us, kcfg: KernelConfig, fcfg: FusedConfig):
    """The per-sample steps (PER_SAMPLE_STEPS) over raw samples (m, 6) held dt_us[k] us each. Returns (out (6,),
    flags (m,)): out = the displacement East, North, Up over the samples (true ENU m, Up 0) and the velocity E, N, U
    at their end."""
    body = remap_axes(samples, kcfg.axis_map)
    acc = (body[:, :3] * kcfg.accel_ms2_per_lsb).tolist()
    gyr = body[:, 3:].tolist()
    dts = (np.asarray(dt_us, dtype=np.float64) * 1e-6).tolist()
    lp = _Loop(st, kcfg, fcfg)
    flags = np.zeros(len(dts), dtype=np.uint8)
    pe0, pn0 = st.pe, st.pn
    for k, dt in enumerate(dts):
        _sample_in(lp, st, acc[k], gyr[k], dt)
        _motion_statistics(lp, st)
        _horizontal_force(lp, st)
        _rest(lp, st)
        _platform(lp, st)
        _travel_direction(lp, st)
        flags[k] = lp.flags()
        _speed(lp, st)
        _lateral_update(lp, st)
        _fix_integrals(lp, st)
        _advance_position(lp, st)
        _tilt_correction(lp, st)
        _rest_update_due(lp, st)
    for k in range(FUSED_MEDIAN_MAX):
        setattr(st, f"med{k}", lp.ring[k])
    st.flags = float(flags[-1]) if len(flags) else st.flags
    ve = lp.sp * (st.cos_t * st.ux - st.sin_t * st.uy)
    vn = lp.sp * (st.sin_t * st.ux + st.cos_t * st.uy)
    out = np.array([st.pe - pe0, st.pn - pn0, 0.0, ve, vn, 0.0])
    return out, flags


def _sample_in(lp: _Loop, st: FusedState, f, c, dt: float) -> None:
    """The sample in the body frame: its specific force less the accelerometer's estimated offsets (m/s^2), its
    rate less the gyro bias (rad/s)."""
    lp.dt = dt
    fx, fy, fz = f
    lp.fx = fx - st.bax
    lp.fy = fy - st.bay
    lp.fz = fz - st.baz
    cx, cy, cz = c
    lp.wx = (cx - st.bgx) * lp.gscale
    lp.wy = (cy - st.bgy) * lp.gscale
    lp.wz = (cz - st.bgz) * lp.gscale


def _motion_statistics(lp: _Loop, st: FusedState) -> None:
    """The mean and variance of |f| over stat_tau_s; its shaking above the gait band (|f| through two first-order
    high-passes at vibration_hz: a walker's steps stay below it, a vehicle's road, wheels and engine reach far
    above) and the variance it is a share of, over vibration_tau_s; the body rate smoothed (an idling engine's shake
    averages out, a turn or a hand's motion does not). Sets shaken (beyond walk_accel_g) and broadband."""
    dt = lp.dt
    nf = math.sqrt(lp.fx * lp.fx + lp.fy * lp.fy + lp.fz * lp.fz)
    alpha = dt * lp.inv_stat
    if alpha > 1.0:
        alpha = 1.0
    st.mean_f += alpha * (nf - st.mean_f)
    d = nf - st.mean_f
    st.var_f += alpha * (d * d - st.var_f)
    beta = dt * lp.vib_rate
    if beta > 1.0:
        beta = 1.0
    st.vib_lp1 += beta * (nf - st.vib_lp1)
    h = nf - st.vib_lp1
    st.vib_lp2 += beta * (h - st.vib_lp2)
    h -= st.vib_lp2
    gamma = dt * lp.inv_vib
    if gamma > 1.0:
        gamma = 1.0
    st.vib_var += gamma * (h * h - st.vib_var)
    st.vib_tot += gamma * (d * d - st.vib_tot)
    st.wsx += alpha * (lp.wx - st.wsx)
    st.wsy += alpha * (lp.wy - st.wsy)
    st.wsz += alpha * (lp.wz - st.wsz)
    lp.nf, lp.d, lp.alpha = nf, d, alpha
    lp.shaken = st.var_f > lp.walk_var
    lp.broadband = st.vib_var > lp.fcfg.vibration_ratio * st.vib_tot


def _horizontal_force(lp: _Loop, st: FusedState) -> None:
    """R(q)'s rows (body -> kernel ENU) and the specific force's horizontal part a_h in the kernel frame, smoothed
    over stat_tau_s (rest asks it to be steady)."""
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    lp.r00 = r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    lp.r01 = r01 = 2.0 * (qx * qy - qw * qz)
    lp.r02 = r02 = 2.0 * (qx * qz + qw * qy)
    lp.r10 = r10 = 2.0 * (qx * qy + qw * qz)
    lp.r11 = r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    lp.r12 = r12 = 2.0 * (qy * qz - qw * qx)
    lp.r20 = 2.0 * (qx * qz - qw * qy)
    lp.r21 = 2.0 * (qy * qz + qw * qx)
    lp.r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    lp.ae = ae = r00 * lp.fx + r01 * lp.fy + r02 * lp.fz
    lp.an = an = r10 * lp.fx + r11 * lp.fy + r12 * lp.fz
    st.ah_e += lp.alpha * (ae - st.ah_e)
    st.ah_n += lp.alpha * (an - st.ah_n)


def _rest(lp: _Loop, st: FusedState) -> None:
    """Rest, decided before the steps (a device at rest is not stepping): still (|f| varies by less than
    rest_accel_g, or where more than the amplitude says rest by less than still_accel_g for a pedestrian's hand and
    idle_accel_g for a vehicle's idling engine: its shaking above the gait band, its speed below rest_speed_ms, as
    creeping traffic's is not), the smoothed rate below rest_gyro_dps, the horizontal force steady within the
    deadband of its average (a push, a start or a stop is no rest) and itself within it, unless a vehicle that shook
    since its last rest or is slower than rest_speed_ms (its tilt error in an outage) and the tilt/offset filter can
    take it for its error (_rest_explained: a smooth start from a stand is no rest), never while fixes arrive that
    say the device moves (a smooth cruise is no rest); all for rest_time_s."""
    fcfg = lp.fcfg
    ae, an = lp.ae, lp.an
    de, dn = ae - st.ah_e, an - st.ah_n
    ah2 = ae * ae + an * an
    deadband = lp.deadband
    gps_moving = st.since_fix < fcfg.gps_timeout_s and st.gps_ok > 0.0
    vehicle = lp.vehicle
    if vehicle:
        still = st.var_f < lp.rest_var or st.var_f < lp.idle_var and lp.broadband and st.speed < fcfg.rest_speed_ms
    else:
        still = st.var_f < lp.rest_var or st.var_f < lp.still_var
    if (still and st.wsx * st.wsx + st.wsy * st.wsy + st.wsz * st.wsz < lp.rest_w2
            and de * de + dn * dn < deadband * deadband
            and (ah2 < deadband * deadband
                 or vehicle and (lp.driven or st.speed < fcfg.rest_speed_ms) and _rest_explained(st, fcfg))
            and not gps_moving):
        st.rest_s += lp.dt
    else:
        st.rest_s = 0.0
    lp.rest = st.rest_s >= fcfg.rest_time_s


def _platform(lp: _Loop, st: FusedState) -> None:
    """Steps or a vehicle. Walking: shaken (the steps), by a pedestrian, not at rest, for walk_time_s (after a fast
    fix, vehicle_walk_time_s: a car creeping on in a queue shakes in the gait band for seconds); on auto only
    while the shaking stays in the gait band and nothing says a vehicle: a fix faster than people run since the
    last rest (fast), or the vehicle's own speed beyond that (a vehicle does not become a pedestrian without
    stopping). A vehicle: shaken far above the gait band unless it walked (a hand's tremor is broadband too: a
    pedestrian becomes a vehicle by a fast fix), a fast fix, or the platform says so; until the steps. When the
    steps stop, the walker has stopped: speed 0 (a vehicle he boards starts from 0 too)."""
    fcfg = lp.fcfg
    platform, shaken, broadband, rest = lp.platform, lp.shaken, lp.broadband, lp.rest
    steps = platform != PLATFORM_VEHICLE and shaken and not rest and (platform == PLATFORM_PEDESTRIAN or not (
        broadband or lp.fast or lp.vehicle and st.speed > fcfg.pedestrian_max_ms))
    st.walk_s = st.walk_s + lp.dt if steps else 0.0
    walk_time = fcfg.vehicle_walk_time_s if lp.drove else fcfg.walk_time_s
    walking = steps and (lp.was_walking or st.walk_s >= walk_time)
    if walking:
        lp.vehicle = lp.drove = False
        lp.walked = True
    elif lp.fast or shaken and broadband and platform != PLATFORM_PEDESTRIAN and not lp.walked:
        lp.vehicle = True  # a walker's hand tremor (8-12 Hz) is broadband too
    if lp.vehicle:
        lp.walked = False
    if rest:  # a walker's stop keeps him a pedestrian (walked): his hand's tremor is broadband, no engine
        lp.driven = lp.fast = False
    elif shaken and lp.vehicle:
        lp.driven = True
    if lp.was_walking and not walking:
        st.speed = 0.0
    lp.was_walking = lp.walking = walking


def _travel_direction(lp: _Loop, st: FusedState) -> None:
    """The travel direction u turned by the rate about Up r (the uncorrected gyro: the tilt correction is not a
    turn), to second order (a turn's held part can be tens of degrees). A walker's turns are quick and the hand's
    slow swings about the course are not turns: u takes a turn at once (with what it held), a slow rotation over
    turn_hold_tau_s (a swing that returns cancels)."""
    dt = lp.dt
    lp.r = r = lp.r20 * lp.wx + lp.r21 * lp.wy + lp.r22 * lp.wz
    st.turn += abs(r) * dt
    st.rate_up += lp.alpha * (r - st.rate_up)
    da = r * dt
    if lp.walking and lp.hold_rate > 0.0:
        if abs(st.rate_up) > lp.turn_start:
            lp.turning = True
        elif abs(st.rate_up) < lp.turn_end:
            lp.turning = False
        st.held += da
        da = st.held if lp.turning else st.held * min(1.0, dt * lp.hold_rate)
        st.held -= da
    else:
        lp.turning = False
        da += st.held
        st.held = 0.0
    cd = 1.0 - 0.5 * da * da
    sd = da * (1.0 - da * da * (1.0 / 6.0))
    ux = cd * st.ux - sd * st.uy
    uy = cd * st.uy + sd * st.ux
    inv = 1.0 / math.sqrt(ux * ux + uy * uy)
    st.ux = ux * inv
    st.uy = uy * inv


def _speed(lp: _Loop, st: FusedState) -> None:
    """The speed along u: at rest 0, after a vehicle's zero-velocity update of the position (the speed it still
    had, not floored at 0, is the error its along-track integration gathered since the last speed it knew, a fix or
    a rest; the position moved by that error's integral along the way it went, and by what the floor kept out: both
    taken back); walking the learned walking speed; a pedestrian whose steps stopped without a rest (the hand
    still moves) decays to 0 over stand_tau_s, never integrated (a standing hand's along-track acceleration less a
    bias is a drift: 29 m/s in 18 s on a real stand); a vehicle's integrated (_vehicle_speed) and, for its
    position, weighed against the speed it keeps (_kept_speed)."""
    rest, walking, walked = lp.rest, lp.walking, lp.walked
    if rest or walking or walked:
        st.med_i = st.med_n = 0.0  # the median ring restarts when the vehicle branch is entered again
        st.acc_lp = 0.0
    if rest:
        if st.zr_t > 0.0:
            k = st.zr_v / st.zr_t
            st.pe += st.zr_ce - k * st.zr_pe
            st.pn += st.zr_cn - k * st.zr_pn
        st.speed = 0.0
        st.zr_t = st.zr_pe = st.zr_pn = st.zr_ce = st.zr_cn = st.zr_v = st.zr_turn = 0.0
        # the speed known (0, exactly); a vehicle that stood starts again from 0, not from the speed it kept, and
        # the rest re-learns the gyro bias (rest_update)
        st.sb_pss = st.sb_psb = st.sk_t = st.sb_lost = st.cal_moved = 0.0
        st.keep_v = -1.0
    elif walking or walked:
        if walking:
            st.speed = st.walk_speed
        else:
            st.speed -= st.speed * min(1.0, lp.dt * lp.inv_stand)
        st.zr_t = st.zr_pe = st.zr_pn = st.zr_ce = st.zr_cn = st.zr_turn = 0.0
        st.zr_v = st.speed
    else:
        _vehicle_speed(lp, st)
        lp.sp = _kept_speed(st, lp.fcfg)
        return
    lp.sp = st.speed


def _vehicle_speed(lp: _Loop, st: FusedState) -> None:
    """A vehicle's speed: the along-track acceleration (the optional sliding median of the last b), less its bias
    and the folded offsets' leak (u0 - u) . f since the outage began, through the board's deadband on its average
    over accel_tau_s (the vehicle's acceleration, not the road's shaking; 0: on each sample), plus the optional pull
    towards the last GPS speed, integrated; floored at 0 (zr_v: the same without the floor). The deadband grows from
    0 at a fix to l over deadband_ramp_s: it keeps out the gravity leak of a tilt error, which grows with the time
    since a fix corrected the tilt, and what it keeps out at once is a car's gentle acceleration in traffic (on a
    real highway 41 % of it lies within l)."""
    dt, deadband = lp.dt, lp.deadband
    ramp = st.since_fix * lp.inv_ramp
    if lp.inv_ramp > 0.0 and ramp < 1.0:
        deadband *= ramp
    a = lp.ae * st.ux + lp.an * st.uy
    if lp.median:
        a = _ring_median(st, lp.ring, a, lp.median)
    a -= st.bias + (st.nh_u0x - st.ux) * st.nh_fx + (st.nh_u0y - st.uy) * st.nh_fy
    if lp.inv_acc > 0.0:
        beta = dt * lp.inv_acc
        st.acc_lp += (beta if beta < 1.0 else 1.0) * (a - st.acc_lp)
        if abs(st.acc_lp) < deadband:
            st.sb_lost += a * dt
            a = 0.0
    elif abs(a) < deadband:
        st.sb_lost += a * dt
        a = 0.0
    a += (st.gps_speed - st.speed) * lp.inv_speed
    st.speed += a * dt
    st.zr_v += a * dt
    if st.speed < 0.0:
        st.speed = 0.0


def _kept_speed(st: FusedState, fcfg: FusedConfig) -> float:
    """A vehicle's speed for its position: two estimates weighed by their variances. The integrated speed s (the
    along-track acceleration less the bias since the speed was last known, t = sk_t ago) has the speed/bias filter's
    variance carried on, V_s = P_ss - 2 t P_sb + t^2 P_bb + speed_noise^2 t + q_b t^3 / 3 (the bias's uncertainty
    grows it with t^2, the bias's own random walk q_b, _bias_walk, with t^3); the kept speed s_k (a car keeps its
    speed: the last fix's) has V_k = kf_vel_sigma_ms^2 + keep_speed_noise^2 t. Their weighted mean
    s + V_s / (V_s + V_k) (s_k - s), bounded to [0, the speed last known + max_accel_ms2 t]. No kept speed after a
    rest (a car that stood starts from 0)."""
    t = st.sk_t
    s = st.speed
    known = st.keep_v
    if known >= 0.0 and fcfg.keep_speed_noise > 0.0:
        v_s = (st.sb_pss - 2.0 * t * st.sb_psb + t * t * st.sb_pbb + fcfg.speed_noise * fcfg.speed_noise * t
               + _bias_walk(st, fcfg) * t * t * t * (1.0 / 3.0))
        v_k = fcfg.kf_vel_sigma_ms * fcfg.kf_vel_sigma_ms + fcfg.keep_speed_noise * fcfg.keep_speed_noise * t
        s += v_s / (v_s + v_k) * (known - s)
    top = (known if known > 0.0 else 0.0) + fcfg.max_accel_ms2 * t
    return top if s > top else s


def _lateral_update(lp: _Loop, st: FusedState) -> None:
    """A vehicle's lateral update in an outage: it does not slide sideways, so across u its acceleration is the
    centripetal speed x rate, and what is left, a_lat - s r = leak - (s - s_true) r, sees the lateral leak and, in
    turns, the speed error. Gathered over nhc_period_s (_nhc_update); the filter starts on the outage's first sample
    of a moving vehicle and stops at a fix, a rest or a walk."""
    fcfg = lp.fcfg
    if lp.nhc_r <= 0.0:
        return
    if lp.rest or lp.walking or not lp.vehicle or st.since_fix < fcfg.gps_timeout_s:
        _nhc_restart(st, fcfg)
        return
    if st.nh_u0x == 0.0 and st.nh_u0y == 0.0:
        _nhc_start(st, fcfg)
    dt = lp.dt
    st.nh_t += dt
    st.nh_z += (lp.an * st.ux - lp.ae * st.uy - st.speed * lp.r) * dt
    st.nh_r += lp.r * dt
    st.nh_ix += st.ux * dt
    st.nh_iy += st.uy * dt
    if st.nh_t + 0.5 * dt >= fcfg.nhc_period_s:  # half a sample's margin: float32 sums agree
        _nhc_update(st, lp.nhc_r, fcfg)


def _fix_integrals(lp: _Loop, st: FusedState) -> None:
    """What the next fix and rest update read: the time at rest towards the next rest update (every rest_update_s,
    after the rest's first: the end of a braking), the kernel-frame horizontal velocity change and its integral, the
    integral of R(q)'s horizontal rows (the tilt/offset filter's M), the times since the fix and since the filter's
    last prediction."""
    dt = lp.dt
    if lp.rest and st.rest_s >= lp.fcfg.rest_time_s + lp.fcfg.rest_update_s:
        st.zt += dt
    ae, an = lp.ae, lp.an
    st.dpx += (st.dvx + 0.5 * ae * dt) * dt
    st.dpy += (st.dvy + 0.5 * an * dt) * dt
    st.dvx += ae * dt
    st.dvy += an * dt
    st.m00 += lp.r00 * dt
    st.m01 += lp.r01 * dt
    st.m10 += lp.r10 * dt
    st.m11 += lp.r11 * dt
    st.m02 += lp.r02 * dt
    st.m12 += lp.r12 * dt
    st.since_fix += dt
    st.sk_t += dt
    st.kf_t += dt


def _advance_position(lp: _Loop, st: FusedState) -> None:
    """The position in true ENU, p += s (A u) dt (A: the kernel frame -> true ENU; s a vehicle's kept-speed
    weighted one), and, for a vehicle, the integrals a zero-velocity update corrects it by: the weight w(t) = 1 +
    zupt_turn_weight x the turn since the speed was known, its integral W, int W (A u) dt, and int (zr_v - s) (A u)
    dt (what the floor at 0 and the kept speed moved it by)."""
    dt = lp.dt
    ue = st.cos_t * st.ux - st.sin_t * st.uy
    un = st.sin_t * st.ux + st.cos_t * st.uy
    st.pe += lp.sp * ue * dt
    st.pn += lp.sp * un * dt
    if not (lp.rest or lp.walking or lp.walked):
        st.zr_turn += abs(lp.r) * dt
        st.zr_t += (1.0 + st.zr_turn * lp.fcfg.zupt_turn_weight) * dt
        st.zr_pe += st.zr_t * ue * dt
        st.zr_pn += st.zr_t * un * dt
        st.zr_ce += (st.zr_v - lp.sp) * ue * dt  # what the floor and the kept speed moved it by, beyond zr_v
        st.zr_cn += (st.zr_v - lp.sp) * un * dt


def _tilt_correction(lp: _Loop, st: FusedState) -> None:
    """The tilt kept honest by gravity, then the attitude integrated: omega += Kp (f_c/|f_c| x up_body), f_c = f
    less, while fixes arrive, the motion acceleration they show (R^T [acc_e, acc_n, 0]; Kp 1 / tilt_tau_s while it
    is steady, else 0), without GPS f itself at 1 / tilt_tau_dark_s; only while ||f_c| - g| < accel_reject_g g. Then
    q <- q (x) [1, omega dt / 2], renormalised."""
    fcfg = lp.fcfg
    fx, fy, fz = lp.fx, lp.fy, lp.fz
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (lp.r00, lp.r01, lp.r02, lp.r10, lp.r11, lp.r12, lp.r20, lp.r21,
                                                   lp.r22)
    wx, wy, wz = lp.wx, lp.wy, lp.wz
    if st.since_fix < fcfg.gps_timeout_s:
        gain = lp.kp if st.steady > 0.0 else 0.0
        cx = fx - (r00 * st.acc_e + r10 * st.acc_n)
        cy = fy - (r01 * st.acc_e + r11 * st.acc_n)
        cz = fz - (r02 * st.acc_e + r12 * st.acc_n)
        nc = math.sqrt(cx * cx + cy * cy + cz * cz)
    else:
        cx, cy, cz, nc = fx, fy, fz, lp.nf
        gain = lp.kp_dark
    if nc > 0.0 and abs(nc - lp.g) < lp.reject:
        inf = gain / nc
        wx += (cy * r22 - cz * r21) * inf
        wy += (cz * r20 - cx * r22) * inf
        wz += (cx * r21 - cy * r20) * inf
    dt = lp.dt
    hx = 0.5 * wx * dt
    hy = 0.5 * wy * dt
    hz = 0.5 * wz * dt
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    nw = qw - qx * hx - qy * hy - qz * hz
    nx = qx + qw * hx + qy * hz - qz * hy
    ny = qy + qw * hy - qx * hz + qz * hx
    nz = qz + qw * hz + qx * hy - qy * hx
    inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    st.qw, st.qx, st.qy, st.qz = nw * inv, nx * inv, ny * inv, nz * inv


def _rest_update_due(lp: _Loop, st: FusedState) -> None:
    """At rest, every rest_update_s: the rest update (rest_update); out of rest its clock restarts."""
    if not lp.rest:
        st.zt = 0.0
    elif st.zt >= lp.fcfg.rest_update_s:
        rest_update(st, lp.gscale, lp.fcfg)


def _nhc_restart(st: FusedState, fcfg: FusedConfig) -> None:
    """The lateral filter stopped (at a fix, at rest, walking): the speed known; it starts again with the outage's
    next sample of a moving vehicle (_nhc_start). Everything is 0 until it starts (u0 is a unit vector then)."""
    if st.nh_u0x == 0.0 and st.nh_u0y == 0.0:
        return
    for name in NHC_FIELDS:
        setattr(st, name, 0.0)


def _nhc_start(st: FusedState, fcfg: FusedConfig) -> None:
    """The lateral filter's start on an outage's first sample of a moving vehicle: the speed known, the lateral leak
    0 +- nhc_leak_sigma_ms2 (the tilt/offset filter has just taken out what it knew), the folded offsets 0 with what
    that filter does not know of the offsets seen horizontally, R_h P_bb R_h^T (times nhc_fold_scale), and the
    travel direction they turn from."""
    st.nh_pbb = fcfg.nhc_leak_sigma_ms2 * fcfg.nhc_leak_sigma_ms2
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    rh = ((1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy)),
          (2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx)))
    pb = [[getattr(st, _PIJ[(min(i, j) + 2, max(i, j) + 2)]) for j in range(3)] for i in range(3)]
    rp = [[sum(rh[a][k] * pb[k][j] for k in range(3)) for j in range(3)] for a in range(2)]  # R_h P_bb
    st.nh_pxx = fcfg.nhc_fold_scale * sum(rp[0][j] * rh[0][j] for j in range(3))
    st.nh_pxy = fcfg.nhc_fold_scale * sum(rp[0][j] * rh[1][j] for j in range(3))
    st.nh_pyy = fcfg.nhc_fold_scale * sum(rp[1][j] * rh[1][j] for j in range(3))
    st.nh_u0x, st.nh_u0y = st.ux, st.uy


def _nhc_update(st: FusedState, var: float, fcfg: FusedConfig) -> None:
    """A vehicle's lateral update in an outage, every nhc_period_s T: a 4-state Kalman filter of the speed error
    e = s - s_true (fed back into the speed at once), the lateral leak l (a random walk, faster in turns) and the
    offsets f folded into the tilt (kernel frame, the horizontal part of the body-fixed offsets when the outage
    began). The tilt stays in the earth frame while the offsets turn with the vehicle, so after the travel direction
    turned from u0 to u they leak (u0 - u) . f along the track (taken out of the along-track acceleration) and
    (n0 - n) . f across it (n = u turned 90 degrees left). Over the period, with ubar the mean of u,
        z = (integral of a_lat - s r dt) / T = l + (n0 - nbar) . f - rbar e + noise,   rbar = (integral of r dt) / T,
        e grows by T (u0 - ubar) . (f - f_estimated) + speed noise,
    noise variance var / T (var: of a 1 s average). Restarts the averages."""
    t = st.nh_t
    inv_t = 1.0 / t
    rbar = st.nh_r * inv_t
    z = st.nh_z * inv_t
    unseen = 0.0
    if abs(rbar) < fcfg.nhc_min_rate:
        # no turn: a handlebar's or a hand's wobble about Up is no turn of the vehicle; the speed error it would show
        # is noise to the leaks (a turn's end must not pass it into the folded offsets)
        unseen = rbar * rbar
        rbar = 0.0
    dux = st.nh_u0x - st.nh_ix * inv_t  # u0 - ubar
    duy = st.nh_u0y - st.nh_iy * inv_t
    dnx, dny = -duy, dux  # n0 - nbar
    if _lateral_predict(st, t * dux, t * duy, fcfg.nhc_speed_noise * fcfg.nhc_speed_noise * t,
                        (fcfg.nhc_leak_turn * st.nh_r) ** 2, fcfg):
        h = (-rbar, 1.0, dnx, dny)
        y = z - st.nh_b - dnx * st.nh_fx - dny * st.nh_fy
        x = _lateral_correct(st, h, var * inv_t + unseen * st.nh_pss, y, fcfg)
        if x is not None:
            _lateral_feed_back(st, x, fcfg)
    st.nh_t = st.nh_z = st.nh_r = st.nh_ix = st.nh_iy = 0.0


def _lateral_predict(st: FusedState, f2: float, f3: float, q_speed: float, q_leak: float, fcfg: FusedConfig) -> bool:
    """The lateral filter's predict, P <- F P F^T + Q: F = I + (row 0: f2, f3 in columns 2, 3; the speed error grows
    by T (u0 - ubar) . (f - f_estimated)), Q = diag(q_speed, q_leak, 0, 0). With A = F - I (row 0 only),
    F P F^T = P + A P + P A^T + A P A^T: row and column 0 gain (A P)[0], the corner twice that and A P A^T.
    Returns False if the covariance went wrong (reset to the prior)."""
    n = NHC_STATES
    p = [[getattr(st, _NHC_PIJ[(min(i, j), max(i, j))]) for j in range(n)] for i in range(n)]
    ap = [f2 * p[2][j] + f3 * p[3][j] for j in range(n)]  # row 0 of A P
    for j in range(1, n):
        setattr(st, _NHC_PIJ[(0, j)], p[0][j] + ap[j])
    st.nh_pss = p[0][0] + 2.0 * ap[0] + (f2 * ap[2] + f3 * ap[3]) + q_speed
    st.nh_pbb = p[1][1] + q_leak
    return _covariance_checked(st, FILTER_LATERAL, STEP_PREDICT, fcfg)


def _lateral_correct(st: FusedState, h, r: float, y: float, fcfg: FusedConfig):
    """The lateral filter's update with z = h . x + noise (variance r), innovation y: P <- P - K S K^T, K = P h / S,
    S = h P h + r (the Joseph form's value for this optimal gain), the upper triangle. Returns the correction K y
    (speed error, leak, folded offsets x, y), or None if the covariance went wrong (reset to the prior)."""
    n = NHC_STATES
    p = [[getattr(st, _NHC_PIJ[(min(i, j), max(i, j))]) for j in range(n)] for i in range(n)]
    ph = [sum(p[i][k] * h[k] for k in range(n)) for i in range(n)]
    s = sum(h[i] * ph[i] for i in range(n)) + r
    if not 0.0 < s <= COV_MAX:
        _covariance_checked(st, FILTER_LATERAL, STEP_UPDATE, fcfg, innovation_ok=False)
        return None
    inv_s = 1.0 / s
    gain = [ph[i] * inv_s for i in range(n)]
    for (i, j), name in _NHC_PIJ.items():
        setattr(st, name, p[i][j] - gain[i] * ph[j])
    if not _covariance_checked(st, FILTER_LATERAL, STEP_UPDATE, fcfg):
        return None
    return [g * y for g in gain]


def _lateral_feed_back(st: FusedState, x, fcfg: FusedConfig) -> None:
    """The lateral update's correction x: the speed error out of the speed at once and, as the zero-velocity update
    takes it (grown at the rate w(t) since the speed was last known), its integral out of the position
    (nhc_position, 1: all of it); the leak and the folded offsets into their estimates."""
    e = x[0]
    st.speed -= e
    st.zr_v -= e
    if fcfg.nhc_position > 0.0 and st.zr_t > 0.0:
        k = fcfg.nhc_position * e / st.zr_t
        st.pe -= k * st.zr_pe
        st.pn -= k * st.zr_pn
    if st.speed < 0.0:
        st.speed = 0.0
    st.nh_b += x[1]
    st.nh_fx += x[2]
    st.nh_fy += x[3]


def _ring_median(st: FusedState, ring: list, a: float, b: int) -> float:
    """Push a into the ring of the last b values and return their median (an even count: the mean of the middle
    two, as numpy.median and dr_median). The ring restarts whenever the vehicle branch was left (med_n = 0)."""
    i = int(st.med_i)
    ring[i] = a
    st.med_i = float((i + 1) % b)
    n = min(int(st.med_n) + 1, b)
    st.med_n = float(n)
    window = sorted(ring[:n])  # after a restart the ring fills from slot 0: the first n slots are the filled ones
    half = n >> 1
    return window[half] if n & 1 else (window[half - 1] + window[half]) * 0.5


def position_update(st: FusedState, ve: float, vn: float, de: float, dn: float, fcfg: FusedConfig) -> None:
    """A fix's position, before its gps_update: (de, dn) = its displacement from the previous fix (true ENU m), (ve,
    vn) its Doppler velocity. A 2-state Kalman filter per axis smooths the receiver's position with its Doppler:
        x_k = x_k-1 + T (v_k-1 + v_k) / 2 + w,   e_k = phi e_k-1 + n,   y_k = x_k + e_k,
    x the true position, e the receiver's error (first-order Gauss-Markov: sigma pos_sigma_m, correlation time
    pos_tau_s, phi = exp(-T / tau) by its cubic Taylor polynomial, T <= gps_timeout_s), w ~ pos_step_sigma_ms T.
    The trapezoid is exact only for a constant acceleration; the IMU supplies the rest,
        x_k - x_k-1 = T (v_k-1 + v_k) / 2 + c,   c = integral of (dv(t) - dv(T) / 2) dt over the interval,
    dv(t) the kernel-frame velocity change since the previous fix (the samples' dvx, dvy; dpx, dpy their integral)
    rotated into true ENU. A constant acceleration error (a gravity leak, an offset) cancels in c; what remains is
    the Doppler's own noise. Measured per 1 s step against the truth: the simulated walk's step error 0.12 -> 0.08
    m, the replayed real walk's 0.15 -> 0.10 m (its gait aliases the 1 Hz Doppler), the car's 0.078 -> 0.069 m.
    The state is kept relative to the fix (fix_ae, fix_an = x_hat - y), so the caller's anchor stays the fix and
    the outage starts from fix + (fix_ae, fix_an). A first fix, or one after an outage, restarts the filter at
    the fix itself (x_hat = y, e_hat = 0, their errors +-pos_sigma_m, perfectly anti-correlated)."""
    sigma2 = fcfg.pos_sigma_m * fcfg.pos_sigma_m
    t = st.since_fix
    if sigma2 <= 0.0:
        return
    if not (st.fix_pxx > 0.0 and 0.0 < t < fcfg.gps_timeout_s):
        _position_prior(st, fcfg)
        _covariance_checked(st, FILTER_POSITION, STEP_START, fcfg)
        return
    phi = _position_predict(st, t, fcfg)
    if phi is None:
        return
    # the IMU's correction to the trapezoid: what the acceleration adds to T (v0 + v1) / 2, true ENU
    cx = st.dpx - 0.5 * t * st.dvx
    cy = st.dpy - 0.5 * t * st.dvy
    ce = st.cos_t * cx - st.sin_t * cy
    cn = st.sin_t * cx + st.cos_t * cy
    ae = st.fix_ae + 0.5 * t * (st.gps_ve + ve) + ce - de  # x_hat- - y, East
    an = st.fix_an + 0.5 * t * (st.gps_vn + vn) + cn - dn
    ee = phi * st.fix_ee
    en = phi * st.fix_en
    gain = _position_correct(st, fcfg)
    if gain is None:
        return
    kx, ke = gain
    st.fix_ae = ae - kx * (ae + ee)  # innovation y - x_hat- - e_hat- = -(a + e)
    st.fix_an = an - kx * (an + en)
    st.fix_ee = ee - ke * (ae + ee)
    st.fix_en = en - ke * (an + en)


def _speed_update(st: FusedState, e: float, fcfg: FusedConfig):
    """A vehicle's speed/bias filter at a fix: states the speed s and the along-track bias b, s integrating the
    along-track acceleration less b. Started on its first fix (_speed_prior), predicted over the sk_t seconds since
    the speed was last known and updated with the fix's speed (innovation e). Returns the gain (k_s, k_b), or None
    if the covariance went wrong (reset, nothing fed back)."""
    if st.sb_pbb <= 0.0:
        _speed_prior(st, fcfg)
        if not _covariance_checked(st, FILTER_SPEED, STEP_START, fcfg):
            return None
    t = st.sk_t
    qb = _bias_walk(st, fcfg) * t + (fcfg.kf_turn_noise * st.turn) ** 2
    qs = fcfg.speed_noise * fcfg.speed_noise * t + st.sb_lost * st.sb_lost  # what the deadband kept out: no bias
    if not _speed_predict(st, t, qs, qb, fcfg):
        return None
    return _speed_correct(st, fcfg.kf_vel_sigma_ms * fcfg.kf_vel_sigma_ms, fcfg)


def _bias_walk(st: FusedState, fcfg: FusedConfig) -> float:
    """The along-track bias's random walk, (m/s^2)^2/s: the gravity leak's (kf_tilt_noise^2), or after a calibration
    that moved, until a rest re-learns the gyro bias, speed_bias_noise^2 (the tilt drifts at the rate calibration
    took for the gyro's bias)."""
    q = fcfg.speed_bias_noise if st.cal_moved > 0.0 else fcfg.kf_tilt_noise
    return q * q


def _speed_prior(st: FusedState, fcfg: FusedConfig) -> None:
    """The speed/bias filter's start (and repair): the bias 0 +- nhc_leak_sigma_ms2 (a still calibration leaves no
    along-track leak beyond the lateral one's: it folded the offsets into the tilt, and they leak after turns, which
    the turn term adds), or kf_bias_init_g after a calibration that moved (it took the motion's mean acceleration
    for gravity); uncorrelated with the speed, whose variance stays what calibration or the last fix left (a repair:
    not known)."""
    if not 0.0 <= st.sb_pss <= COV_MAX:
        st.sb_pss = SPEED_UNKNOWN_VAR
    st.sb_psb = 0.0
    sigma = fcfg.kf_bias_init_g * STANDARD_GRAVITY if st.cal_moved > 0.0 else fcfg.nhc_leak_sigma_ms2
    st.sb_pbb = sigma * sigma


def _speed_predict(st: FusedState, t: float, q_speed: float, q_bias: float, fcfg: FusedConfig) -> bool:
    """The speed/bias filter's predict over t s, P <- F P F^T + Q: F = [[1, -t], [0, 1]] (the speed gathers -t times
    the bias), Q = diag(q_speed, q_bias). Returns False if the covariance went wrong (reset to the prior)."""
    pss, psb, pbb = st.sb_pss, st.sb_psb, st.sb_pbb
    st.sb_pss = pss - 2.0 * t * psb + t * t * pbb + q_speed
    st.sb_psb = psb - t * pbb
    st.sb_pbb = pbb + q_bias
    return _covariance_checked(st, FILTER_SPEED, STEP_PREDICT, fcfg)


def _speed_correct(st: FusedState, r: float, fcfg: FusedConfig):
    """The speed/bias filter's update with the fix's speed (H = [1, 0], variance r): P <- P - K S K^T, K = P H^T / S
    (the Joseph form's value for this optimal gain), as (I - K H) P: pss r / S, psb r / S, pbb - k_b psb. That form
    has no difference of near-equal numbers when the speed starts from SPEED_UNKNOWN_VAR (pss - pss^2 / S lost all
    but a tenth of r's digits in float32). Returns the gain (k_s, k_b), or None if the covariance went wrong (reset
    to the prior)."""
    pss, psb, pbb = st.sb_pss, st.sb_psb, st.sb_pbb
    s = pss + r
    if not 0.0 < s <= COV_MAX:
        _covariance_checked(st, FILTER_SPEED, STEP_UPDATE, fcfg, innovation_ok=False)
        return None
    ks = pss / s
    kb = psb / s
    st.sb_pss = ks * r
    st.sb_psb = kb * r
    st.sb_pbb = pbb - kb * psb
    return (ks, kb) if _covariance_checked(st, FILTER_SPEED, STEP_UPDATE, fcfg) else None


def _position_prior(st: FusedState, fcfg: FusedConfig) -> None:
    """The position filter (re)started at the fix itself: x_hat = y, e_hat = 0, their errors +-pos_sigma_m,
    perfectly anti-correlated (their sum is the fix, known)."""
    sigma2 = fcfg.pos_sigma_m * fcfg.pos_sigma_m
    st.fix_ae = st.fix_an = st.fix_ee = st.fix_en = 0.0
    st.fix_pxx = st.fix_pee = sigma2
    st.fix_pxe = -sigma2


def _position_predict(st: FusedState, t: float, fcfg: FusedConfig):
    """The position filter's predict over t s, P <- F P F^T + Q: F = diag(1, phi), Q = diag((pos_step_sigma_ms t)^2,
    pos_sigma_m^2 (1 - phi^2)), phi = exp(-t / pos_tau_s) by its cubic Taylor polynomial. Returns phi, or None if
    the covariance went wrong (restarted at the fix)."""
    sigma2 = fcfg.pos_sigma_m * fcfg.pos_sigma_m
    x = t / fcfg.pos_tau_s
    phi = 1.0 - x * (1.0 - x * (0.5 - x * (1.0 / 6.0)))
    step = fcfg.pos_step_sigma_ms * t
    st.fix_pxx = st.fix_pxx + step * step
    st.fix_pxe = phi * st.fix_pxe
    st.fix_pee = phi * phi * st.fix_pee + sigma2 * (1.0 - phi * phi)
    return phi if _covariance_checked(st, FILTER_POSITION, STEP_PREDICT, fcfg) else None


def _position_correct(st: FusedState, fcfg: FusedConfig):
    """The position filter's update with the fix y = x + e (H = [1, 1], no noise of its own: the receiver's error
    is the state e): P <- P - K S K^T, K = P H^T / S. Returns the gain (kx, ke), or None if the covariance went
    wrong (restarted at the fix)."""
    pxx, pxe, pee = st.fix_pxx, st.fix_pxe, st.fix_pee
    s = pxx + 2.0 * pxe + pee
    if not 0.0 < s <= COV_MAX:
        _covariance_checked(st, FILTER_POSITION, STEP_UPDATE, fcfg, innovation_ok=False)
        return None
    kx = (pxx + pxe) / s
    ke = (pxe + pee) / s
    st.fix_pxx = pxx - kx * kx * s
    st.fix_pxe = pxe - kx * ke * s
    st.fix_pee = pee - ke * ke * s
    return (kx, ke) if _covariance_checked(st, FILTER_POSITION, STEP_UPDATE, fcfg) else None


def gps_update(st: FusedState, ve: float, vn: float, fcfg: FusedConfig) -> None:
    """One GPS fix's Doppler velocity (true ENU East, North, m/s; 0, 0 when the course is undefined), in steps: the
    heading alignment (_fix_alignment), the travel direction and a walker's speed (_fix_course), the speed and the
    along-track bias (_fix_speed), the tilt and the offsets (tilt_and_offset_update, with the fix's motion
    acceleration), then what the next interval starts from (_fix_restart)."""
    speed = math.sqrt(ve * ve + vn * vn)
    moving = speed >= fcfg.min_speed_ms
    t = st.since_fix
    follows = st.gps_ok > 0.0 and moving and 0.0 < t < fcfg.gps_timeout_s  # a previous fix with a course, in time
    aimed = st.gps_ok > 0.0 and (st.align_c != 0.0 or st.align_s != 0.0)  # the interval's direction was known
    if follows:
        _fix_alignment(st, ve, vn, fcfg)
    if moving:
        _fix_course(st, ve, vn, speed, fcfg)
    _fix_speed(st, speed, t, aimed, fcfg)
    if follows:
        # the motion acceleration over the last interval, into the kernel frame (A^T)
        me = (ve - st.gps_ve) / t
        mn = (vn - st.gps_vn) / t
        ae = st.cos_t * me + st.sin_t * mn
        an = -st.sin_t * me + st.cos_t * mn
    else:
        ae = an = 0.0
    if fcfg.kf_bias_init_g > 0.0:
        tilt_and_offset_update(st, ve, vn, moving, t, fcfg)
    _fix_restart(st, ve, vn, speed, ae, an, fcfg)


def _fix_alignment(st: FusedState, ve: float, vn: float, fcfg: FusedConfig) -> None:
    """The heading alignment of the kernel frame to North from the velocity changes (the previous fix within
    gps_timeout_s, both with a course): the IMU's change dv against the fix's, forgotten at align_forget per fix.
    The new alignment turns the kernel frame; the travel direction keeps its true bearing: u <- A'^T A u."""
    gx = ve - st.gps_ve
    gy = vn - st.gps_vn
    lam = fcfg.align_forget
    st.align_c = lam * st.align_c + st.dvx * gx + st.dvy * gy
    st.align_s = lam * st.align_s + st.dvx * gy - st.dvy * gx
    norm = math.sqrt(st.align_c * st.align_c + st.align_s * st.align_s)
    if norm > 0.0:
        ue = st.cos_t * st.ux - st.sin_t * st.uy
        un = st.sin_t * st.ux + st.cos_t * st.uy
        st.cos_t = st.align_c / norm
        st.sin_t = st.align_s / norm
        st.ux = st.cos_t * ue + st.sin_t * un
        st.uy = -st.sin_t * ue + st.cos_t * un


def _fix_course(st: FusedState, ve: float, vn: float, speed: float, fcfg: FusedConfig) -> None:
    """A fix with a course: the travel direction pulled towards it by heading_gain (before the frame's first
    alignment u means nothing yet: it takes the course at once), and a walker's speed towards the fix's, bounded by
    what people walk and run (pedestrian_max_ms)."""
    gx = (st.cos_t * ve + st.sin_t * vn) / speed  # the GPS course in the kernel frame: A^T g / |g|
    gy = (-st.sin_t * ve + st.cos_t * vn) / speed
    pull = fcfg.heading_gain if st.align_c != 0.0 or st.align_s != 0.0 else 1.0
    ux = st.ux + pull * (gx - st.ux)
    uy = st.uy + pull * (gy - st.uy)
    norm = math.sqrt(ux * ux + uy * uy)
    if norm > 0.0:
        st.ux, st.uy = ux / norm, uy / norm
    if int(st.flags) & WALKING:
        st.walk_speed += fcfg.walk_speed_gain * (min(speed, fcfg.pedestrian_max_ms) - st.walk_speed)


def _fix_speed(st: FusedState, speed: float, t: float, aimed: bool, fcfg: FusedConfig) -> None:
    """The speed at a fix, t s after the previous one. A pedestrian's or a rest's speed is not integrated, so the
    interval says nothing of the along-track bias (a car in slow traffic taken for a walker once learned -12 m/s^2
    here, and ran to 700 m/s when it drove on): pulled by speed_gain, its variance what is left. A vehicle's: the
    speed/bias filter (_speed_update), started from the fix (the interval teaches the bias nothing) after an outage,
    before any fix, or when the interval was not `aimed`: its travel direction not known in the kernel frame at its
    start (the previous fix without a course, or no heading alignment yet). A car's first seconds of driving
    integrated its acceleration along a direction the alignment had not found: the speed lagged the fixes by a third
    and the filter took that for a bias of -1 m/s^2, which an outage then integrated (a simulated car whose cruises
    wandered, docs/fused.md: 8.7 -> 18 m/s in 10 s). Then the speed kept is the fix's."""
    e = speed - st.speed
    if int(st.flags) & (AT_REST | WALKING | WALKED):
        st.speed += fcfg.speed_gain * e
        st.sb_pss = (1.0 - fcfg.speed_gain) ** 2 * e * e + fcfg.kf_vel_sigma_ms * fcfg.kf_vel_sigma_ms
        st.sb_psb = 0.0
    else:
        if not (aimed and 0.0 < t < fcfg.gps_timeout_s):
            st.sb_pss = SPEED_UNKNOWN_VAR
            st.sb_psb = 0.0
        gain = _speed_update(st, e, fcfg)
        if gain is not None:
            st.speed += gain[0] * e
            st.bias += gain[1] * e
    st.keep_v = speed
    st.sk_t = st.sb_lost = 0.0


def _fix_restart(st: FusedState, ve: float, vn: float, speed: float, ae: float, an: float,
                 fcfg: FusedConfig) -> None:
    """What the next interval starts from: whether the motion acceleration (ae, an, kernel frame) is steady enough
    for the tilt correction (steady_accel_ms2 of the last), the fix's velocity and speed, the FAST flag (faster
    than people run: a vehicle until it rests, process), and the integrals since the fix, the zero-velocity
    update's and the lateral filter's restarted."""
    de = ae - st.acc_e
    dn = an - st.acc_n
    st.steady = fcfg.steady_accel_ms2 * fcfg.steady_accel_ms2 - (de * de + dn * dn)
    st.acc_e, st.acc_n = ae, an
    st.gps_ve, st.gps_vn = ve, vn
    st.gps_speed = speed
    st.gps_ok = speed - fcfg.min_speed_ms
    if speed > fcfg.pedestrian_max_ms or speed > fcfg.carried_ms and not int(st.flags) & WALKING:
        st.flags = float(int(st.flags) | FAST | DROVE)
    st.dvx = st.dvy = st.dpx = st.dpy = 0.0
    st.m00 = st.m01 = st.m10 = st.m11 = st.m02 = st.m12 = st.turn = 0.0
    st.zr_t = st.zr_pe = st.zr_pn = st.zr_ce = st.zr_cn = st.zr_turn = 0.0
    st.zr_v = st.speed
    st.since_fix = 0.0
    _nhc_restart(st, fcfg)


# the covariance's upper triangle: (row, column) -> field; the 4 x 4 block row by row, then the fifth column
COVARIANCE_FIELDS = FUSED.field("p").element_names() + FUSED.field("pz").element_names()
_PIJ = {(i, j): name for (i, j), name in zip([(i, j) for i in range(4) for j in range(i, 4)]
                                             + [(i, 4) for i in range(5)], COVARIANCE_FIELDS)}
KF_STATES = 5
# the lateral filter: its covariance's upper triangle, (row, column) -> field, row by row; everything it restarts
NHC_STATES = 4
_NHC_PIJ = dict(zip([(i, j) for i in range(NHC_STATES) for j in range(i, NHC_STATES)],
                    FUSED.field("nh_p").element_names()))
NHC_FIELDS = ("nh_t", "nh_z", "nh_r", "nh_b") + tuple(
    n for f in ("nh_f", "nh_u0", "nh_i", "nh_p") for n in FUSED.field(f).element_names())
POSITION_PIJ = {(0, 0): "fix_pxx", (0, 1): "fix_pxe", (1, 1): "fix_pee"}  # the position filter's (per axis)
# each filter: its covariance's upper triangle, (row, column) -> field
SPEED_PIJ = {(0, 0): "sb_pss", (0, 1): "sb_psb", (1, 1): "sb_pbb"}  # the speed/bias filter's
FILTER_COVARIANCES = {FILTER_TILT: _PIJ, FILTER_LATERAL: _NHC_PIJ, FILTER_POSITION: POSITION_PIJ,
                      FILTER_SPEED: SPEED_PIJ}

_observer = None


def observe_covariances(callback):
    """Call `callback(st, filter, step)` (FILTER_*, STEP_*) after every step of every Kalman filter, before its
    covariance is checked; None stops it. For tests and benchmarks/consistency.py; returns the previous callback."""
    global _observer
    previous, _observer = _observer, callback
    return previous


def covariance_matrix(st: FusedState, which: int) -> np.ndarray:
    """A filter's covariance (FILTER_*) as a full symmetric matrix, from its stored upper triangle."""
    pij = FILTER_COVARIANCES[which]
    n = max(j for _, j in pij) + 1
    p = np.zeros((n, n))
    for (i, j), name in pij.items():
        p[i, j] = p[j, i] = getattr(st, name)
    return p


def _covariance_checked(st: FusedState, which: int, step: int, fcfg: FusedConfig, innovation_ok: bool = True) -> bool:
    """After a step of filter `which`: its covariance usable (every entry a number within +-COV_MAX, every variance
    >= 0, and, for an update, the innovation's covariance S positive definite: innovation_ok)? If not, it is reset
    to its prior, counted in cov_repairs, and False returned: the caller uses nothing of this step (a gain from a
    broken covariance has any sign; an update of one may even look healthy)."""
    if _observer is not None:
        _observer(st, which, step)
    pij = FILTER_COVARIANCES[which]
    if innovation_ok and all(-COV_MAX <= getattr(st, name) <= COV_MAX and (i != j or getattr(st, name) >= 0.0)
           for (i, j), name in pij.items()):
        return True
    st.cov_repairs += 1.0
    if which == FILTER_TILT:
        _kf_prior(st, fcfg)
    elif which == FILTER_LATERAL:
        _nhc_restart(st, fcfg)
    elif which == FILTER_SPEED:
        st.sb_pss = SPEED_UNKNOWN_VAR  # the speed not known: the next fix restarts it
        _speed_prior(st, fcfg)
    else:
        _position_prior(st, fcfg)
    return False


def tilt_and_offset_update(st: FusedState, ve: float, vn: float, moving: bool, t: float, fcfg: FusedConfig) -> None:
    """The GPS-aided filter of the gravity leak and the accelerometer offsets (5 states), at a fix.

    Over the interval T since the previous fix the IMU's kernel-frame horizontal velocity change dv_imu (from the
    samples minus the estimated offsets) and the GPS's dv_gps (rotated into the kernel frame) differ by
        z = (dv_imu - dv_gps) / T = d + (M / T) b + noise,   M = integral of the horizontal rows of R(q) dt (2 x 3),
    d the gravity leak (g times the tilt error; fixed in the earth frame while the gyro is perfect) and b the
    remaining offsets of the accelerometer's x, y, z axes (fixed in the body; the device may be mounted any way up,
    so each axis can lie horizontal). Calibration folds b into the tilt (d = -R_h b at that moment), so the filter
    starts with that correlation; a turn tells them apart (the offset along gravity stays unseen, and harmless).
    Measurement noise per axis 2 kf_vel_sigma_ms^2 / T^2 (1 + |dv_gps|^2 / |A|), A the heading alignment's sums:
    the alignment's angle has the variance 2 kf_vel_sigma_ms^2 / |A| (its sums gather |dv_gps|^2 per fix against
    that noise), and an angle error e turns dv_gps by e |dv_gps| (a weak alignment weighs a fix that changed speed
    much the less; a straight road's builds slowly). At rest the same filter takes dv_gps = 0 (rest_update)."""
    if _kf_start(st, fcfg) or not _kf_predict(st, fcfg):
        return
    norm = math.sqrt(st.align_c * st.align_c + st.align_s * st.align_s)
    if not (st.gps_ok > 0.0 and moving and 0.0 < t < fcfg.gps_timeout_s and norm > 0.0
            and norm >= fcfg.kf_align_min):
        return
    inv_t = 1.0 / t
    gx = ve - st.gps_ve
    gy = vn - st.gps_vn
    z0 = (st.dvx - (st.cos_t * gx + st.sin_t * gy)) * inv_t
    z1 = (st.dvy - (-st.sin_t * gx + st.cos_t * gy)) * inv_t
    h = ((st.m00 * inv_t, st.m01 * inv_t, st.m02 * inv_t), (st.m10 * inv_t, st.m11 * inv_t, st.m12 * inv_t))
    r = 2.0 * fcfg.kf_vel_sigma_ms * fcfg.kf_vel_sigma_ms * inv_t * inv_t * (1.0 + (gx * gx + gy * gy) / norm)
    _kf_update(st, z0, z1, h, r, fcfg)


def rest_update(st: FusedState, gscale: float, fcfg: FusedConfig) -> None:
    """Every rest_update_s at rest (zt seconds since the last): the true rate and acceleration are 0, so the
    smoothed rate ws is the gyro bias's error (the bias pulled towards it with time constant bias_tau_s, in steps of
    zt), and the smoothed horizontal specific force (ah_e, ah_n) is the tilt/offset filter's error alone,
        z = ah = d + R_h b + noise,   noise kf_rest_sigma_ms2 per axis,
    with or without GPS: a vehicle stopped at lights in an outage gets its tilt levelled and its offsets learned
    as at a fix. Restarts zt."""
    zt = st.zt
    st.zt = 0.0
    if fcfg.bias_tau_s > 0.0:
        k = min(zt / fcfg.bias_tau_s, 1.0) / gscale
        st.bgx += k * st.wsx
        st.bgy += k * st.wsy
        st.bgz += k * st.wsz
    if fcfg.kf_bias_init_g <= 0.0 or fcfg.kf_rest_sigma_ms2 <= 0.0 or _kf_start(st, fcfg):
        return
    if not _kf_predict(st, fcfg):
        return
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    h = ((1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy)),
         (2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx)))
    x = _kf_update(st, st.ah_e, st.ah_n, h, fcfg.kf_rest_sigma_ms2 * fcfg.kf_rest_sigma_ms2, fcfg)
    if x is None:
        return
    # the correction leaves the samples from now on: the smoothed value follows
    st.ah_e -= x[0] + h[0][0] * x[2] + h[0][1] * x[3] + h[0][2] * x[4]
    st.ah_n -= x[1] + h[1][0] * x[2] + h[1][1] * x[3] + h[1][2] * x[4]


def _kf_start(st: FusedState, fcfg: FusedConfig) -> bool:
    """The filter's start on its first use after calibration: b ~ kf_bias_init_g per axis across gravity, d = -R_h b
    (calibration folded b into the tilt). The offset along gravity is left out (variance 0): calibration cannot
    see it, it leaks nothing while the device keeps its tilt, and the slight pitch of a stop on a hill would
    otherwise "observe" it from noise. Returns True if it started now (no update this time)."""
    if st.p22 > 0.0:
        return False
    _kf_prior(st, fcfg)
    _covariance_checked(st, FILTER_TILT, STEP_START, fcfg)
    return True


def _kf_prior(st: FusedState, fcfg: FusedConfig) -> None:
    """The tilt/offset filter's covariance at its start (_kf_start), from the attitude now."""
    var = (fcfg.kf_bias_init_g * STANDARD_GRAVITY) ** 2
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    rows = ((1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy)),
            (2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx)),
            (2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy)))
    for (i, j), name in _PIJ.items():
        if j < 2:
            value = var * sum(a * b for a, b in zip(rows[i], rows[j]))
        elif i < 2:
            value = -var * rows[i][j - 2]
        else:
            value = var * ((1.0 if i == j else 0.0) - rows[2][i - 2] * rows[2][j - 2])
        setattr(st, name, value)
    st.kf_t = st.turn = 0.0


def _kf_predict(st: FusedState, fcfg: FusedConfig) -> bool:
    """The filter's predict, P <- P + Q (F = I: the leak and the offsets are constants), Q the process noise over
    the kf_t seconds since its last prediction: kf_tilt_noise^2 T + (kf_turn_noise turn)^2 on d, kf_bias_noise^2 T
    on b. Returns False if the covariance went wrong (reset to the prior)."""
    t = st.kf_t
    qd = fcfg.kf_tilt_noise * fcfg.kf_tilt_noise * t + (fcfg.kf_turn_noise * st.turn) ** 2
    qb = fcfg.kf_bias_noise * fcfg.kf_bias_noise * t
    st.p00 += qd
    st.p11 += qd
    st.p22 += qb
    st.p33 += qb
    st.p44 += qb
    st.kf_t = st.turn = 0.0
    return _covariance_checked(st, FILTER_TILT, STEP_PREDICT, fcfg)


def _kf_innovation(st: FusedState, h, r: float):
    """The tilt/offset filter's P H^T (5 x 2) and innovation covariance S = H P H^T + r I (s00, s01, s11) for
    z = d + h b + noise, H = [I2 | h], h 2 x 3."""
    n = KF_STATES
    p = [[getattr(st, _PIJ[(min(i, j), max(i, j))]) for j in range(n)] for i in range(n)]
    pht = [[p[i][a] + sum(p[i][2 + c] * h[a][c] for c in range(3)) for a in range(2)] for i in range(n)]
    s00 = pht[0][0] + sum(h[0][c] * pht[2 + c][0] for c in range(3)) + r
    s01 = pht[0][1] + sum(h[0][c] * pht[2 + c][1] for c in range(3))
    s11 = pht[1][1] + sum(h[1][c] * pht[2 + c][1] for c in range(3)) + r
    return pht, s00, s01, s11


def _rest_explained(st: FusedState, fcfg: FusedConfig) -> bool:
    """Can the tilt/offset filter take a quiet vehicle's steady horizontal specific force for its own error, as
    rest_update would (z = ah = d + R_h b)? Its normalised square z^T S^-1 z below rest_gate, S the innovation
    covariance with the predict due since the filter's last one (_kf_predict's Q) counted, not stored. A car
    pulling away smoothly from a stand is as quiet and steady as one that stands, but its acceleration is beyond
    the tilt error a filter that has seen turns allows; taken for rest, each rest update would level it away as
    tilt. Before the filter's start (and with rest_gate 0) any force is explained."""
    if fcfg.rest_gate <= 0.0 or st.p22 <= 0.0 or fcfg.kf_rest_sigma_ms2 <= 0.0:
        return True
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    h = ((1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy)),
         (2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx)))
    _, s00, s01, s11 = _kf_innovation(st, h, fcfg.kf_rest_sigma_ms2 * fcfg.kf_rest_sigma_ms2)
    qd = fcfg.kf_tilt_noise * fcfg.kf_tilt_noise * st.kf_t + (fcfg.kf_turn_noise * st.turn) ** 2
    qb = fcfg.kf_bias_noise * fcfg.kf_bias_noise * st.kf_t
    s00 += qd + qb * (h[0][0] * h[0][0] + h[0][1] * h[0][1] + h[0][2] * h[0][2])
    s01 += qb * (h[0][0] * h[1][0] + h[0][1] * h[1][1] + h[0][2] * h[1][2])
    s11 += qd + qb * (h[1][0] * h[1][0] + h[1][1] * h[1][1] + h[1][2] * h[1][2])
    det = s00 * s11 - s01 * s01
    if not det > 0.0:
        return True  # a broken covariance says nothing (its next step repairs it)
    ze, zn = st.ah_e, st.ah_n
    return s11 * ze * ze - 2.0 * s01 * ze * zn + s00 * zn * zn < fcfg.rest_gate * det


def _kf_update(st: FusedState, z0: float, z1: float, h, r: float, fcfg: FusedConfig):
    """The filter's update with z = d + h b + noise (variance r per axis), h 2 x 3, H = [I2 | h]: P <- P - K S K^T
    (the Joseph form's value for the optimal gain K = P H^T S^-1), fed back at once: b into bax, bay, baz, d as a
    small rotation of q about the kernel frame's horizontal axes; the error state returns to 0. Returns the
    correction x (d East, North, b x, y, z), or None if the covariance went wrong (reset to the prior, nothing fed
    back)."""
    pht, s00, s01, s11 = _kf_innovation(st, h, r)
    det = s00 * s11 - s01 * s01
    if not (0.0 < s00 <= COV_MAX and 0.0 < det <= COV_MAX):
        _covariance_checked(st, FILTER_TILT, STEP_UPDATE, fcfg, innovation_ok=False)
        return None
    inv_det = 1.0 / det
    i00, i01, i11 = s11 * inv_det, -s01 * inv_det, s00 * inv_det
    gain = [(row[0] * i00 + row[1] * i01, row[0] * i01 + row[1] * i11) for row in pht]  # K = PH^T S^-1
    x = [kr[0] * z0 + kr[1] * z1 for kr in gain]
    for (i, j), name in _PIJ.items():
        setattr(st, name, getattr(st, name) - (gain[i][0] * pht[j][0] + gain[i][1] * pht[j][1]))
    if not _covariance_checked(st, FILTER_TILT, STEP_UPDATE, fcfg):
        return None
    st.bax += x[2]
    st.bay += x[3]
    st.baz += x[4]
    # remove the leak: q <- [1, (d_N / g, -d_E / g, 0) / 2] (x) q, a rotation about the kernel frame's E, N axes
    hx = 0.5 * x[1] / STANDARD_GRAVITY
    hy = -0.5 * x[0] / STANDARD_GRAVITY
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    nw = qw - hx * qx - hy * qy
    nx = qx + hx * qw + hy * qz
    ny = qy + hy * qw - hx * qz
    nz = qz + hx * qy - hy * qx
    inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    st.qw, st.qx, st.qy, st.qz = nw * inv, nx * inv, ny * inv, nz * inv
    return x


# --------------------------------------------------------------------------------------------- the benchmark method
def _fused_pass(run, fcfg: FusedConfig | None = None):
    """The device's stream over the whole run: calibration, then the IMU with the GPS updates at their epochs.
    Returns (t_imu (N,) s, n_cal, snapshots: fix index -> (sample index, state after the update))."""
    kcfg = KernelConfig.from_board(run.board)
    fcfg = FusedConfig.from_board(run.board) if fcfg is None else fcfg
    t = run.t_us * 1e-6
    dt_us = np.diff(run.t_us)
    n_cal = int(np.searchsorted(t, run.board.algorithm.calibration_s))
    st = FusedState()
    calibrate(st, run.counts[:n_cal], kcfg)
    gps = run.gps
    vel = gps.device_velocity()
    snaps = {}
    k = n_cal
    prev = -1
    for j in np.flatnonzero(gps.valid & (gps.t >= t[n_cal])):
        stop = int(np.searchsorted(t, gps.t[j], side="left"))  # samples before the fix
        stop = min(stop, len(dt_us))
        if stop > k:
            process(st, run.counts[k:stop], dt_us[k:stop], kcfg, fcfg)
            k = stop
        v = vel[j]
        d = gps.enu[j, :2] - gps.enu[prev, :2] if prev >= 0 else np.zeros(2)
        position_update(st, float(v[0]), float(v[1]), float(d[0]), float(d[1]), fcfg)
        gps_update(st, float(v[0]), float(v[1]), fcfg)
        snaps[int(j)] = (k, st.copy())
        prev = int(j)
    return t, dt_us, snaps, kcfg, fcfg


def estimate(run, starts, times, fcfg: FusedConfig | None = None):
    """The registry's method contract (codegen.sim.methods): positions at `times` for outages from `starts`, using
    only the GPS fixes before each start (the state right after the last of them)."""
    key = ("fused_pass", fcfg)
    if key not in run.cache:
        run.cache[key] = _fused_pass(run, fcfg)
    t, dt_us, snaps, kcfg, fcfg = run.cache[key]
    idx = run.gps.last_valid_before(starts)
    out = np.empty(times.shape + (2,))
    for i, j in enumerate(idx):
        k, snap = snaps[int(j)]
        st = snap.copy()
        st.pe = st.pn = 0.0
        base = run.gps.enu[j, :2] + (st.fix_ae, st.fix_an)  # the fix, smoothed
        ends = np.searchsorted(t, times[i], side="right") - 1  # last sample at or before each time
        for h, end in enumerate(ends):
            end = min(int(end), len(dt_us))
            if end > k:
                process(st, run.counts[k:end], dt_us[k:end], kcfg, fcfg)
                k = end
            out[i, h] = base + (st.pe, st.pn)
    return out

