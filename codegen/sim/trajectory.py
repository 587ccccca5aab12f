"""Trajectories with exact truth: position, velocity, acceleration and orientation on a fine time grid.

A trajectory is sampled at `rate_hz` (1 kHz by default) in the earth frame ENU (x East, y North, z Up) and the
board frame (the MPU-6050 axes after the board's axis remap). Orientation is the carrier's (the vehicle's, the
walker's hand or thigh) as Euler angles, R_carrier->ENU = Rz(yaw) · Ry(pitch) · Rx(roll), times a constant
mounting of the board on the carrier: R_board->ENU = R_carrier->ENU · mount. The board's angular rate follows
from the Euler rates by the standard kinematic relation, so integrating `gyro` from `rotation(0)` reproduces
`rotation(k)`.

Every scenario starts with the device at rest (calibration needs `rest_s` seconds of it) and is built from a
short script of commanded longitudinal acceleration / yaw rate / grade segments, smoothed so that jerk stays finite,
then integrated. The scripts are drawn from a seeded generator: the same seed gives the same trajectory.

    trajectory = make_scenario("walk", seed=1)
    trajectory.specific_force()   # (N, 3) m/s^2 in the board frame: +g on the up axis at rest, flat
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import oaconvolve

from codegen.board.model import STANDARD_GRAVITY
from codegen.sim import SIMULATED

TRUTH_RATE_HZ = 1000.0
GRADE_GRID_M = 0.012  # m of road per sample of the car's grade profile (its 20 s smoothing at 12 m/s: ~240 m)
SCENARIOS = SIMULATED


class SampledTruth:
    """Position and velocity between the samples of a truth (`t`, `pos`, `vel`: linear interpolation), shared by the
    simulated trajectory and the recorded truths (codegen/sim/replay.py, codegen/sim/comma.py)."""

    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray

    def at(self, times) -> np.ndarray:
        """ENU position at arbitrary times, (len(times), 3)."""
        times = np.asarray(times, dtype=float)
        return np.stack([np.interp(times, self.t, self.pos[:, i]) for i in range(3)], axis=-1)

    def velocity_at(self, times) -> np.ndarray:
        """ENU velocity at arbitrary times, (len(times), 3)."""
        times = np.asarray(times, dtype=float)
        return np.stack([np.interp(times, self.t, self.vel[:, i]) for i in range(3)], axis=-1)


@dataclass(frozen=True)
class Trajectory(SampledTruth):
    """Exact truth on a uniform grid. Arrays are float64; `t` in s from the start of the run."""

    name: str
    t: np.ndarray  # (N,) s
    pos: np.ndarray  # (N, 3) m, ENU, from the start point
    vel: np.ndarray  # (N, 3) m/s, ENU
    acc: np.ndarray  # (N, 3) m/s^2, ENU, kinematic (no gravity)
    euler: np.ndarray  # (N, 3) rad: roll, pitch, yaw of the board (R = Rz(yaw) Ry(pitch) Rx(roll))
    gyro: np.ndarray  # (N, 3) rad/s, board frame
    rest_s: float  # s at rest at the start (for calibration)
    events: dict = field(default_factory=dict)  # scenario-specific marks, e.g. push start/end times
    mount: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3, 3) R board->carrier, constant

    @property
    def rate_hz(self) -> float:
        return 1.0 / (self.t[1] - self.t[0])

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def rotation(self, index=slice(None)) -> np.ndarray:
        """R board->ENU, (..., 3, 3)."""
        return euler_to_matrix(self.euler[index]) @ self.mount

    def specific_force(self) -> np.ndarray:
        """What an ideal accelerometer measures, in the board frame: R^T (a + g·Up), m/s^2."""
        f_enu = self.acc.copy()
        f_enu[:, 2] += STANDARD_GRAVITY
        return np.einsum("nji,nj->ni", self.rotation(), f_enu)


def euler_to_matrix(euler: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) for euler (..., 3) = (roll, pitch, yaw) in rad; returns (..., 3, 3)."""
    euler = np.asarray(euler, dtype=float)
    cr, sr = np.cos(euler[..., 0]), np.sin(euler[..., 0])
    cp, sp = np.cos(euler[..., 1]), np.sin(euler[..., 1])
    cy, sy = np.cos(euler[..., 2]), np.sin(euler[..., 2])
    r = np.empty(euler.shape[:-1] + (3, 3))
    r[..., 0, 0] = cy * cp
    r[..., 0, 1] = cy * sp * sr - sy * cr
    r[..., 0, 2] = cy * sp * cr + sy * sr
    r[..., 1, 0] = sy * cp
    r[..., 1, 1] = sy * sp * sr + cy * cr
    r[..., 1, 2] = sy * sp * cr - cy * sr
    r[..., 2, 0] = -sp
    r[..., 2, 1] = cp * sr
    r[..., 2, 2] = cp * cr
    return r


def body_rates(euler: np.ndarray, dt: float) -> np.ndarray:
    """Board-frame angular rate (rad/s) from Euler angles sampled every dt s (second-order differences)."""
    d = np.gradient(np.unwrap(euler, axis=0), dt, axis=0, edge_order=2)
    roll, pitch = euler[:, 0], euler[:, 1]
    droll, dpitch, dyaw = d[:, 0], d[:, 1], d[:, 2]
    p = droll - dyaw * np.sin(pitch)
    q = dpitch * np.cos(roll) + dyaw * np.sin(roll) * np.cos(pitch)
    r = -dpitch * np.sin(roll) + dyaw * np.cos(roll) * np.cos(pitch)
    return np.stack([p, q, r], axis=-1)


