"""Trajectories with exact truth: position, velocity, acceleration and orientation on a fine time grid.

A trajectory is sampled at `rate_hz` (1 kHz by default) in the earth frame ENU (x East, y North, z Up) and the
board frame (the MPU-6050 axes after the board's axis remap). Orientation is given as Euler angles with
R_board->ENU = Rz(yaw) · Ry(pitch) · Rx(roll); the board's angular rate follows from the Euler rates by the
standard kinematic relation, so integrating `gyro` from `rotation(0)` reproduces `rotation(k)`.

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

TRUTH_RATE_HZ = 1000.0
SCENARIOS = ("static", "push", "walk", "car")


@dataclass(frozen=True)
class Trajectory:
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

    @property
    def rate_hz(self) -> float:
        return 1.0 / (self.t[1] - self.t[0])

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def rotation(self, index=slice(None)) -> np.ndarray:
        """R board->ENU, (..., 3, 3)."""
        return euler_to_matrix(self.euler[index])

    def specific_force(self) -> np.ndarray:
        """What an ideal accelerometer measures, in the board frame: R^T (a + g·Up), m/s^2."""
        f_enu = self.acc.copy()
        f_enu[:, 2] += STANDARD_GRAVITY
        return np.einsum("nji,nj->ni", self.rotation(), f_enu)

    def at(self, times: np.ndarray) -> np.ndarray:
        """Truth ENU position at arbitrary times (linear interpolation on the fine grid), (len(times), 3)."""
        times = np.asarray(times, dtype=float)
        return np.stack([np.interp(times, self.t, self.pos[:, i]) for i in range(3)], axis=-1)

    def velocity_at(self, times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        return np.stack([np.interp(times, self.t, self.vel[:, i]) for i in range(3)], axis=-1)


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
) -> Trajectory:
    """Velocity from speed along course (rad from North, clockwise) + climb + extra ENU velocity; then integrate."""
    n = len(speed)
    dt = 1.0 / rate
    t = np.arange(n) * dt
    vel = np.stack([speed * np.sin(course), speed * np.cos(course), climb], axis=-1) + extra_vel
    acc = np.gradient(vel, dt, axis=0, edge_order=2)
    pos = _cumtrapz(vel, dt)
    gyro = body_rates(attitude, dt)
    return Trajectory(name, t, pos, vel, acc, attitude, gyro, rest_s, events or {})


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


def walk(duration: float = 300.0, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ) -> Trajectory:
    """A pedestrian holding the device in front of them, screen up and tilted towards the face.

    ~1.4 m/s with steps at ~1.9 Hz (vertical bob, forward surge, sideways sway), turns of 30..120 degrees,
    stops at crossings; the hand tilts and turns the device slowly and jiggles it with every step.
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate
    start = int(rest_s * rate)
    # speed: walk / stop segments
    script_v, script_w = [], []
    elapsed = rest_s
    while elapsed < duration:
        leg = rng.uniform(15.0, 40.0)
        script_v.append((leg, rng.uniform(1.2, 1.6)))
        turn = np.radians(rng.uniform(30, 120)) * rng.choice([-1, 1])
        turn_s = rng.uniform(1.5, 3.0)
        script_w += [(leg - turn_s, rng.normal(0.0, 0.01)), (turn_s, turn / turn_s)]
        elapsed += leg
        if rng.random() < 0.35:
            stop = rng.uniform(3.0, 8.0)
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
    climb = 0.025 * 2 * np.pi * step_hz * moving * np.cos(phase)  # ~2.5 cm vertical bob
    sway = 0.08 * moving * np.sin(phase / 2)  # sideways, half the step rate
    extra = np.stack([sway * np.cos(course), -sway * np.sin(course), np.zeros(n)], axis=-1)
    # the hand: tilted ~25 degrees towards the face, wandering slowly; yaw follows the course with an offset
    wander = gaussian_filter1d(rng.standard_normal((n, 3)), 2.0 * rate, axis=0, mode="nearest") * 80
    settle = np.clip((t - rest_s + 2.0) / 2.0, 0.0, 1.0)
    settle = settle * settle * (3.0 - 2.0 * settle)  # picked up from the table over 2 s before walking
    roll = settle * (np.radians(3) * wander[:, 0] + np.radians(1.5) * moving * np.sin(phase + 0.7))
    pitch = settle * (np.radians(-25) + np.radians(5) * wander[:, 1] + np.radians(2) * moving * np.sin(phase))
    yaw = np.pi / 2 - course + np.radians(10) * settle * wander[:, 2]
    attitude = np.stack([roll, pitch, yaw], axis=-1)
    return _assemble("walk", rate, rest_s, speed, course, climb, extra, attitude)


