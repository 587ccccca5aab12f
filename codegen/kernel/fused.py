"""The fused real-time algorithm (`algorithm: fused`, issue 8): the executable specification, float64.

The seed integrated gravity-removed ENU accelerations twice from a gyro-only orientation that never knew North. The
fused method keeps the same front end (calibration, gyro bias, quaternion body -> kernel ENU) and adds, per sample:

1. tilt kept honest by gravity: a Mahony-type correction of the gyro rate towards the measured specific force,
       omega_c = omega + Kp (f_c/|f_c| x up_body),   up_body = R(q)^T [0, 0, 1],   Kp = 1 / tilt_tau_s
   where f_c = f - R^T [acc_e, acc_n, 0] subtracts the motion acceleration the last two GPS fixes showed, applied
   only while | |f_c| - g | < accel_reject_g g and that acceleration is steady (changed by less than
   steady_accel_ms2 between fixes): acceleration rejection. Without GPS (gps_timeout_s after the last fix) the
   gain is 1 / tilt_tau_dark_s, 0 by default: a car's sustained accelerations would pull the tilt away;
2. motion statistics as exponential moving averages over stat_tau_s: the mean and variance of |f| and the mean of
   |omega|^2. Rest = variance below rest_accel_g^2, rate below rest_gyro_dps and the horizontal acceleration
   |a_h| below the board's deadband (a smooth push is no rest), all for rest_time_s: zero-velocity
   update (speed 0) and the gyro bias re-estimated towards the raw gyro counts (time constant bias_tau_s).
   Walking = the |f| variance above walk_accel_g^2 (the steps shake the device);
3. a travel direction u (unit, horizontal, in the kernel's earth frame) turned by the gyro's rate about Up,
       r = up_body . omega,   u <- u rotated by r dt
   except that a walker's slow rotations are held back: the hand swings the device about the course (the walker
   goes straight), while a walker's turns are quick. While walking, r dt goes into a held angle h; a turn starts
   when r smoothed over stat_tau_s exceeds turn_start_dps and ends when it falls below turn_end_dps (hysteresis,
   so the turn keeps its gentle ends); during a turn u takes h at once, otherwise h dt / turn_hold_tau_s of it
   (a swing that returns cancels in h before u takes much of it; a slow curve still arrives, late). Measured on
   walk seeds 101-136 (10 / 30 / 60 s medians): 3.13 / 6.85 / 11.97 -> 3.04 / 6.83 / 12.36 m, the 10 s drift
   2.24 -> 1.79 m; the replayed real walk unchanged at 10 and 30 s (2.98 / 3.66 -> 2.99 / 3.61 m); no vehicle
   is walking, so the car is untouched;
   and a speed s >= 0 along it: at rest s = 0; walking s = the learned walking speed, and 0 on the sample the
   steps stop (a walker who stops stepping has stopped; the hand still moves, so rest alone misses it: on walk
   seeds 101-112 that took the 10 / 30 / 60 s medians from 3.4 / 7.9 / 13.4 to 3.2 / 7.0 / 12.3 m, and the
   replayed real walk's 60 s from 6.1 to 5.2 m); otherwise (a vehicle)
       s <- s + (D(u . a_h - b) + (s_gps - s) / speed_tau_s) dt,   a = R(q) f - [0, 0, g],
   D the board's deadband (|x| < algorithm.deadband_g becomes 0: it stops a slow tilt leak from building speed),
   applied after the optional median of the last b along-track accelerations (`median`, off by default),
   b the along-track accelerometer bias, s_gps the last GPS speed (an optional prior, off by default: it pulls
   a car that brakes or speeds up during the outage back to its old speed);
4. position in true ENU: p += s (A u) dt, with A the rotation by theta from the kernel's frame to true ENU
   (the kernel's yaw after calibration is arbitrary).

And at each GPS fix with Doppler velocity g (true ENU, m/s), `gps_update`:
- heading alignment (a running 2-D Wahba problem): with dv_imu = the integral of a_h since the previous fix and
  dv_gps = the change of the GPS velocity, accumulate C <- lambda C + dv_imu . dv_gps, S <- lambda S + dv_imu x dv_gps;
  (cos theta, sin theta) = (C, S) / |(C, S)|;
- travel direction: u <- normalise(u + heading_gain (A^T g/|g| - u)) while |g| >= min_speed_ms;
- speed and along-track bias: a steady-state two-state Kalman filter (alpha-beta form) on e = |g| - s:
  s <- s + speed_gain e, b <- b - bias_gain e / T (T: seconds since the previous fix);
- walking speed: while walking, s_walk <- s_walk + walk_speed_gain (|g| - s_walk);
- (before gps_update, position_update) the fix's position smoothed with the Doppler and the IMU's step between
  fixes: a 2-state Kalman filter per axis of the true position and the receiver's slowly wandering error
  (Gauss-Markov, pos_sigma_m, pos_tau_s), so an outage starts from a better point than the raw fix (0 s medians:
  car 2.8 -> 2.2 m, replayed walk 2.3 -> 1.8 m, simulated walk 3.0 -> 2.2 m);
- the tilt and the accelerometer's horizontal offsets, a 4-state Kalman filter (tilt_and_offset_update): the
  difference between the IMU's and the GPS's velocity change over the interval is the gravity leak (g times the
  tilt error, fixed in the earth frame) plus the body-frame offsets seen through R(q). Calibration folds the
  offsets into the tilt, which is harmless until the device turns: after a 90 degree turn a 50 mg offset leaks
  ~0.7 m/s^2 into the horizontal. The filter starts knowing that fold (leak = -R_h b) and separates the two as
  the device turns under GPS; both are fed back (the offsets subtracted from every sample, the leak rotated out
  of q), so an outage starts with the true tilt and offsets, and later turns leak nothing.

Tuning (FusedConfig defaults = the board's algorithm.fused_* defaults): chosen on simulator seeds 101-106 (walk,
car) and replay degradations 101-103, never on the seeds benchmarks/accuracy.py reports (0-2, replay 0-4). What
mattered: rest needs a gyro limit of 0.5 degree/s (a car cruising smoothly looked "at rest" at 2 degree/s and the
zero-velocity update stopped it); walking shows as |f| standard deviation above 0.03 g (hand-held real walk
0.04-0.09 g, cars below 0.006 g), and a walker's speed is best held at the learned walking speed rather than
integrated. For the car, the error budget (one MPU-6050 error source at a time) showed that with ideal sensors the
speed prior alone cost 101 m at 60 s (13 m without it: speed_tau_s 0), and that of the sensor errors the
accelerometer offset dominated (102 of 122 m on seeds 104-106); the tilt/offset filter took the car from 122 to
26 m at 60 s there. With the filter on, the Mahony correction while fixes arrive only fights it (21 m with
tilt_tau_s 100 s, 26 m with 20 s), so it is kept weak; none without GPS (a car's sustained accelerations would
pull the tilt away). The board's deadband (0.03125 g) on the along-track acceleration still helps the car (60 s
median 22 -> 34 m with 0.01 g) and leaves the walks unchanged, so it stays. The block median stays available as
`median` (board fused_median: true): a per-sample filter has no blocks, so it is the seed's median of b samples
made sliding, on a vehicle's along-track acceleration (the ring restarts after rest or walking). On car seeds
101-106 it moved the 30 / 60 s medians from 7.5 / 21.6 m to 7.9 / 22.1 m: the MPU-6050 model's noise is
Gaussian, without the spikes (a door slam, a pothole) a median is for, so it is off by default.

The walk's limit: the fix an outage starts from is already ~2.2 m off (the receiver's slowly wandering error, which
the position filter can only partly average out: with a 60 s correlation time a 300 s run holds only a few
independent draws of it, so 10 s medians move by +-0.1-0.2 m between seed sets; compare variants on 36 seeds),
and the hand's slow yaw swings (the simulator's +-10 degrees about the course) turn u although the walker goes
straight; with them switched off in the simulator the 10 s drift falls from 2.1 to 1.2 m. The turn hold (step 3)
takes back part of that. Its settings, 10 s (60 s) medians on walk seeds 101-136, the rate smoothed over 0.3 s:
- turn end 4 degree/s, turn_hold_tau_s 5 / 10 / 20 s: 3.07 / 3.06 / 3.04 m (11.7 / 12.2 / 12.8 m: a slow curve
  arrives later); hold 10 s, end 2 / 4 / 7 / 10 degree/s: 3.06 / 3.06 / 3.01 / 3.01 m; start 8 / 12 / 16
  degree/s: 3.07 / 3.06 / 3.06 m; end 7, hold 8 / 10 / 15 s: 3.04 / 3.01 / 2.99 m (12.1 / 12.2 / 12.6 m);
- the rate smoothed over stat_tau_s (0.5 s) instead: 3.04 m, within the noise, and one parameter fewer.
Tried and dropped, each measured on walk seeds 101-112 (or 101-136) and the replayed real walk:
- no turn while the smoothed rate about Up stays below 7 degree/s (10 s 3.5 -> 3.2 m, but 30 / 60 s
  7.4 -> 8.3 / 14.3 -> 19.9 m: real turns lose their gentle ends);
- the hand's offset from the course (what the GPS pulls on u add up to, less their mean) decaying back to its
  mean during an outage, as a Gauss-Markov process would (time constants 3-20 s): 10 s 3.2 -> 3.2-3.7 m, since
  the pulls see the offset late and noisily (its correlation with the true offset is 0.55);
- ending the walk earlier (a higher variance limit to stop, or a faster variance for it, 0.3 s): within 0.05 m;
- the walker's axis as the principal axis of the horizontal acceleration (the steps surge forwards): exact on
  the simulator's gait (8 degrees), but on the real walk's IMU the axis is 64 degrees off the course in the median
  (its sway and the vertical bob leaking through the tilt dominate): a simulator artefact, not used;
- heading gains 0.08-1.0 (0.3 is best), walking speed gains 0.1-0.3 (0.2 is best).

The state is a flat vector of floats (the C kernel's caller-owned buffer holds the same fields in the same order);
FusedState below names them. One GPS-free pass over the IMU and the GPS updates at their epochs is exactly what the
device does; `estimate` runs it for the simulator's benchmark (codegen.sim.methods registers it as "fused").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from codegen.board.model import FUSED_MEDIAN_MAX
from codegen.kernel.reference import (
    STANDARD_GRAVITY,
    KernelConfig,
    remap_axes,
    tilt_from_gravity,
)


@dataclass(frozen=True)
class FusedConfig:
    """The fused method's parameters (board `algorithm.fused_*`, the C `dr_fused_config`), with units."""

    tilt_tau_s: float = 100.0  # s, time constant of the tilt correction towards gravity (Kp = 1/tau)
    accel_reject_g: float = 0.1  # g, no tilt correction while | |f| - g | exceeds this
    tilt_tau_dark_s: float = 0.0  # s, the same without GPS (no motion acceleration to subtract); 0: none
    steady_accel_ms2: float = 0.3  # m/s^2, the tilt is corrected only while the GPS acceleration changes less
    speed_tau_s: float = 0.0  # s, a vehicle's speed relaxes towards the last GPS speed (0: never)
    gps_timeout_s: float = 2.0  # s, the GPS counts as lost this long after its last fix
    stat_tau_s: float = 0.5  # s, time constant of the motion statistics
    rest_accel_g: float = 0.01  # g, standard deviation of |f| below which the device may be at rest
    rest_gyro_dps: float = 0.5  # degree/s, rate below which the device may be at rest
    rest_time_s: float = 0.4  # s, both below their limits this long = at rest
    bias_tau_s: float = 30.0  # s, time constant of the gyro bias re-estimation at rest
    walk_accel_g: float = 0.03  # g, standard deviation of |f| above which the device is carried by a walker
    min_speed_ms: float = 0.5  # m/s, GPS speeds below this carry no course
    heading_gain: float = 0.3  # per fix, pull of the travel direction towards the GPS course
    align_forget: float = 0.98  # per fix, forgetting factor of the heading alignment sums
    speed_gain: float = 0.5  # per fix, pull of the speed towards the GPS speed
    bias_gain: float = 0.1  # per fix, along-track bias correction per m/s of speed error (times 1/T)
    walk_speed_gain: float = 0.2  # per fix, pull of the walking speed towards the GPS speed
    kf_bias_init_g: float = 0.05  # g, initial sigma of the horizontal accelerometer offsets (body x, y); 0: no filter
    kf_bias_noise: float = 0.001  # m/s^2/sqrt(s), random walk of those offsets
    kf_tilt_noise: float = 0.002  # m/s^2/sqrt(s), random walk of the gravity leak (tilt error times g)
    kf_turn_noise: float = 0.1  # m/s^2 per rad, gravity leak a turn adds (gyro cross-axis and scale errors)
    kf_vel_sigma_ms: float = 0.15  # m/s, GPS Doppler velocity error per axis (with unmodelled motion)
    kf_align_min: float = 20.0  # (m/s)^2, heading alignment sums needed before the filter trusts the frame
    median: float = 0.0  # 1: a vehicle's along-track acceleration is the median of the last b (algorithm.block)
    pos_sigma_m: float = 2.1  # m, the receiver's position error per axis (Gauss-Markov sigma); 0: no smoothing
    pos_tau_s: float = 60.0  # s, its correlation time
    pos_step_sigma_ms: float = 0.1  # m/s, error of the step between fixes (Doppler trapezoid + IMU), per second
    turn_hold_tau_s: float = 10.0  # s, a walker's slow rotations about Up reach u over this (0: at once)
    turn_start_dps: float = 12.0  # degree/s, a walker's turn starts when the smoothed rate about Up exceeds this
    turn_end_dps: float = 7.0  # degree/s, and ends when it falls below this

    @classmethod
    def from_board(cls, board) -> "FusedConfig":
        alg = board.algorithm
        values = {}
        for f in fields(cls):
            name = "fused_" + f.name
            if hasattr(alg, name):
                values[f.name] = float(getattr(alg, name))
        return cls(**values)