def gaussian_filter1d(x: np.ndarray, sigma: float, axis: int = 0, mode: str = "nearest") -> np.ndarray:
    """Gaussian smoothing along axis 0 with edge values held (FFT overlap-add: long kernels stay cheap)."""
    x = np.asarray(x, dtype=float)
    half = int(4 * sigma) + 1
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    k /= k.sum()
    padded = np.concatenate([np.repeat(x[:1], half, axis=0), x, np.repeat(x[-1:], half, axis=0)], axis=0)
    if x.ndim == 2:
        k = k[:, None]
    return oaconvolve(padded, k, mode="valid", axes=0)


def _cumtrapz(y: np.ndarray, dt: float) -> np.ndarray:
    out = np.zeros_like(y)
    out[1:] = np.cumsum(0.5 * (y[1:] + y[:-1]) * dt, axis=0)
    return out


def _segments(n: int, rate: float, script: list[tuple[float, float]], start: int) -> np.ndarray:
    """Piecewise-constant command: script of (duration s, value) from sample `start`; 0 elsewhere."""
    out = np.zeros(n)
    k = start
    for duration, value in script:
        m = int(round(duration * rate))
        out[k : k + m] = value
        k += m
    return out


def _assemble(
    name: str,
    rate: float,
    rest_s: float,
    speed: np.ndarray,
    course: np.ndarray,
    climb: np.ndarray,
    extra_vel: np.ndarray,
    attitude: np.ndarray,
    events: dict | None = None,
    mount: np.ndarray | None = None,
) -> Trajectory:
    """Velocity from speed along course (rad from North, clockwise) + climb + extra ENU velocity; then integrate.
    `attitude` is the carrier's (Euler angles); `mount` (3, 3) turns the board into the carrier's frame."""
    n = len(speed)
    dt = 1.0 / rate
    t = np.arange(n) * dt
    vel = np.stack([speed * np.sin(course), speed * np.cos(course), climb], axis=-1) + extra_vel
    acc = np.gradient(vel, dt, axis=0, edge_order=2)
    pos = _cumtrapz(vel, dt)
    mount = np.eye(3) if mount is None else np.asarray(mount, dtype=float)
    gyro = body_rates(attitude, dt) @ mount  # board frame: mount^T omega, row by row
    return Trajectory(name, t, pos, vel, acc, attitude, gyro, rest_s, events or {}, mount)


def static(duration: float = 120.0, seed: int = 0, rate: float = TRUTH_RATE_HZ) -> Trajectory:
    """The device lying still, slightly tilted, for `duration` s."""
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    attitude = np.tile([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-np.pi, np.pi)], (n, 1))
    zero = np.zeros(n)
    return _assemble("static", rate, duration, zero, zero, zero, np.zeros((n, 3)), attitude)


def push(count: int = 12, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ) -> Trajectory:
    """The seed's test: the device on a table or cart, pushed 1..10 m in a straight line, resting in between.

    The device starts with its x axis pointing East (the seed's yaw-0 frame is then ENU, so its error E means what
    it meant on the seed's bench); the cart is turned by hand between pushes.

    Each push has a raised-cosine speed profile (zero acceleration at both ends); events["pushes"] lists
    (start s, end s) of each push, so the seed's error E can be measured per push.
    """
    rng = np.random.default_rng(seed)
    lengths = rng.uniform(1.0, 10.0, count)
    durations = np.clip(lengths / rng.uniform(0.5, 1.2, count), 3.0, 15.0)
    rests = rng.uniform(4.0, 8.0, count)
    total = rest_s + float(np.sum(durations + rests)) + 2.0
    n = int(round(total * rate)) + 1
    t = np.arange(n) / rate
    speed = np.zeros(n)
    course = np.zeros(n)
    pushes = []
    start = rest_s
    heading = np.pi / 2  # the first push goes East, along the board's x axis, as on the seed's test bench
    course[:] = heading
    for length, duration, rest in zip(lengths, durations, rests):
        inside = (t >= start) & (t < start + duration)
        phase = (t[inside] - start) / duration
        speed[inside] = length / duration * (1.0 - np.cos(2 * np.pi * phase))  # integrates to `length`
        pushes.append((start, start + duration, float(length)))
        start += duration + rest
        heading += rng.choice([-1, 1]) * rng.uniform(0.3, 2.5)
        course[t >= start - rest / 2] = heading
    # the cart is turned by hand in the middle of each rest; the gyro sees a quick rotation, the cart stays put
    yaw = gaussian_filter1d(np.pi / 2 - course, 0.4 * rate, mode="nearest")
    attitude = np.stack([np.full(n, 0.02), np.full(n, -0.015), yaw], axis=-1)
    zero = np.zeros(n)
    return _assemble("push", rate, rest_s, speed, course, zero, np.zeros((n, 3)), attitude, {"pushes": pushes})


CARRIES = ("hand", "pocket", "backpack")


HAND_TREMOR_MG = (11.0, 27.0)  # |f| shaking of a hand holding a device still: 22 real hand-held walks outside ../shared/data
HAND_TREMOR_HZ = (1.5, 12.0)  # the arm's postural sway up to physiological tremor (8-12 Hz)
HAND_BOB_M = 0.006  # the step bob a holding arm passes on: gnss-imu-walk's |f| shaking while walking (~65 mg)