def car(duration: float = 420.0, rest_s: float = 12.0, seed: int = 0, rate: float = TRUTH_RATE_HZ) -> Trajectory:
    """A car with the device mounted on the dashboard: starts, stops, turns at junctions, hills.

    Longitudinal acceleration up to ~2.5 m/s^2, cruise 8..17 m/s, turns of 60..100 degrees at ~6 m/s, stops at
    lights; the road rises and falls by up to 6 %; the body rolls in turns and pitches with acceleration and grade.
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration * rate)) + 1
    t = np.arange(n) / rate
    start = int(rest_s * rate)
    script_a, script_w = [], []
    v = 0.0
    elapsed = rest_s
    while elapsed < duration:
        target = rng.uniform(8.0, 17.0)
        accel = rng.uniform(1.2, 2.5)
        ramp = (target - v) / accel
        cruise = rng.uniform(10.0, 30.0)
        slow_to = rng.uniform(0.0, 1.0) < 0.3 and 0.0 or 6.0
        brake = rng.uniform(1.5, 3.0)
        brake_s = (target - slow_to) / brake
        script_a += [(ramp, accel), (cruise, 0.0), (brake_s, -brake)]
        script_w += [(ramp + cruise + brake_s, 0.0)]
        elapsed += ramp + cruise + brake_s
        if slow_to == 0.0:
            wait = rng.uniform(3.0, 10.0)
            script_a.append((wait, 0.0))
            script_w.append((wait, 0.0))
            elapsed += wait
        else:
            turn = np.radians(rng.uniform(60, 100)) * rng.choice([-1, 1])
            turn_s = rng.uniform(4.0, 6.0)
            script_a.append((turn_s, 0.0))
            script_w.append((turn_s, turn / turn_s))
            elapsed += turn_s
        v = slow_to
    a_cmd = gaussian_filter1d(_segments(n, rate, script_a, start), 0.3 * rate, mode="nearest")
    w_cmd = gaussian_filter1d(_segments(n, rate, script_w, start), 0.5 * rate, mode="nearest")
    speed = np.maximum(np.cumsum(a_cmd) / rate, 0.0)
    course = rng.uniform(0, 2 * np.pi) + np.cumsum(w_cmd) / rate
    grade = 0.06 * np.tanh(gaussian_filter1d(rng.standard_normal(n), 20.0 * rate, mode="nearest") * 150)
    grade *= np.clip((t - rest_s) / 5.0, 0.0, 1.0)
    climb = speed * grade
    a_long = np.gradient(speed, 1.0 / rate)
    a_lat = speed * np.gradient(course, 1.0 / rate)
    vibration = 0.001 * gaussian_filter1d(rng.standard_normal((n, 3)), 0.01 * rate, axis=0) * np.sqrt(0.01 * rate)
    vibration *= np.clip(speed / 5.0, 0.0, 1.0)[:, None]
    mount_yaw = rng.uniform(-0.2, 0.2)
    roll = np.radians(0.5) * a_lat + np.radians(2.0) + vibration[:, 0]
    pitch = -np.arctan(grade) - np.radians(0.4) * a_long + np.radians(-3.0) + vibration[:, 1]
    yaw = np.pi / 2 - course + mount_yaw + vibration[:, 2]
    attitude = np.stack([roll, pitch, yaw], axis=-1)
    zero3 = np.zeros((n, 3))
    return _assemble("car", rate, rest_s, speed, course, climb, zero3, attitude)


def make_scenario(name: str, seed: int = 0, duration: float | None = None) -> Trajectory:
    """One of SCENARIOS by name; `duration` overrides the default length where the scenario has one."""
    kwargs = {"seed": seed}
    if duration is not None and name != "push":
        kwargs["duration"] = duration
    builders = {"static": static, "push": push, "walk": walk, "car": car}
    if name not in builders:
        raise ValueError(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)}")
    return builders[name](**kwargs)