# The state vector: name -> offset (the C struct dr_fused_state has the same fields in this order).
STATE_FIELDS = (
    "qw", "qx", "qy", "qz",  # orientation body -> kernel ENU
    "bgx", "bgy", "bgz",  # gyro bias, counts (body frame)
    "mean_f", "var_f", "w2",  # motion statistics: |f| m/s^2, its variance (m/s^2)^2, |omega|^2 (rad/s)^2
    "acc_e", "acc_n",  # motion acceleration from the GPS, kernel frame m/s^2 (the tilt reference subtracts it)
    "steady",  # > 0 while that acceleration changed less than steady_accel_ms2: steady^2 - change^2
    "rest_s",  # s the device has looked at rest
    "ux", "uy",  # travel direction, kernel frame (unit)
    "speed", "bias",  # speed along u m/s, along-track accel bias m/s^2
    "walk_speed",  # m/s, learned walking speed
    "cos_t", "sin_t",  # rotation kernel frame -> true ENU
    "align_c", "align_s",  # heading alignment sums, (m/s)^2
    "dvx", "dvy",  # integral of the kernel-frame horizontal acceleration since the last fix, m/s
    "since_fix",  # s since the last GPS update
    "gps_ve", "gps_vn",  # previous fix's velocity, m/s (true ENU)
    "gps_speed",  # m/s, the last fix's speed (a vehicle's speed relaxes towards it)
    "gps_ok",  # > 0 if the previous fix's velocity has a course: its speed - min_speed_ms
    "pe", "pn",  # position accumulated since the last reset, true ENU m
    "flags",  # 1 at rest, 2 walking, 4 turning (bit field, last sample)
    "bax", "bay",  # accelerometer offsets, body x and y, m/s^2 (subtracted from every sample)
    "m00", "m01", "m10", "m11",  # integral of the horizontal rows of R(q) since the last fix, s
    "turn",  # integral of |rate about Up| since the last fix, rad
    "p00", "p01", "p02", "p03", "p11", "p12", "p13", "p22", "p23", "p33",  # the filter's covariance (upper)
    "fix_ae", "fix_an",  # smoothed position minus the last fix's, true ENU m (where an outage starts from)
    "fix_ee", "fix_en",  # the receiver's position error estimated at the last fix, m
    "fix_pxx", "fix_pxe", "fix_pee",  # their covariance (the same for East and North), m^2
    "dpx", "dpy",  # integral of dvx, dvy since the last fix, m (after the fields the app reads: their offsets stay)
    "rate_up",  # rad/s, the rate about Up smoothed over stat_tau_s
    "held",  # rad, rotation about Up a walker's u has not taken yet
    "med_i", "med_n",  # the median option's ring: next slot, slots filled
) + tuple(f"med{k}" for k in range(FUSED_MEDIAN_MAX))  # the last along-track accelerations (a ring), m/s^2
IDX = {name: i for i, name in enumerate(STATE_FIELDS)}
STATE_LEN = len(STATE_FIELDS)
OUT_LEN = 6