def walk(duration: float = 300.0, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ,
         carry: str = "hand", stands: bool = False) -> Trajectory:
    """A pedestrian: ~1.4 m/s with steps at ~1.9 Hz (vertical bob, forward surge, sideways sway), turns of
    30..120 degrees, stops at crossings. Where the device is (`carry`):

    - "hand": held in front, screen up and tilted ~25 degrees towards the face, wandering slowly; the hand turns
      it about the course and jiggles it with every step;
    - "pocket": in a front trouser pocket, riding the thigh: the thigh swings about the hip by ~+-22 degrees at
      the stride rate (half the step rate; hip flexion-extension in normal gait spans ~40-45 degrees), the pocket
      ~25 cm below the hip joint, the device upright or upside down, screen in or out, a little askew;
    - "backpack": in a bag on the back, in any orientation: the trunk leans forward ~8 degrees, twists about the
      vertical and rolls at the stride rate, bobs and pitches with each step, ~15 cm behind and 45 cm above the
      hips.

    With `stands` (a hand only) the walker stops at half the legs' ends for 10-60 s, holding the device, and the
    hand trembles (HAND_TREMOR_MG of |f| shaking, drawn per seed, in HAND_TREMOR_HZ) from the moment it picks the
    device up. events: "carry", "mount" (the rotation board -> carrier); with stands "stands" ((start s, end s) of
    each, the speed command's) and "tremor_mg".
    """
    from scipy.spatial.transform import Rotation

    if carry not in CARRIES:
        raise ValueError(f"unknown carry {carry!r}; choose from {', '.join(CARRIES)}")
    if stands and carry != "hand":
        raise ValueError("stands are modelled for a device held in a hand only")
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate
    start = int(rest_s * rate)
    # speed: walk / stop segments
    script_v, script_w = [], []
    standing = []
    elapsed = rest_s
    while elapsed < duration:
        leg = rng.uniform(15.0, 40.0)
        script_v.append((leg, rng.uniform(1.2, 1.6)))
        turn = np.radians(rng.uniform(30, 120)) * rng.choice([-1, 1])
        turn_s = rng.uniform(1.5, 3.0)
        script_w += [(leg - turn_s, rng.normal(0.0, 0.01)), (turn_s, turn / turn_s)]
        elapsed += leg
        if rng.random() < (0.5 if stands else 0.35):
            stop = rng.uniform(10.0, 60.0) if stands else rng.uniform(3.0, 8.0)
            standing.append((elapsed, elapsed + stop))
            script_v.append((stop, 0.0))
            script_w.append((stop, 0.0))
            elapsed += stop
    v_cmd = gaussian_filter1d(_segments(n, rate, script_v, start), 0.5 * rate, mode="nearest")
    w_cmd = gaussian_filter1d(_segments(n, rate, script_w, start), 0.3 * rate, mode="nearest")
    course0 = rng.uniform(0, 2 * np.pi)
    course = course0 + np.cumsum(w_cmd) / rate
    moving = np.clip(v_cmd / 1.4, 0.0, 1.2)
    step_hz = 1.9 + 0.1 * rng.standard_normal()
    phase = 2 * np.pi * step_hz * (t - rest_s)
    speed = v_cmd + 0.15 * moving * np.sin(phase)
    bob = HAND_BOB_M if stands else 0.025  # m: the body's ~2.5 cm vertical bob, or what a holding arm passes on
    climb = bob * 2 * np.pi * step_hz * moving * np.cos(phase)
    sway = 0.08 * moving * np.sin(phase / 2)  # sideways, half the step rate
    extra = np.stack([sway * np.cos(course), -sway * np.sin(course), np.zeros(n)], axis=-1)
    heading = np.pi / 2 - course
    events = {"carry": carry}
    if carry == "hand":
        # tilted ~25 degrees towards the face, wandering slowly; yaw follows the course with an offset
        wander = gaussian_filter1d(rng.standard_normal((n, 3)), 2.0 * rate, axis=0, mode="nearest") * 80
        settle = np.clip((t - rest_s + 2.0) / 2.0, 0.0, 1.0)
        settle = settle * settle * (3.0 - 2.0 * settle)  # picked up from the table over 2 s before walking
        roll = settle * (np.radians(3) * wander[:, 0] + np.radians(1.5) * moving * np.sin(phase + 0.7))
        pitch = settle * (np.radians(-25) + np.radians(5) * wander[:, 1] + np.radians(2) * moving * np.sin(phase))
        yaw = heading + np.radians(10) * settle * wander[:, 2]
        attitude = np.stack([roll, pitch, yaw], axis=-1)
        if not stands:
            return _assemble("walk", rate, rest_s, speed, course, climb, extra, attitude, events)
        # the hand's tremor: a displacement whose acceleration has HAND_TREMOR_MG rms on every axis (|f| sees the
        # vertical one), faded in as the device is picked up
        tremor_mg = rng.uniform(*HAND_TREMOR_MG)
        shake = np.stack([_band_noise(rng, n, rate, *HAND_TREMOR_HZ) for _ in range(3)], axis=-1)
        accel = np.gradient(np.gradient(shake, 1.0 / rate, axis=0), 1.0 / rate, axis=0)
        shake *= tremor_mg * 1e-3 * STANDARD_GRAVITY / accel.std(axis=0)
        extra = extra + np.gradient(shake * settle[:, None], 1.0 / rate, axis=0, edge_order=2)
        events.update(stands=standing, tremor_mg=tremor_mg)
        return _assemble("walk-stand", rate, rest_s, speed, course, climb, extra, attitude, events)
    stride = phase / 2 + rng.uniform(0, 2 * np.pi)  # one leg, or the trunk's left-right cycle
    if carry == "pocket":
        thigh = np.radians(5.0) + np.radians(rng.uniform(20.0, 24.0)) * moving * np.sin(stride)
        attitude = np.stack([np.zeros(n), thigh, heading], axis=-1)
        lever = np.array([0.06, 0.0, -0.25])  # the pocket on the front of the thigh, below the hip joint
        screen = rng.choice([-1.0, 1.0])  # screen facing forwards or towards the thigh
        top = rng.choice([-1.0, 1.0])  # the device's top up or down the thigh
        y_dev = np.array([0.0, 0.0, top])
        z_dev = np.array([screen, 0.0, 0.0])
        base = np.stack([np.cross(y_dev, z_dev), y_dev, z_dev], axis=-1)  # columns: device axes in the thigh frame
        mount = base @ Rotation.from_rotvec(rng.normal(0.0, np.radians(6.0), 3)).as_matrix()
    else:  # backpack
        lean = np.radians(rng.uniform(5.0, 11.0))
        roll = np.radians(2.0) * moving * np.sin(stride)
        pitch = lean * np.clip((t - rest_s + 2.0) / 2.0, 0.0, 1.0) + np.radians(1.5) * moving * np.sin(phase)
        yaw = heading + np.radians(4.0) * moving * np.sin(stride + 0.5)
        attitude = np.stack([roll, pitch, yaw], axis=-1)
        lever = np.array([-0.15, 0.0, 0.45])
        mount = Rotation.random(random_state=rng).as_matrix()
    arm = euler_to_matrix(attitude) @ lever
    extra += np.gradient(arm - arm[0], 1.0 / rate, axis=0, edge_order=2)
    events["mount"] = mount
    return _assemble(f"walk-{carry}", rate, rest_s, speed, course, climb, extra, attitude, events, mount=mount)


def _stops_and_turns(rng, rest_s: float, duration: float, *, cruise_ms, accel_ms2, cruise_s, stop_share: float,
                     turn_ms: float, brake_ms2, wait_s, turn_s):
    """A ride as segment scripts (seconds, value): speed up to a cruise, cruise, brake, then either stop for a while
    (a share `stop_share` of the time) or turn by 60..100 degrees at `turn_ms`; repeated until `duration`. Returns
    the along-track acceleration, the turn rate, the pedalling (1 while speeding up or cruising) and the cruising (1
    while cruising) scripts."""
    script_a, script_w, script_p, script_c = [], [], [], []
    v = 0.0
    elapsed = rest_s
    while elapsed < duration:
        target = rng.uniform(*cruise_ms)
        accel = rng.uniform(*accel_ms2)
        ramp = (target - v) / accel
        cruise = rng.uniform(*cruise_s)
        slow_to = 0.0 if rng.uniform() < stop_share else turn_ms
        brake = rng.uniform(*brake_ms2)
        brake_s = (target - slow_to) / brake
        script_a += [(ramp, accel), (cruise, 0.0), (brake_s, -brake)]
        script_w += [(ramp + cruise + brake_s, 0.0)]
        script_p += [(ramp + cruise, 1.0), (brake_s, 0.0)]
        script_c += [(ramp, 0.0), (cruise, 1.0), (brake_s, 0.0)]
        elapsed += ramp + cruise + brake_s
        if slow_to == 0.0:
            wait = rng.uniform(*wait_s)
            script_a.append((wait, 0.0))
            script_w.append((wait, 0.0))
            script_p.append((wait, 0.0))
            script_c.append((wait, 0.0))
            elapsed += wait
        else:
            turn = np.radians(rng.uniform(60, 100)) * rng.choice([-1, 1])
            seconds = rng.uniform(*turn_s)
            script_a.append((seconds, 0.0))
            script_w.append((seconds, turn / seconds))
            script_p.append((seconds, 0.0))
            script_c.append((seconds, 0.0))
            elapsed += seconds
        v = slow_to
    return script_a, script_w, script_p, script_c