class FusedState:
    """The fused state as named floats (float64 here; float32 in the C kernel and the fallback)."""

    __slots__ = STATE_FIELDS

    def __init__(self):
        for name in STATE_FIELDS:
            setattr(self, name, 0.0)
        self.qw = 1.0
        self.ux = 1.0
        self.cos_t = 1.0

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
    st.w2 = 0.0
    st.rest_s = 0.0
    st.speed = 0.0
    st.bax = st.bay = 0.0
    std_g = body[:, :3].std(axis=0) / kcfg.accel_lsb_per_g
    return bool(np.any(std_g > kcfg.motion_threshold_g))


def process(st: FusedState, samples, dt_us, kcfg: KernelConfig, fcfg: FusedConfig):
    """Steps 1-4 over raw samples (m, 6) held dt_us[k] us each. Returns (out (6,), flags (m,)): out = the
    displacement East, North, Up over the samples (true ENU m, Up 0) and the velocity E, N, U at their end."""
    body = remap_axes(samples, kcfg.axis_map)
    acc = (body[:, :3] * kcfg.accel_ms2_per_lsb).tolist()
    gyr = body[:, 3:].tolist()
    dts = (np.asarray(dt_us, dtype=np.float64) * 1e-6).tolist()
    g = STANDARD_GRAVITY
    gscale = kcfg.gyro_rads_per_lsb
    kp = 1.0 / fcfg.tilt_tau_s
    reject = fcfg.accel_reject_g * g
    kp_dark = 1.0 / fcfg.tilt_tau_dark_s if fcfg.tilt_tau_dark_s > 0.0 else 0.0
    deadband = kcfg.deadband_ms2
    rest_var = (fcfg.rest_accel_g * g) ** 2
    rest_w2 = math.radians(fcfg.rest_gyro_dps) ** 2
    walk_var = (fcfg.walk_accel_g * g) ** 2
    inv_stat = 1.0 / fcfg.stat_tau_s
    inv_bias = 1.0 / fcfg.bias_tau_s
    inv_speed = 1.0 / fcfg.speed_tau_s if fcfg.speed_tau_s > 0.0 else 0.0
    median = kcfg.block if fcfg.median > 0.0 and kcfg.block > 1 else 0
    if median > FUSED_MEDIAN_MAX:
        raise ValueError(f"the median option takes algorithm.block <= {FUSED_MEDIAN_MAX}, not {median}")
    ring = [getattr(st, f"med{k}") for k in range(FUSED_MEDIAN_MAX)]
    flags = np.zeros(len(dts), dtype=np.int8)
    was_walking = bool(int(st.flags) & 2)
    turning = bool(int(st.flags) & 4)
    hold_rate = 1.0 / fcfg.turn_hold_tau_s if fcfg.turn_hold_tau_s > 0.0 else 0.0
    turn_start = math.radians(fcfg.turn_start_dps)
    turn_end = math.radians(fcfg.turn_end_dps)
    pe0, pn0 = st.pe, st.pn
    qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
    for k, dt in enumerate(dts):
        fx, fy, fz = acc[k]
        fx -= st.bax
        fy -= st.bay
        cx, cy, cz = gyr[k]
        wx = (cx - st.bgx) * gscale
        wy = (cy - st.bgy) * gscale
        wz = (cz - st.bgz) * gscale
        # motion statistics
        nf = math.sqrt(fx * fx + fy * fy + fz * fz)
        alpha = dt * inv_stat
        if alpha > 1.0:
            alpha = 1.0
        st.mean_f += alpha * (nf - st.mean_f)
        d = nf - st.mean_f
        st.var_f += alpha * (d * d - st.var_f)
        st.w2 += alpha * (wx * wx + wy * wy + wz * wz - st.w2)
        # rotation matrix rows of q (body -> kernel ENU)
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        ae = r00 * fx + r01 * fy + r02 * fz
        an = r10 * fx + r11 * fy + r12 * fz
        # rest: still (variance, rate) and no horizontal acceleration beyond the deadband (a smooth push is no rest)
        if st.var_f < rest_var and st.w2 < rest_w2 and ae * ae + an * an < deadband * deadband:
            st.rest_s += dt
        else:
            st.rest_s = 0.0
        rest = st.rest_s >= fcfg.rest_time_s
        walking = st.var_f > walk_var
        if was_walking and not walking:
            st.speed = 0.0  # the steps stopped, and so did the walker (a vehicle he boards starts from 0 too)
        was_walking = walking
        # travel direction turned by the rate about Up (uncorrected gyro: the tilt correction is not a turn)
        r = r20 * wx + r21 * wy + r22 * wz
        st.turn += abs(r) * dt
        st.rate_up += alpha * (r - st.rate_up)
        da = r * dt
        if walking and hold_rate > 0.0:
            # a walker's turns are quick; the hand's slow swings about the course are not turns: u takes a turn at
            # once (with what it held), a slow rotation over turn_hold_tau_s (a swing that returns cancels)
            if abs(st.rate_up) > turn_start:
                turning = True
            elif abs(st.rate_up) < turn_end:
                turning = False
            st.held += da
            da = st.held if turning else st.held * min(1.0, dt * hold_rate)
            st.held -= da
        else:
            turning = False
            da += st.held
            st.held = 0.0
        flags[k] = (1 if rest else 0) | (2 if walking else 0) | (4 if turning else 0)
        # u rotated by da (to second order: a turn's held part can be tens of degrees)
        cd = 1.0 - 0.5 * da * da
        sd = da * (1.0 - da * da * (1.0 / 6.0))
        ux = cd * st.ux - sd * st.uy
        uy = cd * st.uy + sd * st.ux
        inv = 1.0 / math.sqrt(ux * ux + uy * uy)
        st.ux = ux * inv
        st.uy = uy * inv
        # speed along u
        if rest or walking:
            st.med_i = st.med_n = 0.0  # the median ring restarts when the vehicle branch is entered again
        if rest:
            st.speed = 0.0
            st.bgx += dt * inv_bias * (cx - st.bgx)
            st.bgy += dt * inv_bias * (cy - st.bgy)
            st.bgz += dt * inv_bias * (cz - st.bgz)
        elif walking:
            st.speed = st.walk_speed
        else:
            a = ae * st.ux + an * st.uy
            if median:  # the seed's block median, sliding: the median of the last b along-track accelerations
                a = _ring_median(st, ring, a, median)
            a -= st.bias
            if abs(a) < deadband:  # the board's deadband (algorithm.deadband_g), on the along-track acceleration
                a = 0.0
            st.speed += (a + (st.gps_speed - st.speed) * inv_speed) * dt
            if st.speed < 0.0:
                st.speed = 0.0
        st.dpx += (st.dvx + 0.5 * ae * dt) * dt
        st.dpy += (st.dvy + 0.5 * an * dt) * dt
        st.dvx += ae * dt
        st.dvy += an * dt
        st.m00 += r00 * dt
        st.m01 += r01 * dt
        st.m10 += r10 * dt
        st.m11 += r11 * dt
        st.since_fix += dt
        # position, true ENU
        ve = st.speed * (st.cos_t * st.ux - st.sin_t * st.uy)
        vn = st.speed * (st.sin_t * st.ux + st.cos_t * st.uy)
        st.pe += ve * dt
        st.pn += vn * dt
        # tilt correction towards gravity: e = f/|f| x up_body
        # (while fixes arrive, minus the motion acceleration they show: f_c = f - R^T [acc_e, acc_n, 0])
        if st.since_fix < fcfg.gps_timeout_s:
            gain = kp if st.steady > 0.0 else 0.0
            cx = fx - (r00 * st.acc_e + r10 * st.acc_n)
            cy = fy - (r01 * st.acc_e + r11 * st.acc_n)
            cz = fz - (r02 * st.acc_e + r12 * st.acc_n)
            nc = math.sqrt(cx * cx + cy * cy + cz * cz)
        else:
            cx, cy, cz, nc = fx, fy, fz, nf
            gain = kp_dark
        if nc > 0.0 and abs(nc - g) < reject:
            inf = gain / nc
            ex = (cy * r22 - cz * r21) * inf
            ey = (cz * r20 - cx * r22) * inf
            ez = (cx * r21 - cy * r20) * inf
            wx += ex
            wy += ey
            wz += ez
        # q <- q (x) [1, omega dt / 2], renormalised
        hx = 0.5 * wx * dt
        hy = 0.5 * wy * dt
        hz = 0.5 * wz * dt
        nw = qw - qx * hx - qy * hy - qz * hz
        nx = qx + qw * hx + qy * hz - qz * hy
        ny = qy + qw * hy - qx * hz + qz * hx
        nz = qz + qw * hz + qx * hy - qy * hx
        inv = 1.0 / math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        qw, qx, qy, qz = nw * inv, nx * inv, ny * inv, nz * inv
    st.qw, st.qx, st.qy, st.qz = qw, qx, qy, qz
    for k in range(FUSED_MEDIAN_MAX):
        setattr(st, f"med{k}", ring[k])
    st.flags = float(flags[-1]) if len(flags) else st.flags
    ve = st.speed * (st.cos_t * st.ux - st.sin_t * st.uy)
    vn = st.speed * (st.sin_t * st.ux + st.cos_t * st.uy)
    out = np.array([st.pe - pe0, st.pn - pn0, 0.0, ve, vn, 0.0])
    return out, flags


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
        st.fix_ae = st.fix_an = st.fix_ee = st.fix_en = 0.0
        st.fix_pxx = st.fix_pee = sigma2
        st.fix_pxe = -sigma2
        return
    x = t / fcfg.pos_tau_s
    phi = 1.0 - x * (1.0 - x * (0.5 - x * (1.0 / 6.0)))
    step = fcfg.pos_step_sigma_ms * t
    pxx = st.fix_pxx + step * step
    pxe = phi * st.fix_pxe
    pee = phi * phi * st.fix_pee + sigma2 * (1.0 - phi * phi)
    # the IMU's correction to the trapezoid: what the acceleration adds to T (v0 + v1) / 2, true ENU
    cx = st.dpx - 0.5 * t * st.dvx
    cy = st.dpy - 0.5 * t * st.dvy
    ce = st.cos_t * cx - st.sin_t * cy
    cn = st.sin_t * cx + st.cos_t * cy
    ae = st.fix_ae + 0.5 * t * (st.gps_ve + ve) + ce - de  # x_hat- - y, East
    an = st.fix_an + 0.5 * t * (st.gps_vn + vn) + cn - dn
    ee = phi * st.fix_ee
    en = phi * st.fix_en
    s = pxx + 2.0 * pxe + pee
    kx = (pxx + pxe) / s
    ke = (pxe + pee) / s
    st.fix_ae = ae - kx * (ae + ee)  # innovation y - x_hat- - e_hat- = -(a + e)
    st.fix_an = an - kx * (an + en)
    st.fix_ee = ee - ke * (ae + ee)
    st.fix_en = en - ke * (an + en)
    st.fix_pxx = pxx - kx * kx * s
    st.fix_pxe = pxe - kx * ke * s
    st.fix_pee = pee - ke * ke * s