def bike(duration: float = 360.0, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ) -> Trajectory:
    """A cyclist with the device on the handlebar stem, screen up and tilted back ~20 degrees.

    Cruise 4..7 m/s, accelerating at 0.4..1 m/s^2 and braking at 1..2 m/s^2, turns of 60..100 degrees at ~3.5 m/s
    leaning into them (tan(lean) = lateral acceleration / g), stops of 5..30 s at lights with the bike leaning on
    the rider's foot by ~8 degrees; pedalling at 1.2..1.5 Hz while speeding up or cruising rocks the bike by
    ~1.5 degrees and surges it; the frame has no suspension: the road (ISO 8608 class A, a smooth cycle path or
    asphalt) reaches it through the tyres only (a 12 kg frame share on 100 kN/m tyres: ~15 Hz, lightly damped).
    """
    from codegen.sim import vibration as vib

    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate
    start = int(rest_s * rate)
    script_a, script_w, script_p, _ = _stops_and_turns(
        rng, rest_s, duration, cruise_ms=(4.0, 7.0), accel_ms2=(0.4, 1.0), cruise_s=(15.0, 45.0), stop_share=0.4,
        turn_ms=3.5, brake_ms2=(1.0, 2.0), wait_s=(5.0, 30.0), turn_s=(3.0, 5.0))
    a_cmd = gaussian_filter1d(_segments(n, rate, script_a, start), 0.4 * rate, mode="nearest")
    w_cmd = gaussian_filter1d(_segments(n, rate, script_w, start), 0.5 * rate, mode="nearest")
    pedal = gaussian_filter1d(_segments(n, rate, script_p, start), 0.5 * rate, mode="nearest")
    cadence = rng.uniform(1.2, 1.5)
    crank = 2 * np.pi * cadence * (t - rest_s)
    speed = np.maximum(np.cumsum(a_cmd) / rate + 0.08 * pedal * np.sin(2 * crank), 0.0)
    course = rng.uniform(0, 2 * np.pi) + np.cumsum(w_cmd) / rate
    a_lat = speed * np.gradient(course, 1.0 / rate)
    stopped = gaussian_filter1d((speed < 0.3).astype(float), 0.7 * rate, mode="nearest")
    mount_up = np.clip((t - rest_s + 2.0) / 1.5, 0.0, 1.0)  # upright on its stand while the device calibrates,
    stopped *= mount_up * mount_up * (3.0 - 2.0 * mount_up)  # then the rider gets on and leans it on a foot
    foot = rng.choice([-1.0, 1.0]) * np.radians(8.0)
    roll = np.arctan(a_lat / STANDARD_GRAVITY) + foot * stopped + np.radians(1.5) * pedal * np.sin(crank)
    # the tyres filter the road: a 12 kg frame share on 100 kN/m tyres with a little damping
    road = vib.Road(gd_n0=float(np.exp(rng.uniform(np.log(4e-6), np.log(16e-6)))), potholes_per_km=1.0,
                    pothole_depth_m=(0.01, 0.03))
    distance = np.cumsum(speed) / rate
    x, heights = vib.road_profile(float(distance[-1]) + 2.0, road, rng, tracks=1)
    # the frame is the "unsprung" mass here: on the tyres, under the rider's arms and saddle
    corner = vib.QuarterCar(sprung_kg=40.0, unsprung_kg=12.0, spring_n_m=20_000.0, damper_ns_m=300.0,
                            tyre_n_m=100_000.0)
    wheelbase = 1.0
    frame = corner.wheel_height(np.stack([np.interp(distance + wheelbase, x, heights[:, 0]),
                                          np.interp(distance, x, heights[:, 0])], axis=-1), rate)
    heave = frame[:, 0]  # the stem sits over the front wheel
    pitch = (frame[:, 1] - frame[:, 0]) / wheelbase
    yaw = np.pi / 2 - course + np.radians(1.0) * pedal * np.sin(crank + 1.0)  # the bars steer with each stroke
    attitude = np.stack([roll, pitch, yaw], axis=-1)
    extra = np.zeros((n, 3))
    extra[:, 2] = np.gradient(heave - heave[0], 1.0 / rate, edge_order=2)
    lever = np.array([0.55, 0.0, 0.95])  # the stem: forward of and above the contact line's midpoint
    arm = euler_to_matrix(attitude) @ lever
    extra += np.gradient(arm - arm[0], 1.0 / rate, axis=0, edge_order=2)
    mount = euler_to_matrix(np.array([0.0, np.radians(-20.0), 0.0]))  # screen up, tilted back towards the rider
    climb = np.zeros(n)
    return _assemble("bike", rate, rest_s, speed, course, climb, extra, attitude, {"mount": mount}, mount=mount)


# a cruise in traffic, calibrated on car-comma2k19's highway (its CAN speed from 12 s, after the on-ramp, through
# codegen.sim.features.along_track_acceleration): 24 % of the time under 0.1 m/s^2, 41 % within a vehicle's deadband
# (0.1-0.31), 35 % over; the cruises of tuning seeds 100-105 read 23 / 38 / 39 % (tests/test_sim_motion.py checks
# seeds 0-2), their rms 0.35 m/s^2 against the highway's 0.48. When cruises held their speed, all of a cruise lay
# under 0.1 m/s^2 and the whole moving drive read 61 / 3 / 36 %.
CAR_TRAFFIC_MS2 = 0.5  # m/s^2 rms of the wander's acceleration
CAR_TRAFFIC_HZ = (0.02, 0.25)  # its band: car-comma2k19's CAN speed has 87 % of that acceleration's power below 0.2 Hz
CAR_TRAFFIC_FADE_S = 3.0  # s: the wander fades in and out over this at the cruise's ends (a smoothstep)


def car(duration: float = 420.0, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ,
        mount: str = "any", vibration: bool = True) -> Trajectory:
    """A car on ordinary roads: starts, stops at lights with the engine idling, turns at junctions, hills.

    Longitudinal acceleration up to ~2.5 m/s^2, cruise 8..17 m/s wandering with the traffic (CAR_TRAFFIC_MS2),
    turns of 60..100 degrees at ~6 m/s, stops of 3..30 s; the road rises and falls by up to 6 %; the body rolls in
    turns and pitches with acceleration and grade.
    With `vibration` the body shakes as codegen.sim.vibration models it: road roughness (ISO 8608, class B to C,
    drawn per seed) through the suspension, potholes, and the engine, which runs from the start or is started a
    few seconds before the car moves (drawn per seed).

    mount="any": the device sits anywhere in the cabin in any orientation (a uniformly random rotation, as a
    device dropped in a door pocket, a cup holder or a bag); "dashboard": flat on the dashboard, facing forward.
    events: "engine_on_s" (when the engine starts), "mount" (the rotation board -> car), "lever_m".
    """
    from scipy.spatial.transform import Rotation

    from codegen.sim import vibration as vib

    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate
    start = int(rest_s * rate)
    # a stop at lights, or a turn at a junction
    script_a, script_w, _, script_c = _stops_and_turns(
        rng, rest_s, duration, cruise_ms=(8.0, 17.0), accel_ms2=(1.2, 2.5), cruise_s=(10.0, 30.0), stop_share=0.45,
        turn_ms=6.0, brake_ms2=(1.5, 3.0), wait_s=(3.0, 30.0), turn_s=(4.0, 6.0))
    a_cmd = gaussian_filter1d(_segments(n, rate, script_a, start), 0.3 * rate, mode="nearest")
    w_cmd = gaussian_filter1d(_segments(n, rate, script_w, start), 0.5 * rate, mode="nearest")
    # a cruise is not a constant speed: the traffic and the driver's foot make it wander (CAR_TRAFFIC_MS2). It is a
    # speed that comes and goes within the cruise (faded in and out over CAR_TRAFFIC_FADE_S at its ends, exactly 0
    # outside), so the script's ramps and stops hold. Drawn from a stream of its own, so the script is the one the
    # seed drew without it.
    cruise_spans = _segments(n, rate, script_c, start)
    edges = np.flatnonzero(np.diff(np.concatenate([[0.0], cruise_spans, [0.0]])))
    cruising = np.zeros(n)
    for b, e in zip(edges[::2], edges[1::2]):
        inside = np.clip(np.minimum(np.arange(b, e) - b + 0.5, e - 0.5 - np.arange(b, e)) / (CAR_TRAFFIC_FADE_S * rate),
                         0.0, 1.0)
        cruising[b:e] = inside * inside * (3.0 - 2.0 * inside)
    surge = _band_noise(np.random.default_rng([seed, 1]), n, rate, *CAR_TRAFFIC_HZ)
    wander = np.cumsum(surge) / rate
    wander = CAR_TRAFFIC_MS2 * (wander - np.mean(wander))
    speed = np.maximum(np.cumsum(a_cmd) / rate + cruising * wander, 0.0)
    course = rng.uniform(0, 2 * np.pi) + np.cumsum(w_cmd) / rate
    # the road's grade is a property of the road: a function of the distance driven (a car stopped on a hill keeps
    # its pitch), varying over ~240 m (a smooth profile drawn on a grid of GRADE_GRID_M along the road), flat for the
    # first 50 m (the parking spot where the device calibrates)
    profile = 0.06 * np.tanh(gaussian_filter1d(rng.standard_normal(n), 20.0 * rate, mode="nearest") * 150)
    distance = np.cumsum(speed) / rate
    grade = np.interp(distance, np.arange(n) * GRADE_GRID_M, profile) * np.clip(distance / 50.0, 0.0, 1.0)
    climb = speed * grade
    a_long = np.gradient(speed, 1.0 / rate)
    a_lat = speed * np.gradient(course, 1.0 / rate)
    roll = np.radians(0.5) * a_lat
    pitch = -np.arctan(grade) - np.radians(0.4) * a_long
    yaw = np.pi / 2 - course
    extra = np.zeros((n, 3))
    angles = np.zeros((n, 3))
    engine_on = 0.0 if rng.random() < 0.5 else rest_s - rng.uniform(2.0, 4.0)
    # the mounting is drawn before the road, whose draws depend on the distance driven (and so on the traffic): a
    # seed's device sits the same way however its cruises wander
    if mount == "any":
        rotation = Rotation.random(random_state=rng).as_matrix()
        lever = np.array([rng.uniform(-1.0, 1.5), rng.uniform(-0.7, 0.7), rng.uniform(0.0, 0.8)])
    elif mount == "dashboard":
        rotation = euler_to_matrix(np.array([np.radians(2.0), np.radians(-3.0), rng.uniform(-0.2, 0.2)]))
        lever = np.array([1.2, 0.3, 0.4])
    else:
        raise ValueError(f"unknown car mount {mount!r}; choose any or dashboard")
    if vibration:
        road = vib.Road(gd_n0=float(np.exp(rng.uniform(np.log(64e-6), np.log(256e-6)))))
        heave, pitch_v, roll_v = vib.road_shake(distance, rate, vib.VehicleBody(), road, rng)
        engine = vib.Engine()
        angles, _, _, engine_vel = vib.engine_shake(t, engine.rpm(speed), t >= engine_on, engine, rng)
        roll = roll + roll_v
        pitch = pitch + pitch_v
        extra[:, 2] += np.gradient(heave - heave[0], 1.0 / rate, edge_order=2)
        extra += engine_vel
    body = np.stack([roll, pitch, yaw], axis=-1)
    arm = euler_to_matrix(body) @ lever  # the body's pitch and roll move the device on its lever arm
    extra += np.gradient(arm - arm[0], 1.0 / rate, axis=0, edge_order=2)
    # the engine's shake is the mounting's own: local flexing (cm from its centre), no lever arm
    attitude = body + angles
    events = {"engine_on_s": engine_on, "mount": rotation, "lever_m": lever,
              "cruises": [(b / rate, e / rate) for b, e in zip(edges[::2], edges[1::2])]}
    return _assemble("car", rate, rest_s, speed, course, climb, extra, attitude, events, mount=rotation)