def gps_update(st: FusedState, ve: float, vn: float, fcfg: FusedConfig) -> None:
    """One GPS fix's Doppler velocity (true ENU East, North, m/s; 0, 0 when the course is undefined)."""
    speed = math.sqrt(ve * ve + vn * vn)
    moving = speed >= fcfg.min_speed_ms
    t = st.since_fix
    # heading alignment from velocity changes (previous fix within 2 s and both fixes with a course)
    if st.gps_ok > 0.0 and moving and 0.0 < t < fcfg.gps_timeout_s:
        gx = ve - st.gps_ve
        gy = vn - st.gps_vn
        lam = fcfg.align_forget
        st.align_c = lam * st.align_c + st.dvx * gx + st.dvy * gy
        st.align_s = lam * st.align_s + st.dvx * gy - st.dvy * gx
        norm = math.sqrt(st.align_c * st.align_c + st.align_s * st.align_s)
        if norm > 0.0:
            st.cos_t = st.align_c / norm
            st.sin_t = st.align_s / norm
    if moving:
        # GPS course in the kernel frame: A^T g / |g|
        gx = (st.cos_t * ve + st.sin_t * vn) / speed
        gy = (-st.sin_t * ve + st.cos_t * vn) / speed
        ux = st.ux + fcfg.heading_gain * (gx - st.ux)
        uy = st.uy + fcfg.heading_gain * (gy - st.uy)
        norm = math.sqrt(ux * ux + uy * uy)
        if norm > 0.0:
            st.ux, st.uy = ux / norm, uy / norm
        if int(st.flags) & 2:
            st.walk_speed += fcfg.walk_speed_gain * (speed - st.walk_speed)
    e = speed - st.speed
    st.speed += fcfg.speed_gain * e
    if t > 0.0 and not int(st.flags) & 3:
        st.bias -= fcfg.bias_gain * e / t
    if st.gps_ok > 0.0 and moving and 0.0 < t < fcfg.gps_timeout_s:
        # the motion acceleration over the last interval, into the kernel frame (A^T)
        me = (ve - st.gps_ve) / t
        mn = (vn - st.gps_vn) / t
        ae = st.cos_t * me + st.sin_t * mn
        an = -st.sin_t * me + st.cos_t * mn
    else:
        ae = an = 0.0
    tilt_and_offset_update(st, ve, vn, moving, t, fcfg)
    de = ae - st.acc_e
    dn = an - st.acc_n
    st.steady = fcfg.steady_accel_ms2 * fcfg.steady_accel_ms2 - (de * de + dn * dn)
    st.acc_e, st.acc_n = ae, an
    st.gps_ve, st.gps_vn = ve, vn
    st.gps_speed = speed
    st.gps_ok = speed - fcfg.min_speed_ms
    st.dvx = st.dvy = st.dpx = st.dpy = 0.0
    st.m00 = st.m01 = st.m10 = st.m11 = st.turn = 0.0
    st.since_fix = 0.0