def _town_script(rng, n: int, rate: float, start: int, duration: float):
    """A drive in town as exact sample counts: (samples, along-track acceleration m/s^2, turn rate rad/s, kind) per
    segment, kind "park" (creeping in a car park), "queue" (stop-and-go), "road" (an ordinary street), "stand" (the
    engine idling). Each speed change integrates exactly to its target on the sample grid."""
    segments = []
    v = 0.0
    k = start

    def add(seconds, accel, turn, kind):
        nonlocal k
        m = max(1, int(round(seconds * rate)))
        segments.append((m, accel, turn, kind))
        k += m

    def reach(target, accel, kind, turn=0.0):
        nonlocal v
        if abs(target - v) > 1e-9:
            m = max(1, int(round(abs(target - v) / accel * rate)))
            add(m / rate, (target - v) * rate / m, turn, kind)
        v = target

    while k < n:
        kind = rng.choice(["park", "queue", "road", "stand"], p=[0.3, 0.3, 0.25, 0.15])
        if kind == "park":  # aisles at 2-4 m/s, a 90 degree turn at the end of each
            for _ in range(int(rng.integers(2, 5))):
                reach(rng.uniform(2.0, 4.0), rng.uniform(0.4, 1.0), kind)
                add(rng.uniform(4.0, 12.0), 0.0, 0.0, kind)
                seconds = rng.uniform(4.0, 7.0)
                add(seconds, 0.0, np.radians(90.0) * rng.choice([-1, 1]) / seconds, kind)
            reach(0.0, rng.uniform(0.8, 1.5), kind)
            add(rng.uniform(2.0, 8.0), 0.0, 0.0, "stand")
        elif kind == "queue":  # creeping traffic: up to 2-7 m/s, brake, wait, again
            for _ in range(int(rng.integers(3, 7))):
                reach(rng.uniform(2.0, 7.0), rng.uniform(0.5, 1.2), kind)
                add(rng.uniform(1.0, 6.0), 0.0, 0.0, kind)
                reach(0.0, rng.uniform(0.8, 1.5), kind)
                add(rng.uniform(2.0, 10.0), 0.0, 0.0, "stand")
        elif kind == "road":  # a street at 8-14 m/s, then a junction: a stop or a turn at 5 m/s
            reach(rng.uniform(8.0, 14.0), rng.uniform(1.0, 2.0), kind)
            add(rng.uniform(10.0, 25.0), 0.0, 0.0, kind)
            if rng.random() < 0.5:
                reach(5.0, rng.uniform(1.5, 2.5), kind)
                seconds = rng.uniform(4.0, 6.0)
                add(seconds, 0.0, np.radians(rng.uniform(60, 100)) * rng.choice([-1, 1]) / seconds, kind)
            reach(0.0, rng.uniform(1.5, 2.5), kind)
            add(rng.uniform(2.0, 6.0), 0.0, 0.0, "stand")
        else:  # a long stop: lights, a barrier, a drop-off
            reach(0.0, rng.uniform(1.0, 2.0), kind)
            add(rng.uniform(10.0, 60.0), 0.0, 0.0, "stand")
    return segments


def _band_noise(rng, n: int, rate: float, low_hz: float, high_hz: float) -> np.ndarray:
    """Gaussian noise of unit rms with a flat spectrum between low_hz and high_hz (FFT-shaped), (n,)."""
    spectrum = np.fft.rfft(rng.standard_normal(n))
    hz = np.fft.rfftfreq(n, 1.0 / rate)
    spectrum[(hz < low_hz) | (hz > high_hz)] = 0.0
    x = np.fft.irfft(spectrum, n)
    return x / max(float(np.std(x)), 1e-12)


def _body_pitch_mode(a_long: np.ndarray, rate: float, hz: float = 1.3, damping: float = 0.3) -> np.ndarray:
    """The along-track acceleration as the body's pitch follows it: through its pitch mode (second order, unit
    static gain), so a sudden change of the pedals rocks the body before it settles."""
    from scipy.signal import bilinear, lfilter, lfilter_zi

    w = 2 * np.pi * hz
    b, a = bilinear([w * w], [1.0, 2 * damping * w, w * w], fs=rate)
    out, _ = lfilter(b, a, a_long, zi=lfilter_zi(b, a) * a_long[0])
    return out


# Calibration of car_town's shaking (docs/simulator.md: what each figure came from, the command that prints it)
TOWN_HARSHNESS = 0.2  # the wheels' motion reaching the cabin past the springs: car-comma2k19's share above 8 Hz
TOWN_STAND_MG = (10.0, 20.0)  # an idling engine's |f| shaking at a stand, mg: a real car outside ../shared/data waited at 14.5 mg
TOWN_BUMP_M = (0.05, 0.08)  # speed bumps' height (m) over 2.5-4 m; one in every other car park aisle
TOWN_PARK_GD = (256e-6, 1024e-6)  # m^3: car park lanes, ISO 8608 class C..D
TOWN_PEDAL_MS2 = 0.8  # m/s^2 rms, a creeping driver's surge: a real car park's share (0.02-0.04, fused's statistic)
TOWN_ROAD_GD = (16e-6, 64e-6)  # m^3: streets, ISO 8608 class A..B (car-comma2k19's shaking at 8-20 m/s)
ENGINE_START_S = 0.5  # s: an idling engine's shake grows from nothing to its own as the engine starts


def car_town(duration: float = 420.0, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ) -> Trajectory:
    """A car in town, the device anywhere in the cabin (any orientation, as car's mount="any"): car parks crept
    through at 2-4 m/s with 90 degree turns and speed bumps, queues of stop-and-go traffic at 2-7 m/s, streets at
    8-14 m/s, stands of 2-60 s with the engine idling, the engine started 2-4 s before the car moves.

    The shaking is car's (ISO 8608 road through the quarter-car, the engine) with three calibrations: part of the
    wheels' own motion reaches the cabin (TOWN_HARSHNESS), the engine's linear shake is vertical with its idle |f|
    shaking drawn in TOWN_STAND_MG, and car parks are rough and bumpy, so slow driving shakes mostly below 8 Hz.
    events: "engine_on_s", "mount", "lever_m", "segments" ((start s, end s, kind) per script segment).
    """
    from scipy.spatial.transform import Rotation

    from codegen.sim import vibration as vib

    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate
    start = int(rest_s * rate)
    script = _town_script(rng, n, rate, start, duration)
    a_cmd, w_cmd = np.zeros(n), np.zeros(n)
    spans = []
    k = start
    for m, accel, turn, kind in script:
        a_cmd[k : k + m] = accel
        w_cmd[k : k + m] = turn
        if k < n:
            spans.append((k / rate, min(k + m, n - 1) / rate, str(kind)))
        k += m
    a_cmd = gaussian_filter1d(a_cmd, 0.3 * rate, mode="nearest")
    w_cmd = gaussian_filter1d(w_cmd, 0.5 * rate, mode="nearest")
    # creeping (a car park, a queue), the driver plays the pedals: a surge of TOWN_PEDAL_MS2 rms at 0.2-1.5 Hz on
    # top of the scripted speed, which the body answers by pitching on its springs. It is a speed that comes and
    # goes within the creep (faded in with the speed up to 1 m/s and out at the span's ends), so the script's speeds
    # hold outside it: a stand stands. (Integrated as an acceleration, its mean over a span carried over into the
    # stand after it: cars crept through "stands" at up to 2.6 m/s.)
    creep = np.zeros(n)
    for begin, end, kind in spans:
        if kind in ("park", "queue") and end - begin > 2.0:
            creep[int(begin * rate) : int(end * rate)] = 1.0
    creep = gaussian_filter1d(creep, 0.5 * rate, mode="nearest")
    scripted = np.maximum(np.cumsum(a_cmd) / rate, 0.0)
    wobble = _band_noise(rng, n, rate, 0.2, 1.5)
    wobble *= TOWN_PEDAL_MS2 / float(np.std(np.gradient(wobble, 1.0 / rate)))
    speed = np.maximum(scripted + creep * np.minimum(scripted, 1.0) * wobble, 0.0)
    speed[speed < 1e-6] = 0.0
    course = rng.uniform(0, 2 * np.pi) + np.cumsum(w_cmd) / rate
    distance = np.cumsum(speed) / rate
    a_long = np.gradient(speed, 1.0 / rate)
    a_lat = speed * np.gradient(course, 1.0 / rate)
    roll = np.radians(0.5) * a_lat
    pitch = -np.radians(0.4) * _body_pitch_mode(a_long, rate)
    engine_on = rest_s - rng.uniform(2.0, 4.0)
    # car parks: a bump across every other aisle, and a rough surface (a second, rougher profile felt where the car
    # creeps through a car park)
    bumps = []
    park = np.zeros(n, dtype=bool)
    for begin, end, kind in spans:
        if kind != "park":
            continue
        i, j = int(begin * rate), min(int(end * rate), n - 1)
        park[i:j] = True
        if distance[j] - distance[i] > 5.0 and rng.random() < 0.5:
            bumps.append((rng.uniform(distance[i] + 2.0, distance[j] - 2.0), rng.uniform(*TOWN_BUMP_M),
                          rng.uniform(2.5, 4.0)))
    body_model = vib.VehicleBody(harshness=TOWN_HARSHNESS)
    road = vib.Road(gd_n0=float(np.exp(rng.uniform(*np.log(TOWN_ROAD_GD)))))
    heave, pitch_v, roll_v = vib.road_shake(distance, rate, body_model, road, rng, bumps=bumps)
    lot = vib.Road(gd_n0=float(np.exp(rng.uniform(*np.log(TOWN_PARK_GD)))), potholes_per_km=10.0)
    lot_heave, lot_pitch, lot_roll = vib.road_shake(distance, rate, body_model, lot, rng)
    blend = gaussian_filter1d(park.astype(float), 1.0 * rate, mode="nearest")
    heave += blend * lot_heave
    roll = roll + roll_v + blend * lot_roll
    pitch = pitch + pitch_v + blend * lot_pitch
    stand_mg = rng.uniform(*TOWN_STAND_MG)
    # an idling inline four shakes vertically at its firing frequency; the DLPF and the harmonics take a little:
    # the linear amplitude is the idle |f| shaking drawn, in m/s^2 rms
    engine = vib.Engine(accel_rms_ms2=stand_mg * 1e-3 * STANDARD_GRAVITY, vertical=True)
    # the engine spins up over ENGINE_START_S: switched on at full amplitude its shake's velocity would step, a jolt
    # of up to 0.9 m/s^2 at the truth's 1 kHz depending on its phase
    starting = np.clip((t - engine_on) / ENGINE_START_S, 0.0, 1.0)
    angles, _, _, engine_vel = vib.engine_shake(t, engine.rpm(speed), starting, engine, rng)
    extra = np.zeros((n, 3))
    extra[:, 2] += np.gradient(heave - heave[0], 1.0 / rate, edge_order=2)
    extra += engine_vel
    rotation = Rotation.random(random_state=rng).as_matrix()
    lever = np.array([rng.uniform(-1.0, 1.5), rng.uniform(-0.7, 0.7), rng.uniform(0.0, 0.8)])
    body = np.stack([roll, pitch, np.pi / 2 - course], axis=-1)
    arm = euler_to_matrix(body) @ lever
    extra += np.gradient(arm - arm[0], 1.0 / rate, axis=0, edge_order=2)
    events = {"engine_on_s": engine_on, "mount": rotation, "lever_m": lever, "segments": spans,
              "stand_mg": stand_mg}
    return _assemble("car-town", rate, rest_s, speed, course, np.zeros(n), extra, body + angles, events,
                     mount=rotation)


def make_scenario(name: str, seed: int = 0, duration: float | None = None) -> Trajectory:
    """One of SCENARIOS by name; `duration` overrides the default length where the scenario has one."""
    kwargs = {"seed": seed}
    if duration is not None and name != "push":
        kwargs["duration"] = duration
    builders = {"static": static, "push": push, "walk": walk, "car": car, "bike": bike, "car-town": car_town,
                "walk-pocket": lambda **kw: walk(carry="pocket", **kw),
                "walk-backpack": lambda **kw: walk(carry="backpack", **kw),
                "walk-stand": lambda **kw: walk(stands=True, **kw)}
    if name not in builders:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}")
    return builders[name](**kwargs)