# the covariance's upper triangle in STATE_FIELDS order: (row, column) -> field
COVARIANCE_FIELDS = ("p00", "p01", "p02", "p03", "p11", "p12", "p13", "p22", "p23", "p33")
_PIJ = {(i, j): COVARIANCE_FIELDS[n] for n, (i, j) in enumerate((i, j) for i in range(4) for j in range(i, 4))}


def tilt_and_offset_update(st: FusedState, ve: float, vn: float, moving: bool, t: float, fcfg: FusedConfig) -> None:
    """The GPS-aided filter of the gravity leak and the horizontal accelerometer offsets (4 states).

    Over the interval T since the previous fix the IMU's kernel-frame horizontal velocity change dv_imu (from the
    samples minus the estimated offsets) and the GPS's dv_gps (rotated into the kernel frame) differ by
        z = (dv_imu - dv_gps) / T = d + (M / T) b + noise,   M = integral of the horizontal rows of R(q) dt,
    d the gravity leak (g times the tilt error; fixed in the earth frame while the gyro is perfect) and b the
    remaining offsets of the accelerometer's x, y axes (fixed in the body). Calibration folds b into the tilt
    (d = -R_h b at that moment), so the filter starts with that correlation; a turn tells them apart. Process noise
    per interval: kf_tilt_noise^2 T + (kf_turn_noise turn)^2 on d, kf_bias_noise^2 T on b; measurement noise
    2 kf_vel_sigma_ms^2 / T^2 per axis. The estimate is fed back at once (b into bax, bay; d as a small rotation
    of q about the kernel frame's horizontal axes) and the error state returns to zero."""
    if fcfg.kf_bias_init_g <= 0.0:
        return
    if st.p22 <= 0.0:  # the first fix after calibration: start the filter
        var = (fcfg.kf_bias_init_g * STANDARD_GRAVITY) ** 2
        qw, qx, qy, qz = st.qw, st.qx, st.qy, st.qz
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        st.p00 = var * (r00 * r00 + r01 * r01)
        st.p01 = var * (r00 * r10 + r01 * r11)
        st.p11 = var * (r10 * r10 + r11 * r11)
        st.p02, st.p03, st.p12, st.p13 = -var * r00, -var * r01, -var * r10, -var * r11
        st.p22 = st.p33 = var
        st.p23 = 0.0
        return
    if t <= 0.0:
        return
    qd = fcfg.kf_tilt_noise * fcfg.kf_tilt_noise * t + (fcfg.kf_turn_noise * st.turn) ** 2
    qb = fcfg.kf_bias_noise * fcfg.kf_bias_noise * t
    st.p00 += qd
    st.p11 += qd
    st.p22 += qb
    st.p33 += qb
    norm = math.sqrt(st.align_c * st.align_c + st.align_s * st.align_s)
    if not (st.gps_ok > 0.0 and moving and t < fcfg.gps_timeout_s and norm >= fcfg.kf_align_min):
        return
    inv_t = 1.0 / t
    gx = ve - st.gps_ve
    gy = vn - st.gps_vn
    z0 = (st.dvx - (st.cos_t * gx + st.sin_t * gy)) * inv_t
    z1 = (st.dvy - (-st.sin_t * gx + st.cos_t * gy)) * inv_t
    h = ((st.m00 * inv_t, st.m01 * inv_t), (st.m10 * inv_t, st.m11 * inv_t))
    p = [[getattr(st, _PIJ[(min(i, j), max(i, j))]) for j in range(4)] for i in range(4)]
    # PH^T (4 x 2): H = [I2 | h]
    pht = [[p[i][a] + p[i][2] * h[a][0] + p[i][3] * h[a][1] for a in range(2)] for i in range(4)]
    r = 2.0 * fcfg.kf_vel_sigma_ms * fcfg.kf_vel_sigma_ms * inv_t * inv_t
    s00 = pht[0][0] + h[0][0] * pht[2][0] + h[0][1] * pht[3][0] + r
    s01 = pht[0][1] + h[0][0] * pht[2][1] + h[0][1] * pht[3][1]
    s11 = pht[1][1] + h[1][0] * pht[2][1] + h[1][1] * pht[3][1] + r
    inv_det = 1.0 / (s00 * s11 - s01 * s01)
    i00, i01, i11 = s11 * inv_det, -s01 * inv_det, s00 * inv_det
    gain = [(row[0] * i00 + row[1] * i01, row[0] * i01 + row[1] * i11) for row in pht]  # K = PH^T S^-1
    x = [kr[0] * z0 + kr[1] * z1 for kr in gain]
    for i in range(4):
        for j in range(i, 4):
            name = _PIJ[(i, j)]
            setattr(st, name, getattr(st, name) - (gain[i][0] * pht[j][0] + gain[i][1] * pht[j][1]))
    st.bax += x[2]
    st.bay += x[3]
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

