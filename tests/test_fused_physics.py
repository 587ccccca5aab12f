"""The fused algorithm's steps against physics and closed forms, each on every implementation on its own.

Every test here states what a step must do to a known motion (a known rotation, a constant acceleration, a stop, a
steady speed error, a turned frame) and checks each implementation against that, not against another implementation:
`impl` is the float64 reference (codegen/kernel/fused.py), the float32 C kernel through cffi (native_ext/dr_fused.c)
or the generated fallback on the unix-port `micropython` (dr_fallback.py), driven by tests/fusedkit.py. Tolerances
are the physics' (counts quantisation, the method's own approximations) plus float32 rounding where stated.
docs/fused.md lists the steps and their tests. The equivalence of the implementations on simulated runs is
tests/test_fused.py's and tests/test_fused_micropython.py's.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from codegen.kernel import fused as F
from codegen.kernel.layout import FUSED
from codegen.kernel.reference import (
    STANDARD_GRAVITY,
    quat_from_rotvec,
    quat_multiply,
    quat_to_matrix,
    tilt_from_gravity,
)
from fusedkit import FCFG, IMPLEMENTATIONS, KCFG, chunks, run

G = STANDARD_GRAVITY
EPS32 = 2.0**-24
DT_US = 5000
ONE_G = KCFG.accel_lsb_per_g  # counts
QUAT = slice(0, 4)
FUSED_PLATFORM = FUSED.param("platform")
ALIGNED = 100.0  # (m/s)^2: align_c of a heading alignment found long ago, the kernel frame true ENU (cos_t 1)


@pytest.fixture(params=IMPLEMENTATIONS)
def impl(request):
    if request.param == "c":
        from conftest import require_tool

        require_tool("cc")
    return request.param


def _samples(n, accel_g=(0.0, 0.0, 1.0), gyro=(0, 0, 0)):
    """n identical raw samples: the specific force in g (body frame) and the gyro in counts; dt 5 ms each."""
    acc = np.round(np.asarray(accel_g, dtype=float) * ONE_G)
    row = np.concatenate([acc, gyro]).astype(np.int16)
    return np.tile(row, (n, 1)), np.full(n, DT_US, dtype=np.int32)


def _still(**fields) -> F.FusedState:
    """A starting state: level, |f| averaged at 1 g, GPS lost long ago (no tilt correction), and `fields`."""
    st = F.FusedState()
    st.mean_f = st.vib_lp1 = G
    st.since_fix = 10.0
    for name, value in fields.items():
        setattr(st, name, value)
    return st


def _rotation_angle(q, expected) -> float:
    """Radians between two unit quaternions' rotations."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q)
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q, expected)))))


# ------------------------------------------------------------------------------------------------ calibration
def test_calibration_levels_gravity_and_takes_the_gyro_bias(impl, tmp_path):
    """At rest, tilted by a known rotation, the gyro reading constant counts: the calibrated orientation turns the
    measured specific force onto Up, the gyro bias is those counts, the mean |f| is the counts' 1 g. Shaken (0.05 g
    noise on x, above the 0.02 g motion threshold), the calibration says the device moved."""
    tilt = quat_to_matrix(quat_from_rotvec(np.array([0.3, -0.2, 0.0])))
    f = np.round(tilt.T @ [0.0, 0.0, ONE_G])  # gravity's counts in a body tilted by `tilt`
    gyro = np.array([40, -25, 7])
    rest = np.tile(np.concatenate([f, gyro]).astype(np.int16), (500, 1))
    trace = run(impl, [], tmp_path, calib=rest)
    assert trace.moved is False
    up = quat_to_matrix(trace.start[QUAT]) @ (f / np.linalg.norm(f))
    np.testing.assert_allclose(up, [0.0, 0.0, 1.0], atol=1e-6)
    # the mean of constant counts; the C multiplies the sum by 1/count (dr_recip: a few float32 ulp)
    np.testing.assert_allclose(trace.start[[F.IDX[n] for n in ("bgx", "bgy", "bgz")]], gyro, rtol=4 * EPS32)
    assert trace.start[F.IDX["mean_f"]] == pytest.approx(np.linalg.norm(f) * KCFG.accel_ms2_per_lsb, rel=1e-6)
    shaken = rest.copy()
    shaken[:, 0] += np.round(np.random.default_rng(1).normal(0.0, 0.05 * ONE_G, len(rest))).astype(np.int16)
    assert run(impl, [], tmp_path, calib=shaken).moved is True


# ------------------------------------------------------------------------------------------------ orientation
def test_gyro_turns_the_orientation_by_omega_t(impl, tmp_path):
    """90 degrees in 1 s about the body axis (1, 2, 2)/3, from a tilted start: q = q0 (x) exp(theta n / 2) (a body
    rate composes on the right). No GPS for longer than gps_timeout_s and tilt_tau_dark_s 0: no tilt correction.
    The step q (x) [1, h], renormalised, turns by 2 atan|h| instead of 2|h| (|h| = omega dt / 2 = 3.9e-3 rad), 8e-6
    rad short over the 200 samples; float32 rounds each of the 200 products and renormalisations (~1e-7 rad each)."""
    counts = np.array([3930, 7860, 7860])  # |counts| = 11790 = 90 degree/s at 131 counts per degree/s
    rate = math.radians(np.linalg.norm(counts) / KCFG.gyro_lsb_per_dps)
    q0 = quat_from_rotvec(np.array([0.3, -0.2, 0.5]))
    start = _still(qw=q0[0], qx=q0[1], qy=q0[2], qz=q0[3])
    samples, dt = _samples(200, gyro=counts)
    trace = run(impl, [("p", samples, dt)], tmp_path, start=start)
    theta = rate * 1.0
    half = np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) * counts / np.linalg.norm(counts)])
    assert theta == pytest.approx(math.pi / 2)
    assert _rotation_angle(trace.states[-1][QUAT], quat_multiply(q0, half)) < 8e-6 + 200 * 4 * EPS32 * 2 + 1e-6


def test_tilt_converges_to_gravity_with_gps(impl, tmp_path):
    """Started 5.8 degrees off level, at rest with GPS fixes (standing still) arriving: the Mahony correction alone
    (tilt_tau_s 20 s, no offset filter) takes the tilt error down as exp(-t / 20 s): below 5.8 e^-5 degrees after
    120 s (six time constants, with margin for its start-up)."""
    mahony = replace(FCFG, tilt_tau_s=20.0, kf_bias_init_g=0.0)
    q0 = quat_from_rotvec(np.radians([5.0, -3.0, 0.0]))
    start = _still(qw=q0[0], qx=q0[1], qy=q0[2], qz=q0[3], since_fix=0.0, steady=1.0)
    samples, dt = _samples(200)
    steps = [step for _ in range(120) for step in (("p", samples, dt), ("v", 0.0, 0.0))]
    trace = run(impl, steps, tmp_path, params=mahony, start=start)
    up = quat_to_matrix(trace.states[-1][QUAT])[2]
    assert math.degrees(math.acos(min(1.0, up[2]))) < 5.0 * math.exp(-5)
    assert math.degrees(math.acos(min(1.0, quat_to_matrix(trace.states[0][QUAT])[2][2]))) > 4.0  # it started off


# ------------------------------------------------------------------------------------------------ rest
def test_at_rest_nothing_moves(impl, tmp_path):
    """Calibrated at rest, tilted, with a gyro bias: 10 s more at rest moves nothing and the flags say at rest."""
    tilt = quat_to_matrix(quat_from_rotvec(np.array([0.1, -0.05, 0.0])))
    f = np.round(tilt.T @ [0.0, 0.0, ONE_G])
    rest = np.tile(np.concatenate([f, [12, -7, 3]]).astype(np.int16), (2000, 1))
    dt = np.full(len(rest), DT_US, dtype=np.int32)
    trace = run(impl, [("p", rest, dt)], tmp_path, calib=rest)
    # float32 rounding of the calibrated tilt leaves ~1e-7 m/s^2 until rest is declared (rest_time_s): nanometres
    bound = 1e-9 if impl == "reference" else 1e-6
    assert np.all(np.abs(trace.outs[-1]) < bound)
    assert int(trace.at(-1, "flags")) == F.AT_REST


def test_a_vehicle_that_stops_comes_to_rest(impl, tmp_path):
    """A vehicle rolling at 10 m/s East (its speed just set by a fix) stops dead (the IMU level and still from then
    on): with no GPS it rolls on at 10 m/s until the device has looked still for rest_time_s (0.4 s: n = 80 samples,
    4.0 m), then the zero-velocity update sets the speed to 0 and nothing moves any more. That update also takes
    back what the speed it still had says: an error grown evenly over the n dt since the speed was known, its
    integral along the way, v dt (n + 1) / 2 of the v dt n rolled, leaving v dt (n - 1) / 2 (1.975 m)."""
    start = _still(speed=10.0, zr_v=10.0)
    samples, dt = _samples(400)
    trace = run(impl, chunks(samples, dt, 20), tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    first_rest = int(np.argmax(flags == F.AT_REST))
    assert first_rest == 80 // 20 - 1 or first_rest == 80 // 20  # the chunk holding sample 80 (or 81: float32)
    pe = trace.series("pe")
    rolled = [10.0 * 0.005 * (n - 1) / 2 for n in (79, 80)]  # 79 or 80 samples before the update (float32)
    assert min(rolled) - 1e-4 <= pe[-1] <= max(rolled) + 1e-4
    assert np.all(pe[first_rest + 1:] == pe[-1]) and trace.at(-1, "speed") == 0.0 and abs(trace.at(-1, "pn")) < 1e-9


def test_rest_pulls_the_gyro_bias_with_its_time_constant(impl, tmp_path):
    """At rest the gyro bias estimate moves towards the raw counts with the time constant bias_tau_s (30 s), in steps
    of rest_update_s (1 s) once the rest is rest_update_s old (its first second is the end of a braking): an
    estimate 20 counts off about Up (the yaw it turns keeps gravity vertical, so the device stays at rest), at rest
    from 0.4 s, is updated at 2.4, 3.4, ... 9.4 s: 8 times, each taking 1/30 of the error the smoothed rate shows
    (which trails a step by e^-2 of it after 1 s: each update takes at most 1 % more), 20 (29/30)^8 left."""
    true_z = 5
    start = _still(bgz=true_z + 20.0)
    samples, dt = _samples(2000, gyro=(0, 0, true_z))
    trace = run(impl, [("p", samples, dt)], tmp_path, start=start)
    left = trace.at(-1, "bgz") - true_z
    assert int(trace.at(-1, "flags")) == F.AT_REST
    step = FCFG.rest_update_s / FCFG.bias_tau_s
    assert 20 * (1 - 1.01 * step) ** 8 <= left <= 20 * (1 - step) ** 8 * (1 + 1e-4)


def _engine(n, seed=0):
    """n samples of a device at rest, level, in a vehicle whose engine idles: the firing order's shake at 27 Hz
    (sampled at 200 Hz), 0.9 degree/s rms on the gyro about a random axis and 0.1 m/s^2 rms on the accelerometer,
    as codegen.sim.vibration models a real roof-mounted car drive."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    wave = np.sin(2 * np.pi * 27.0 * t + rng.uniform(0, 2 * np.pi))
    axis_w, axis_a = rng.normal(size=3), rng.normal(size=3)
    gyro = np.outer(wave, axis_w / np.linalg.norm(axis_w)) * 0.9 * math.sqrt(2) * KCFG.gyro_lsb_per_dps
    accel = np.outer(wave, axis_a / np.linalg.norm(axis_a)) * 0.1 * math.sqrt(2) / G + [0.0, 0.0, 1.0]
    samples = np.hstack([np.round(accel * ONE_G), np.round(gyro)]).astype(np.int16)
    return samples, np.full(n, DT_US, dtype=np.int32)


def test_a_stopped_vehicle_with_its_engine_running_comes_to_rest(impl, tmp_path):
    """Stopped with the engine idling, the gyro reads 0.9 degree/s rms, above the 0.5 degree/s rest limit, but it is
    a 27 Hz shake: its 0.5 s average is ~0.01 degree/s, so the device comes to rest after rest_time_s (0.4 s) plus
    the average's settling, and no speed survives. While fixes arrive that say it moves (the last one's speed above
    min_speed_ms, less than gps_timeout_s ago) it does not: a smooth cruise looks still too."""
    samples, dt = _engine(600)
    trace = run(impl, chunks(samples, dt, 20), tmp_path, start=_still(speed=3.0))
    flags = trace.series("flags").astype(int)
    assert np.all(flags[-20:] & F.AT_REST) and trace.at(-1, "speed") == 0.0
    assert int(np.argmax(flags & F.AT_REST)) * 20 * 0.005 < 1.5  # at rest within 1.5 s
    moving = _still(speed=3.0, gps_ok=2.5, gps_speed=3.0, since_fix=0.0)
    trace = run(impl, chunks(samples[:300], dt[:300], 20), tmp_path, start=moving)  # 1.5 s: the fix is 1.5 s old
    assert not np.any(trace.series("flags").astype(int) & F.AT_REST)


def _idle(n, vertical_g, seed=0):
    """_engine's idle with its shake along Up `vertical_g` rms at 27 Hz and 54 Hz (the firing frequency and its
    harmonic, 2:1): |f| then varies by that much (the horizontal part, under 0.1 m/s^2, stays within the deadband)."""
    samples, dt = _engine(n, seed)
    t = np.arange(n) * 0.005
    wave = (2.0 * np.sin(2 * np.pi * 27.0 * t) + np.sin(2 * np.pi * 54.0 * t + 1.0)) / math.sqrt(2.5)
    samples[:, 2] = np.round(ONE_G * (1.0 + vertical_g * wave)).astype(np.int16)
    return samples, dt


def test_an_idling_engine_at_25_mg_is_rest_and_creeping_traffic_is_not(impl, tmp_path):
    """A vehicle stopped in an outage with its engine idling harder than the rest limit (|f| 25 mg rms against
    rest_accel_g's 10 mg; a real car idled at 14.5 mg): the shake is above the gait band (27 and 54
    Hz: its share above vibration_hz is ~90 %), its 0.5 s average rate ~0, its speed below rest_speed_ms after the
    braking: at rest (up to idle_accel_g, 30 mg) within 2 s, speed 0. The same shake while the vehicle creeps at 2 m/s (its speed before says it
    moves; constant speed feels exactly like a stop) is no rest, and the speed is kept."""
    samples, dt = _idle(800, 0.025)
    f = samples[:, :3].astype(float) / ONE_G
    assert np.std(np.linalg.norm(f, axis=1)) == pytest.approx(0.025, abs=0.002)
    start = _still(speed=0.4, zr_v=0.4, flags=float(F.VEHICLE), vib_tot=(0.03 * G) ** 2, vib_var=(0.025 * G) ** 2,
                   var_f=(0.025 * G) ** 2)
    trace = run(impl, chunks(samples, dt, 20), tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    assert np.all(flags[-10:] & F.AT_REST) and trace.at(-1, "speed") == 0.0
    assert int(np.argmax(flags & F.AT_REST)) * 20 * 0.005 < 2.0
    quiet = run(impl, chunks(samples, dt, 20), tmp_path, start=start, params=replace(FCFG, idle_accel_g=0.0))
    assert not np.any(quiet.series("flags").astype(int) & F.AT_REST)  # the amplitude alone: never at rest
    creeping = run(impl, chunks(samples, dt, 20), tmp_path, start=_still(
        speed=2.0, zr_v=2.0, flags=float(F.VEHICLE), vib_tot=(0.03 * G) ** 2, vib_var=(0.025 * G) ** 2,
        var_f=(0.025 * G) ** 2))
    assert not np.any(creeping.series("flags").astype(int) & F.AT_REST)
    assert creeping.at(-1, "speed") == pytest.approx(2.0, abs=1e-3)


def _hand(n, seed=0, accel_g=0.03):
    """n samples of a hand holding the device still, level: |f| varies by `accel_g` rms, 60 % of its power in the
    sway (0.3-0.8 Hz) and 40 % in the physiological tremor (8-12 Hz); the horizontal specific force by a third of
    that (tilt wobble); the rate 1.5 degree/s rms of tremor (which a 0.5 s average takes out) plus the arm's sway,
    0.2 degree/s rms at 0.2-0.5 Hz (+-0.1 degree: the accelerometer's share of it is under 2 mg)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005

    def band(lo, hi, count):
        f = rng.uniform(lo, hi, count)
        wave = np.sum(np.sin(2 * np.pi * f[:, None] * t[None, :] + rng.uniform(0, 2 * np.pi, count)[:, None]), axis=0)
        return wave / np.std(wave)

    vertical = accel_g * (math.sqrt(0.6) * band(0.3, 0.8, 4) + math.sqrt(0.4) * band(8.0, 12.0, 6))
    horizontal = np.stack([band(0.3, 12.0, 8), band(0.3, 12.0, 8)], axis=-1) * accel_g / 3.0
    accel = np.column_stack([horizontal, 1.0 + vertical])
    gyro = np.stack([1.5 * band(8.0, 12.0, 6) + 0.2 * band(0.2, 0.5, 2) for _ in range(3)], axis=-1)
    gyro *= KCFG.gyro_lsb_per_dps
    samples = np.hstack([np.round(accel * ONE_G), np.round(gyro)]).astype(np.int16)
    return samples, np.full(n, DT_US, dtype=np.int32)


def _slow_walk(n, speed_ms, seed=0):
    """n samples of a slow walk (0.5-1 m/s) with the device in the hand: steps at 1.4-1.8 Hz that shake |f| by
    only 38 mg rms (above walk_accel_g, within still_accel_g: the amplitude would allow a rest), a forward surge of the walking speed by +-15 % of it at the step
    frequency, and the hand's swing about Up at half of it (+-8 degrees)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    step = rng.uniform(1.4, 1.8)
    phase = 2 * np.pi * step * t
    vertical = 0.038 * math.sqrt(2) * np.sin(phase)
    surge = 0.15 * speed_ms * 2 * np.pi * step * np.cos(phase) / G  # d/dt of 0.15 v sin(phase), in g
    swing = math.radians(8.0) * np.pi * step * np.cos(phase / 2)  # rad/s
    accel = np.column_stack([surge, np.zeros(n), 1.0 + vertical])
    gyro = np.column_stack([np.zeros(n), np.zeros(n), np.degrees(swing) * KCFG.gyro_lsb_per_dps])
    samples = np.hstack([np.round(accel * ONE_G), np.round(gyro)]).astype(np.int16)
    return samples, np.full(n, DT_US, dtype=np.int32)


def test_a_hand_holding_the_device_still_at_30_mg_is_rest(impl, tmp_path):
    """A walker stopped at a waypoint, the device in the hand (|f| 30 mg rms: real hand-held stands shook
    11-27 mg): its horizontal specific force stays within the deadband and the tremor averages out of the rate, so
    it comes to rest (up to still_accel_g, 40 mg), speed 0. With the amplitude alone (still_accel_g 0) it would not."""
    samples, dt = _hand(1000)
    f = np.linalg.norm(samples[:, :3].astype(float) / ONE_G, axis=1)
    assert np.std(f) == pytest.approx(0.03, abs=0.003)
    start = _still(flags=float(F.WALKED), var_f=(0.03 * G) ** 2, vib_tot=(0.03 * G) ** 2)
    trace = run(impl, chunks(samples, dt, 20), tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    assert np.all(flags[-10:] & F.AT_REST) and not np.any(flags & F.WALKING) and trace.at(-1, "speed") == 0.0
    assert int(np.argmax(flags & F.AT_REST)) * 20 * 0.005 < 2.5
    quiet = run(impl, chunks(samples, dt, 20), tmp_path, start=start, params=replace(FCFG, still_accel_g=0.0))
    assert not np.any(quiet.series("flags").astype(int) & F.AT_REST)


@pytest.mark.parametrize("speed_ms", [0.5, 1.0])
def test_slow_walking_is_not_rest(impl, tmp_path, speed_ms):
    """A slow walk shaking |f| little (38 mg rms, within still_accel_g) is never at rest: its surge
    (+-15 % of the speed at the step frequency) breaks the steady horizontal force within a step, and the hand's
    swing keeps the averaged rate above rest_gyro_dps; it stays a walk at the walking speed."""
    samples, dt = _slow_walk(1200, speed_ms)
    start = _still(flags=float(F.WALKING | F.WALKED), walk_speed=speed_ms, speed=speed_ms,
                   var_f=(0.038 * G) ** 2, vib_tot=(0.038 * G) ** 2)
    trace = run(impl, chunks(samples, dt, 20), tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    assert not np.any(flags & F.AT_REST)
    assert np.mean(flags & F.WALKING > 0) > 0.9 and trace.at(-1, "speed") == pytest.approx(speed_ms)


def test_a_car_slowed_to_5_ms_after_gps_said_15_is_never_a_walker(impl, tmp_path):
    """A car (level, heading East, unknown yet: no flags) speeds up from 5 to 15 m/s and slows to 5 again by GPS,
    smoothly, then drives at 5 m/s through a car park whose surface shakes it in the gait band (2 Hz, 0.06 g rms: its
    share above vibration_hz ~0.3 %, below the 4 % a vehicle needs; a real car park had 2-4 %), 3 s
    under GPS and 8 s in an outage. A pedestrian does not go 15 m/s (pedestrian_max_ms, 6), so it is a vehicle
    until it rests: never a walk, its speed never reset to a walker's (or to 0 when the "steps" stop). Without that
    bound the same samples are a walk and the speed is lost."""
    shaking, dt = _shaken("steps", 200, accel_g=0.06)
    steps, previous = [], 5.0
    for v in (5.0, 10.0, 15.0, 15.0, 10.0, 5.0):  # the along-track acceleration the GPS speeds show
        steps += [("p", *_samples(200, accel_g=((v - previous) / G, 0.0, 1.0))), ("g", v, 0.0, v, 0.0)]
        previous = v
    steps += [("p", shaking, dt), ("g", 5.0, 0.0, 5.0, 0.0)] * 3 + [("p", shaking, dt)] * 8
    start = _still(since_fix=0.5, walk_speed=1.2, speed=5.0)
    trace = run(impl, steps, tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    assert not np.any(flags & F.WALKING) and np.all(flags[3:] & (F.VEHICLE | F.FAST) == F.VEHICLE | F.FAST)
    assert trace.at(-1, "speed") == pytest.approx(5.0, abs=0.5)
    unbounded = run(impl, steps, tmp_path, start=start, params=replace(FCFG, pedestrian_max_ms=100.0,
                                                                       carried_ms=100.0))
    assert np.any(unbounded.series("flags").astype(int) & F.WALKING)
    assert abs(unbounded.at(-1, "speed") - 5.0) > 1.0


def test_slow_traffic_that_gps_sees_moving_without_steps_is_never_a_walker(impl, tmp_path):
    """A car (level, heading East, no flags) in slow traffic: GPS says 4 m/s (slower than people run, so
    pedestrian_max_ms says nothing) while its shaking shows no steps, then a queue's surface shakes it in the gait
    band (2 Hz, 0.06 g rms), 3 s under GPS at 4 m/s and 8 s in an outage. A pedestrian who moves faster than
    carried_ms (2.5 m/s) steps, so a device moving that fast without steps is carried: a vehicle until it rests,
    never a walk, its speed kept. Without that rule the same samples are a walk and the speed is lost."""
    shaking, dt = _shaken("steps", 200, accel_g=0.06)
    steps = [("p", *_samples(200, accel_g=(0.0, 0.0, 1.0))), ("g", 4.0, 0.0, 4.0, 0.0)] * 2
    steps += [("p", shaking, dt), ("g", 4.0, 0.0, 4.0, 0.0)] * 3 + [("p", shaking, dt)] * 8
    start = _still(since_fix=0.5, walk_speed=1.2, speed=4.0)
    trace = run(impl, steps, tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    assert not np.any(flags & F.WALKING) and np.all(flags[200:] & F.FAST)
    assert trace.at(-1, "speed") == pytest.approx(4.0, abs=0.5)
    unruled = run(impl, steps, tmp_path, start=start, params=replace(FCFG, carried_ms=100.0))
    assert np.any(unruled.series("flags").astype(int) & F.WALKING)
    assert abs(unruled.at(-1, "speed") - 4.0) > 1.0


def test_a_pedestrian_who_stops_stepping_without_rest_slows_to_0(impl, tmp_path):
    """A pedestrian whose steps stopped (flags: walked since the last rest) with 1.5 m/s from the last fix, the hand
    turning the device slowly (1 degree/s: no rest) and tilted by 3 degrees (0.5 m/s^2 of gravity along the track,
    which integrated would reach 3 m/s in 3 s): the speed decays over stand_tau_s (1 s) to 1.5 e^-3 in 3 s, and the
    position moves 1.5 tau (1 - e^-3) ~ 1.4 m, never integrating the leak."""
    n = 600
    tilt = math.radians(3.0)
    samples, dt = _samples(n, accel_g=(math.sin(tilt), 0.0, math.cos(tilt)), gyro=(round(KCFG.gyro_lsb_per_dps), 0, 0))
    start = _still(flags=float(F.WALKED), speed=1.5, walk_speed=1.4)
    trace = run(impl, chunks(samples, dt, 200), tmp_path, start=start)
    speed = trace.series("speed")
    assert np.all(np.diff(speed) < 0) and speed[-1] == pytest.approx(1.5 * math.exp(-3.0), rel=0.02)
    assert np.hypot(trace.at(-1, "pe"), trace.at(-1, "pn")) == pytest.approx(1.5 * (1 - math.exp(-3.0)), rel=0.02)
    assert not np.any(trace.series("flags").astype(int) & (F.AT_REST | F.WALKING))


def test_a_vehicle_quiet_after_shaking_comes_to_rest_and_levels_its_tilt(impl, tmp_path):
    """A vehicle (flags: broadband shaking seen, shaken since its last rest) stops after a 90 degree turn in an
    outage with its kernel tilt 2 degrees off: its horizontal specific force is g sin 2 = 0.34 m/s^2, beyond the
    deadband that a device not known to be a vehicle needs, but it is steady and the vehicle went quiet: rest. The
    tilt/offset filter (started at the last fix) allows for what the turn may have added (kf_turn_noise x pi/2 =
    0.16 m/s^2) and each rest_update_s takes that force as its error (z = d + R_h b, dv_true = 0): the tilt is
    levelled, here to under a tenth of its error within 12 s."""
    tilt = quat_to_matrix(quat_from_rotvec(np.array([0.0, math.radians(2.0), 0.0])))
    f = np.round(tilt.T @ [0.0, 0.0, ONE_G])  # the body tilted 2 degrees; the kernel believes it level
    samples = np.tile(np.concatenate([f, [0, 0, 0]]).astype(np.int16), (2400, 1))
    dt = np.full(len(samples), DT_US, dtype=np.int32)
    fixed = _still(flags=float(F.VEHICLE | F.SHAKEN), speed=4.0)
    F.gps_update(fixed, 0.0, 0.0, FCFG)  # the filter starts at a fix
    start = _still(**{n: getattr(fixed, n) for n in F.COVARIANCE_FIELDS}, flags=float(F.VEHICLE | F.SHAKEN),
                   speed=4.0, turn=math.pi / 2, kf_t=30.0)
    trace = run(impl, chunks(samples, dt, 200), tmp_path, start=start)
    assert int(trace.at(-1, "flags")) & F.AT_REST and trace.at(-1, "speed") == 0.0
    q = trace.states[-1][QUAT]
    up = quat_to_matrix(q / np.linalg.norm(q)) @ (f / np.linalg.norm(f))  # the measured gravity in the kernel frame
    assert math.degrees(math.acos(up[2])) < 0.2
    plain = run(impl, chunks(samples, dt, 200), tmp_path, start=_still(speed=4.0))  # no vehicle seen: no rest
    assert not int(plain.at(-1, "flags")) & F.AT_REST


def test_a_car_pulling_away_smoothly_from_a_stand_leaves_rest(impl, tmp_path):
    """A vehicle stands at rest in an outage (shaken since its last rest, level, quiet), its tilt/offset filter
    converged (0.03 m/s^2 per state: it has seen turns). It pulls away as gently as a town car does: the
    acceleration ramps up over 2.5 s (0.4 m/s^3, slow enough that the smoothed force follows within the deadband)
    to 1 m/s^2 and holds it for 3 s, with no more shaking than the stand had: still and steady. The filter cannot
    take that force for its tilt error (rest_gate), so the rest ends 0.9 s into the ramp and the speed integrates:
    3.85 of the true 4.25 m/s by the end (what came before and what the deadband keeps out are lost). Without the
    gate (rest_gate 0) it stays at rest and every rest update levels the acceleration away as tilt: speed 0."""
    t = np.arange(1100) * 0.005
    accel = np.minimum(t / 2.5, 1.0) / G  # g along the body's x axis (forward, level)
    samples = np.zeros((len(t), 6), dtype=np.int16)
    samples[:, 0] = np.round(accel * ONE_G)
    samples[:, 2] = ONE_G
    dt = np.full(len(t), DT_US, dtype=np.int32)
    fields = {name: 0.0 for name in F.COVARIANCE_FIELDS}
    for i in range(4):  # tilt East, North; offsets x, y (the one along gravity unseen: 0)
        fields[F._PIJ[(i, i)]] = 0.03 ** 2
    start = _still(**fields, flags=float(F.AT_REST | F.VEHICLE | F.SHAKEN), rest_s=2.0)
    trace = run(impl, chunks(samples, dt, 20), tmp_path, start=start)
    flags = trace.series("flags").astype(int)
    assert not flags[-1] & F.AT_REST
    assert trace.at(-1, "speed") > 3.5
    assert int(np.argmin(flags & F.AT_REST)) * 20 * 0.005 < 1.5  # left rest early in the ramp
    ungated = run(impl, chunks(samples, dt, 20), tmp_path, start=start, params=replace(FCFG, rest_gate=0.0))
    assert np.all(ungated.series("flags").astype(int) & F.AT_REST) and ungated.at(-1, "speed") == 0.0


def test_a_calibration_that_moved_leaves_the_speed_to_the_first_fix_not_to_a_bias(impl, tmp_path):
    """A car calibrated while it drives (its speed taken as 0, not known: sb_pss large) keeps an even 20 m/s for
    1 s, then a fix says so: the speed/bias filter takes the 20 m/s for the speed (gain ~1) and leaves the
    along-track bias alone. Had calibration stood still (the speed known 0), the same fix would have been a bias:
    that was the real highway drive's -2.6 m/s^2 from its first fix."""
    samples, dt = _samples(200)
    moving = dict(flags=float(F.VEHICLE), since_fix=0.0, gps_ok=19.5, gps_speed=20.0, align_c=ALIGNED)
    unknown = run(impl, [("p", samples, dt), ("v", 20.0, 0.0)], tmp_path,
                  start=_still(**moving, sb_pss=F.SPEED_UNKNOWN_VAR, cal_moved=1.0))
    assert not int(unknown.states[0][F.IDX["flags"]]) & F.AT_REST
    assert unknown.at(-1, "speed") == pytest.approx(20.0, abs=0.01)
    assert abs(unknown.at(-1, "bias")) < 0.01
    assert unknown.at(-1, "keep_v") == pytest.approx(20.0) and unknown.at(-1, "sk_t") == 0.0
    known = run(impl, [("p", samples, dt), ("v", 20.0, 0.0)], tmp_path, start=_still(**moving))
    assert known.at(-1, "bias") < -1.0


def test_an_interval_whose_travel_direction_was_not_known_teaches_no_along_track_bias(impl, tmp_path):
    """A car whose heading alignment has not been found yet (its first seconds of driving: the kernel frame's yaw
    is arbitrary, so the acceleration was integrated along a direction the fixes had not placed) gets a fix 20 m/s
    faster than its integrated speed: the speed takes it, the along-track bias does not. The same fix after an
    aimed interval is a bias (as the calibration test above shows). A simulated car that learned its first
    seconds' lag as a bias of -1 m/s^2 ran from 8.7 to 18 m/s in a 10 s outage."""
    samples, dt = _samples(200)
    start = dict(flags=float(F.VEHICLE), since_fix=0.0, gps_ok=19.5, gps_speed=20.0)
    unaligned = run(impl, [("p", samples, dt), ("v", 20.0, 0.0)], tmp_path, start=_still(**start))
    assert unaligned.at(-1, "speed") == pytest.approx(20.0, abs=0.01)
    assert abs(unaligned.at(-1, "bias")) < 1e-3  # 2e-5: the speed's restart variance (1e4) leaves a trace
    after_a_stop = run(impl, [("p", samples, dt), ("v", 20.0, 0.0)], tmp_path,
                       start=_still(**dict(start, gps_ok=-0.5, align_c=ALIGNED)))  # the last fix had no course
    assert abs(after_a_stop.at(-1, "bias")) < 1e-3
    aimed = run(impl, [("p", samples, dt), ("v", 20.0, 0.0)], tmp_path, start=_still(**start, align_c=ALIGNED))
    assert aimed.at(-1, "bias") < -1.0


def test_a_fix_that_finds_a_pedestrian_teaches_no_along_track_bias(impl, tmp_path):
    """A pedestrian whose steps stopped (WALKED: his speed decays, never integrated) gets a fix 2 m/s faster than
    his speed: the speed moves speed_gain of it, the bias not at all (a car in slow traffic taken for a walker once
    learned -12 m/s^2 that way and ran to 700 m/s when it drove on)."""
    start = _still(flags=float(F.WALKED), since_fix=1.0, gps_ok=0.5, speed=1.0, bias=0.2)
    trace = run(impl, [("v", 3.0, 0.0)], tmp_path, start=start)
    assert trace.at(-1, "bias") == pytest.approx(0.2)
    assert trace.at(-1, "speed") == pytest.approx(1.0 + FCFG.speed_gain * 2.0, rel=1e-6)


def test_a_vehicle_weighs_its_integrated_speed_against_the_speed_it_keeps(impl, tmp_path):
    """A car at 20 m/s by its last fix, calibrated while it drove (so its tilt drifts and the along-track bias walks
    at speed_bias_noise), in an outage 30 s on a level straight road at an even speed, its accelerometer reading
    0.05 g along the track too much: integrated, the speed runs to 35 m/s and the car 225 m too far. The integrated
    speed's variance grows with t^3 (the bias's walk), the kept speed's with t (keep_speed_noise): weighed by them,
    V_s / (V_s + V_k) of the excess is taken off (half of it by 30 s), so the position follows
    int (20 + a t (1 - w(t))) dt; without the kept speed (keep_speed_noise 0) it is all there."""
    counts = round(0.05 * ONE_G)
    samples, dt = _samples(6000, accel_g=(counts / ONE_G, 0.0, 1.0))
    start = _still(flags=float(F.VEHICLE), speed=20.0, zr_v=20.0, keep_v=20.0, cal_moved=1.0, sb_pss=0.02,
                   sb_psb=-0.002, sb_pbb=0.004, gps_speed=20.0)
    kept = run(impl, chunks(samples, dt, 500), tmp_path, start=start)
    alone = run(impl, chunks(samples, dt, 500), tmp_path, start=start, params=replace(FCFG, keep_speed_noise=0.0))
    a = counts * KCFG.accel_ms2_per_lsb
    assert not np.any(kept.series("flags").astype(int) & F.AT_REST)
    assert alone.at(-1, "pe") == pytest.approx(600.0 + 0.5 * a * 30.0 ** 2, rel=0.02)
    t = (np.arange(6000) + 1) * 0.005
    v_s = (0.02 + 0.004 * t + 0.004 * t * t + FCFG.speed_noise ** 2 * t + FCFG.speed_bias_noise ** 2 * t ** 3 / 3)
    v_k = FCFG.kf_vel_sigma_ms ** 2 + FCFG.keep_speed_noise ** 2 * t
    excess = a * np.maximum(t - _gated(a, 6000) * 0.005, 0.0)  # the deadband holds the first samples back
    weighed = np.sum((20.0 + excess * (1.0 - v_s / (v_s + v_k))) * 0.005)
    assert kept.at(-1, "pe") == pytest.approx(weighed, abs=0.02 * (weighed - 600.0))
    assert kept.at(-1, "pe") - 600.0 < 0.8 * (alone.at(-1, "pe") - 600.0)
    assert kept.at(-1, "speed") == pytest.approx(alone.at(-1, "speed"))  # the integration itself is unchanged
    assert kept.outs[-1][3] < kept.at(-1, "speed")  # the velocity out is the weighed one


def test_zero_velocity_update_takes_back_a_steady_drift(impl, tmp_path):
    """A vehicle at 10 m/s East (the speed a fix just gave, which it keeps) brakes evenly to a stop over 10 s (50 m), shaken by its
    road (0.05 g rms of vertical noise) until it stops, but its accelerometer reads 0.2 m/s^2 too much along the
    track (-0.8 instead of -1 m/s^2), and still reads it when stopped. Integrated, the speed is still ~2 m/s when the
    vehicle stops and the position ~10 m too far; the device then needs ~2 s to see itself still (the road's
    variance fading from its 0.5 s average, then rest_time_s), rolling on at ~2 m/s. At rest, the zero-velocity
    update takes that speed as an error grown evenly since the fix and takes back its integral: the braking's 10 m
    and half the last 4 m (the even growth the update assumes puts half of the error gathered in its last seconds
    earlier), so the position ends within 3 m of the 50 m, where the integration alone leaves it over 10 m beyond."""
    leak = 0.2
    t = np.arange(2400) * 0.005
    a = np.where(t < 10.0, -1.0, 0.0) + leak
    road = np.where(t < 10.0, 0.05 * np.random.default_rng(1).standard_normal(len(t)), 0.0)
    samples = np.stack([np.round(a / G * ONE_G), np.zeros_like(t), np.round((1.0 + road) * ONE_G), np.zeros_like(t),
                        np.zeros_like(t), np.zeros_like(t)], axis=-1).astype(np.int16)
    dt = np.full(len(t), DT_US, dtype=np.int32)
    start = _still(speed=10.0, zr_v=10.0, keep_v=10.0, flags=float(F.VEHICLE | F.SHAKEN))
    trace = run(impl, chunks(samples, dt, 200), tmp_path, start=start)
    assert int(trace.at(-1, "flags")) & F.AT_REST
    assert trace.at(-1, "pe") == pytest.approx(50.0, abs=3.0) and abs(trace.at(-1, "pn")) < 1e-6
    drift = run(impl, chunks(samples, dt, 200), tmp_path, start=start, params=replace(FCFG, rest_time_s=1e9))
    assert drift.at(-1, "pe") > 60.0


def test_a_turn_in_an_outage_finds_a_vehicles_speed_error(impl, tmp_path):
    """A vehicle in an outage at 6 m/s, which its integration believes is 8 m/s (the speed error an along-track
    leak builds), drives 4 s straight and then turns at 0.3 rad/s for 8 s, its road shaking it (0.05 g of vertical
    noise, so it never looks at rest). It does not slide sideways: across the travel direction its acceleration is
    the centripetal s r = 1.8 m/s^2, so the lateral residual a_lat - s r = -(s - s_true) r = -0.6 m/s^2 in the turn
    (0 on the straight, which tells the filter there is no lateral leak). The lateral update takes the speed to
    within 0.4 m/s of 6 m/s (the filter lets the leak take some of the residual: a turn may change it); without it
    the speed stays at 8 m/s, as nothing along the track tells it otherwise."""
    n = 2400
    t = np.arange(n) * 0.005
    rate_counts = np.where(t < 4.0, 0.0, np.round(math.degrees(0.3) * KCFG.gyro_lsb_per_dps))
    rate = np.radians(rate_counts / KCFG.gyro_lsb_per_dps)
    lateral = np.round(6.0 * rate / G * ONE_G)  # the centripetal specific force, counts along the body's left (y)
    road = 0.05 * np.random.default_rng(1).standard_normal(n)
    zero = np.zeros(n)
    samples = np.stack([zero, lateral, np.round((1.0 + road) * ONE_G), zero, zero, rate_counts],
                       axis=-1).astype(np.int16)
    dt = np.full(n, DT_US, dtype=np.int32)
    start = _still(speed=8.0, zr_v=8.0, flags=float(F.VEHICLE))
    truth = float(lateral[-1] / ONE_G * G / rate[-1])  # 6 m/s but for the counts' rounding
    trace = run(impl, chunks(samples, dt, 200), tmp_path, start=start)
    assert trace.series("speed")[:4] == pytest.approx(8.0, abs=1e-3)  # straight: nothing to see
    assert trace.at(-1, "speed") == pytest.approx(truth, abs=0.4)
    blind = run(impl, chunks(samples, dt, 200), tmp_path, start=start, params=replace(FCFG, nhc_sigma_ms2=0.0))
    assert blind.at(-1, "speed") == pytest.approx(8.0, abs=1e-3)


def test_a_turn_in_an_outage_shows_the_offsets_folded_into_the_tilt(impl, tmp_path):
    """A level vehicle whose accelerometer reads 0.03 g too much along its forward (body x) axis, calibrated at rest:
    the offset is folded into the tilt (tilted by 0.03 rad), so before any turn the two cancel. In an outage at 8 m/s
    it turns 180 degrees (0.3 rad/s) and drives on. The offset turns with the car, the tilt error stays in the earth
    frame: after the turn they add up to 0.06 g = 0.59 m/s^2 along the travel direction (0.03 g (1 - cos psi) on the
    way), 4.8 m/s of speed gained by the end. The tilt/offset filter knows it has not told them apart (its
    covariance: 0.05 g per horizontal axis), so the lateral filter estimates the fold from what the turn shows across
    the track (the offset's lateral part rises and falls with the heading while the tilt's does not) and takes it out
    of the along-track integration: the speed ends within 0.5 m/s of 8 m/s. With nhc_fold_scale 0 it ends more than
    3 m/s off."""
    n = 3700  # 10.5 s of turn (pi / 0.3) after 2 s of straight, then 6 s straight: 18.5 s at 5 ms
    t = np.arange(n) * 0.005
    turning = (t >= 2.0) & (t < 2.0 + math.pi / 0.3)
    rate_counts = np.where(turning, np.round(math.degrees(0.3) * KCFG.gyro_lsb_per_dps), 0.0)
    rate = np.radians(rate_counts / KCFG.gyro_lsb_per_dps)
    offset = 0.03 * ONE_G
    lateral = np.round(8.0 * rate / G * ONE_G)  # the centripetal specific force along the body's left (y)
    road = 0.05 * np.random.default_rng(2).standard_normal(n)
    zero = np.zeros(n)
    samples = np.stack([np.full(n, np.round(offset)), lateral, np.round((1.0 + road) * ONE_G), zero, zero,
                        rate_counts], axis=-1).astype(np.int16)
    dt = np.full(n, DT_US, dtype=np.int32)
    q = tilt_from_gravity([np.round(offset), 0.0, ONE_G])  # calibration at rest: the offset folded into the tilt
    var = (0.05 * G) ** 2
    start = _still(speed=8.0, zr_v=8.0, flags=float(F.VEHICLE), qw=q[0], qx=q[1], qy=q[2], qz=q[3], p22=var, p33=var)
    trace = run(impl, chunks(samples, dt, 200), tmp_path, start=start)
    assert trace.at(-1, "speed") == pytest.approx(8.0, abs=0.5)
    blind = run(impl, chunks(samples, dt, 200), tmp_path, start=start, params=replace(FCFG, nhc_fold_scale=0.0))
    assert abs(blind.at(-1, "speed") - 8.0) > 3.0


# ------------------------------------------------------------------------------------------------ steps or a vehicle
def _shaken(kind, n=1200, seed=0, accel_g=0.1):
    """n samples of a level device whose |f| swings `accel_g` rms: "steps", a 2 Hz sine (a walker's bob), or
    "road", white noise (broadband, as a vehicle's road, wheels and engine)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    swing = accel_g * (math.sqrt(2) * np.sin(2 * np.pi * 2.0 * t) if kind == "steps" else rng.standard_normal(n))
    zero = np.zeros(n)
    samples = np.stack([zero, zero, np.round(ONE_G * (1.0 + swing)), zero, zero, zero], axis=-1).astype(np.int16)
    return samples, np.full(n, DT_US, dtype=np.int32)


@pytest.mark.parametrize("platform", ["auto", "pedestrian", "vehicle"])
def test_steps_are_a_walk_and_broadband_shaking_a_vehicle(impl, tmp_path, platform):
    """The same 0.1 g rms of |f| shaking, as a walker's 2 Hz steps and as broadband vibration: the share of its
    variance above vibration_hz (8 Hz) is ~0.3 % for the steps and ~80 % for white noise at 200 Hz (above the 4 %
    limit). On auto the steps are a walk once they have lasted walk_time_s (1 s) and the noise a vehicle; a
    pedestrian walks whatever shakes it, a vehicle never walks."""
    code = FUSED_PLATFORM.code(platform)
    params = replace(FCFG, platform=float(code))
    for kind in ("steps", "road"):
        samples, dt = _shaken(kind)
        trace = run(impl, chunks(samples, dt, 20), tmp_path, params=params, start=_still(walk_speed=1.2))
        flags = trace.series("flags").astype(int)
        walks = platform == "pedestrian" or platform == "auto" and kind == "steps"
        assert bool(flags[-1] & F.WALKING) == walks, (kind, flags[-1])
        assert bool(flags[-1] & F.VEHICLE) == (not walks)
        if walks:
            first = int(np.argmax(flags & F.WALKING)) * 20 * 0.005
            assert 1.0 <= first < 1.5  # walk_time_s after the shaking passed walk_accel_g
            assert trace.at(-1, "speed") == pytest.approx(1.2)



def test_a_vehicle_that_creeps_on_after_a_stop_steps_for_seconds_before_it_is_a_pedestrian(impl, tmp_path):
    """A car that drove (a fast fix since its last walk: DROVE) and has rested since (FAST cleared) moves on in an
    outage, its queue's surface shaking it in the gait band (2 Hz, 0.1 g rms). A car creeping in a queue shakes like
    that for seconds at a time; a passenger who got out walks on: it is a pedestrian after vehicle_walk_time_s (10 s)
    of steps, not walk_time_s (1 s). A device that is a vehicle only by its broadband shaking (a hand's tremor is
    broadband too) walks after walk_time_s; so does a pedestrian platform, whatever the flags say."""
    samples, dt = _shaken("steps", 2600)
    pedestrian = replace(FCFG, platform=float(FUSED_PLATFORM.code("pedestrian")))
    for flags, params, walk_after in ((F.VEHICLE | F.DROVE, FCFG, 10.0), (F.VEHICLE, FCFG, 1.0), (0, FCFG, 1.0),
                                      (F.VEHICLE | F.DROVE, replace(FCFG, vehicle_walk_time_s=1.0), 1.0),
                                      (F.DROVE, pedestrian, 1.0)):
        trace = run(impl, chunks(samples, dt, 20), tmp_path, params=params,
                    start=_still(flags=float(flags), speed=2.0, walk_speed=1.2))
        seen = trace.series("flags").astype(int)
        walking = seen & F.WALKING
        assert walking[-1] and not seen[-1] & F.DROVE, flags
        first = int(np.argmax(walking)) * 20 * 0.005
        assert walk_after <= first < walk_after + 0.5, (flags, first)


def test_a_fast_fix_marks_a_device_that_drove_until_it_walks(impl, tmp_path):
    """A fix at 8 m/s (faster than people run) sets FAST and DROVE; a fix at 0 m/s and the rest that follows (6 s
    of a level, quiet device) clear FAST only."""
    quiet = _samples(400, accel_g=(0.0, 0.0, 1.0))
    steps = [("p", *quiet), ("g", 8.0, 0.0, 8.0, 0.0), ("p", *quiet), ("g", 0.0, 0.0, 0.0, 0.0)] + [("p", *quiet)] * 3
    trace = run(impl, steps, tmp_path, start=_still(since_fix=0.5, speed=8.0, walk_speed=1.2))
    flags = trace.series("flags").astype(int)
    assert flags[-1] & F.AT_REST and flags[-1] & F.DROVE and not flags[-1] & F.FAST, flags[-1]


# ------------------------------------------------------------------------------------------------ travel direction
def test_turn_rotates_the_travel_direction(impl, tmp_path):
    """A turn of 90 degrees (counter-clockwise) about Up at 0.5 rad/s turns the travel direction with it."""
    rate_counts = round(math.degrees(0.5) * KCFG.gyro_lsb_per_dps)
    rate = math.radians(rate_counts / KCFG.gyro_lsb_per_dps)
    steps = round(math.pi / 2 / rate / 0.005)
    samples, dt = _samples(steps, gyro=(0, 0, rate_counts))
    trace = run(impl, [("p", samples, dt)], tmp_path, start=_still())
    turned = rate * steps * 0.005
    assert math.atan2(trace.at(-1, "uy"), trace.at(-1, "ux")) == pytest.approx(turned, abs=1e-3)


def _walking(samples_t, rate_dps):
    """Steps at 2 Hz (|f| swinging 0.15 g), the device level, turned about Up at rate_dps (degree/s) per sample."""
    counts = np.round(rate_dps * KCFG.gyro_lsb_per_dps)
    f = np.round(ONE_G * (1.0 + 0.15 * np.sin(2 * np.pi * 2.0 * samples_t)))
    zero = np.zeros_like(samples_t)
    return np.stack([zero, zero, f, zero, zero, counts], axis=-1).astype(np.int16), counts


def test_walker_holds_the_hands_swing_and_takes_a_turn_at_once(impl, tmp_path):
    """Walking (steps at 2 Hz), the device level: 1 s straight; the hand swings it 9 degrees left and back (6
    degree/s for 1.5 s each way, below the 7 degree/s a turn ends at); a 90 degree turn at 45 degree/s; 1 s straight.
    The travel direction keeps the course through the swing (under 2 degrees where the gyro moved 9: the held angle,
    a triangle up to 9 degrees over 3 s, leaks into u at a tenth per second, about 1.2 degrees at most) and takes the
    turn with what it held, ending on the device's heading. Without the hold (turn_hold_tau_s 0) u follows the hand
    all the way."""
    t = np.arange(2000) * 0.005
    rate_dps = np.select([(t >= 1.0) & (t < 2.5), (t >= 2.5) & (t < 4.0), (t >= 4.0) & (t < 6.0)], [6.0, -6.0, 45.0])
    samples, counts = _walking(t, rate_dps)
    dt = np.full(len(t), DT_US, dtype=np.int32)
    heading = np.degrees(np.cumsum(counts / KCFG.gyro_lsb_per_dps * np.radians(1.0) * 0.005))[19::20]
    start = _still(var_f=(0.1 * G) ** 2, vib_tot=(0.1 * G) ** 2, walk_speed=1.4, flags=float(F.WALKING))  # walking

    def u_angles(trace):
        assert np.all(trace.series("flags").astype(int) & F.WALKING)
        return np.degrees(np.arctan2(trace.series("uy"), trace.series("ux")))

    swing, after = (t[19::20] >= 1.0) & (t[19::20] < 4.0), t[19::20] >= 6.5
    assert np.max(np.abs(heading[swing])) == pytest.approx(9.0, abs=0.1)  # what the gyro saw
    u = u_angles(run(impl, chunks(samples, dt, 20), tmp_path, start=start))
    assert np.max(np.abs(u[swing])) < 2.0
    assert np.all(np.abs(u[after] - heading[after]) < 0.05) and heading[-1] == pytest.approx(90.0, abs=0.1)
    follows = u_angles(run(impl, chunks(samples, dt, 20), tmp_path, params=replace(FCFG, turn_hold_tau_s=0.0),
                           start=start))
    assert np.allclose(follows, heading, atol=0.05)


def test_walker_stops_when_the_steps_stop(impl, tmp_path):
    """5 s of steps at the learned walking speed (1.4 m/s, the device level, u East), then 3 s without steps while
    the hand still turns the device slowly (1 degree/s about its x axis, which a 0.5 s average of the rate keeps:
    no rest). Walking, the device goes 1.4 m/s; the speed drops to 0 with the steps (the variance of |f|, a 0.5 s
    moving average, falls below the walking limit ~1.3 s after the last step), and in the last second nothing
    moves; it never counted as at rest, and stays a pedestrian (WALKED) whose speed is never integrated."""
    t = np.arange(1600) * 0.005
    f = np.round(ONE_G * (1.0 + np.where(t < 5.0, 0.15 * np.sin(2 * np.pi * 2.0 * t), 0.0)))
    rate = np.full_like(t, np.round(KCFG.gyro_lsb_per_dps))
    zero = np.zeros_like(t)
    samples = np.stack([zero, zero, f, rate, zero, zero], axis=-1).astype(np.int16)
    dt = np.full(len(t), DT_US, dtype=np.int32)
    start = _still(walk_speed=1.4, var_f=(0.1 * G) ** 2, vib_tot=(0.1 * G) ** 2, flags=float(F.WALKING))  # walking
    trace = run(impl, [("p", samples[:1000], dt[:1000]), ("p", samples[1000:1400], dt[1000:1400]),
                       ("p", samples[1400:], dt[1400:])], tmp_path, start=start)
    walked, fading, still = trace.outs
    assert int(trace.at(0, "flags")) == F.WALKING | F.WALKED and trace.at(0, "speed") == pytest.approx(1.4, rel=1e-6)
    assert walked[0] == pytest.approx(1.4 * 5.0, rel=1e-3) and abs(walked[1]) < 1e-3
    assert int(trace.at(1, "flags")) == F.WALKED and trace.at(1, "speed") == 0.0  # a pedestrian, not walking
    assert int(trace.at(2, "flags")) == F.WALKED and np.hypot(still[0], still[1]) < 1e-6


# ------------------------------------------------------------------------------------------------ speed
def _gated(a, n, since_fix=None):
    """Samples of a constant along-track acceleration a (m/s^2, from rest) the deadband's gate holds back: while its
    moving average over accel_tau_s, a (1 - (1 - dt / tau)^k) after k samples, is below the deadband; all n if it
    never gets there. The deadband is l, or from since_fix s after a fix it grows to l over deadband_ramp_s."""
    k = np.arange(1, n + 1)
    smoothed = a * (1.0 - (1.0 - 0.005 / FCFG.accel_tau_s) ** k)
    deadband = np.full(n, KCFG.deadband_ms2)
    if since_fix is not None:
        deadband *= np.minimum(1.0, (since_fix + (k - 1) * 0.005) / FCFG.deadband_ramp_s)
    return int(np.argmax(smoothed >= deadband)) if smoothed[-1] >= deadband[-1] else n


def test_constant_along_track_acceleration_builds_speed_a_t(impl, tmp_path):
    """A level vehicle heading East (u = East) under a constant 0.1 g along-track acceleration for 1 s (n = 200
    samples of dt = 5 ms): the deadband gates on the acceleration averaged over accel_tau_s (0.5 s), so the first
    k samples (until that average passes the deadband, 0.19 s) build nothing; then the speed grows by a (n - k) dt,
    the position by the per-sample steps' sum a dt^2 m (m + 1) / 2, m = n - k (float32 may put the gate's opening a
    sample either way). A 0.02 g acceleration, inside the board's 0.03125 g deadband, builds nothing."""
    counts = round(0.1 * ONE_G)
    a = counts * KCFG.accel_ms2_per_lsb
    samples, dt = _samples(200, accel_g=(counts / ONE_G, 0.0, 1.0))
    trace = run(impl, [("p", samples, dt)], tmp_path, start=_still())
    gated = _gated(a, 200)
    assert 30 < gated < 45  # 0.15-0.22 s
    built = [200 - k for k in (gated - 1, gated, gated + 1)]
    assert any(trace.at(-1, "speed") == pytest.approx(a * 0.005 * m, rel=1e-5) for m in built)
    assert any(trace.outs[-1][0] == pytest.approx(a * 0.005**2 * m * (m + 1) / 2, rel=1e-5) for m in built)
    assert abs(trace.outs[-1][1]) < 1e-6
    samples, dt = _samples(200, accel_g=(0.02, 0.0, 1.0))
    trace = run(impl, [("p", samples, dt)], tmp_path, start=_still())
    assert trace.at(-1, "speed") == 0.0 and trace.outs[-1][0] == 0.0


@pytest.mark.parametrize("since_fix", [0.0, 3.0, 10.0])
def test_a_vehicles_deadband_grows_from_0_at_a_fix_to_l_over_deadband_ramp_s(impl, tmp_path, since_fix):
    """A vehicle cruising level at 10 m/s East speeds up gently, at 0.02 g (under the board's 0.03125 g deadband, as
    41 % of a real highway's along-track acceleration is), for 1 s starting since_fix s after a fix. The deadband grows
    from 0 at the fix to l over deadband_ramp_s (10 s): the gate passes sample k while the acceleration's average over
    accel_tau_s, a (1 - (1 - dt / tau)^k), is not below l (since_fix + (k - 1) dt) / 10. Right after the fix all of the
    second is speed (a 0.2 m/s change); 3 s after it the first 0.37 s is held back; 10 s after it, all of it (the
    gravity leak a tilt error gathers by then is what l keeps out). Float32 may move the gate by a sample."""
    fcfg = replace(FCFG, rest_time_s=1e9)
    assert fcfg.deadband_ramp_s == 10.0
    counts = round(0.02 * ONE_G)
    a = counts * KCFG.accel_ms2_per_lsb
    samples, dt = _samples(200, accel_g=(counts / ONE_G, 0.0, 1.0))
    trace = run(impl, [("p", samples, dt)], tmp_path, params=fcfg, start=_still(speed=10.0, since_fix=since_fix))
    k = np.arange(1, 201)
    smoothed = a * (1.0 - (1.0 - 0.005 / fcfg.accel_tau_s) ** k)
    deadband = KCFG.deadband_ms2 * np.minimum(1.0, (since_fix + (k - 1) * 0.005) / fcfg.deadband_ramp_s)
    passed = smoothed >= deadband
    built = int(np.sum(passed))
    assert {0.0: 200, 3.0: 126, 10.0: 0}[since_fix] == built  # the closed form's own count, for the reader
    # float32: 200 additions to 10 m/s, each rounded by up to half of 10's ulp (4.8e-7); a sample adds 1e-3
    assert any(trace.at(-1, "speed") == pytest.approx(10.0 + a * 0.005 * m, abs=1e-4) for m in (built - 1, built,
                                                                                                   built + 1))


@pytest.mark.parametrize("median", [False, True])
def test_median_option_ignores_a_spike(impl, tmp_path, median):
    """A vehicle cruising level at 10 m/s East; one sample carries a 0.5 g jolt along the track. With the deadband on
    each sample (accel_tau_s 0) and without the median it adds 0.5 g x 5 ms to the speed; the median of the last b =
    16 along-track accelerations ignores it. So does the default gate: the jolt moves the 0.5 s average by 0.005 g,
    inside the deadband."""
    fcfg = replace(FCFG, median=1.0 if median else 0.0, rest_time_s=1e9)
    samples, dt = _samples(64)
    samples[40, 0] += int(0.5 * ONE_G)
    trace = run(impl, [("p", samples, dt)], tmp_path, params=replace(fcfg, accel_tau_s=0.0), start=_still(speed=10.0))
    jolt = 0.5 * G * 0.005
    assert trace.at(-1, "speed") == pytest.approx(10.0 if median else 10.0 + jolt, abs=1e-4)
    trace = run(impl, [("p", samples, dt)], tmp_path, params=fcfg, start=_still(speed=10.0))
    assert trace.at(-1, "speed") == pytest.approx(10.0, abs=1e-4)


def test_gps_sets_speed_and_course(impl, tmp_path):
    """Fixes at a steady 1.4 m/s heading North-East: the speed and the true-frame course follow them."""
    ve = vn = 1.4 / math.sqrt(2)
    trace = run(impl, [("v", ve, vn)] * 40, tmp_path, start=F.FusedState())
    assert trace.at(-1, "speed") == pytest.approx(1.4, rel=1e-5)
    ux, uy, c, s = (trace.at(-1, n) for n in ("ux", "uy", "cos_t", "sin_t"))
    assert math.atan2(s * ux + c * uy, c * ux - s * uy) == pytest.approx(math.pi / 4, abs=1e-4)


def test_walking_speed_learns_the_gps_speed(impl, tmp_path):
    """Walking, fixes at 1.3 m/s: the walking speed moves walk_speed_gain (0.2) of its error per fix,
    w_n = 1.3 (1 - 0.8^n), and the speed speed_gain (0.5) of its own; the along-track bias is left alone."""
    trace = run(impl, [("v", 1.3, 0.0)] * 10, tmp_path, start=_still(flags=float(F.WALKING), since_fix=0.0))
    for n in range(1, 11):
        assert trace.at(n - 1, "walk_speed") == pytest.approx(1.3 * (1 - 0.8**n), rel=1e-6)
        assert trace.at(n - 1, "speed") == pytest.approx(1.3 * (1 - 0.5**n), rel=1e-6)
    assert trace.at(-1, "bias") == 0.0


def test_along_track_bias_is_learned_from_a_steady_speed_error(impl, tmp_path):
    """A level vehicle at a steady 10 m/s East whose accelerometer reads 0.06 g (0.59 m/s^2) too much along the
    track: integrated alone, that is 0.59 m/s of speed error a second. Fixes at 10 m/s East once a second drive the
    along-track bias towards the offset until the remainder is inside the deadband as it stands a second after a fix
    (l / deadband_ramp_s a second, 0.031 m/s^2: below it the remainder builds little speed, so the fixes see little
    error), and the speed back to 10 m/s within what that remainder builds in a second. (No tilt correction: it
    would take the offset as tilt.)"""
    fcfg = replace(FCFG, tilt_tau_s=1e9)
    offset = round(0.06 * ONE_G) * KCFG.accel_ms2_per_lsb
    samples, dt = _samples(200, accel_g=(round(0.06 * ONE_G) / ONE_G, 0.0, 1.0))
    start = _still(speed=10.0, gps_speed=10.0, gps_ve=10.0, gps_ok=9.5, since_fix=0.0, align_c=ALIGNED)
    trace = run(impl, [s for _ in range(40) for s in (("p", samples, dt), ("v", 10.0, 0.0))], tmp_path,
                params=fcfg, start=start)
    gated = _gated(offset, 200, since_fix=0.0)  # the first second, unlearned, after the gate opens
    assert any(trace.at(0, "speed") == pytest.approx(10.0 + offset * 0.005 * (200 - k), rel=1e-4)
               for k in (gated - 1, gated, gated + 1))
    left = offset - trace.at(-1, "bias")
    assert 0.0 < left < KCFG.deadband_ms2 * 1.0 / fcfg.deadband_ramp_s
    assert abs(trace.at(-1, "speed") - 10.0) < left * 1.0 and abs(trace.at(-2, "speed") - 10.0) < left * 1.0


# ------------------------------------------------------------------------------------------------ GPS alignment
def test_heading_alignment_finds_the_kernel_frame_rotation(impl, tmp_path):
    """The kernel frame's yaw after calibration is arbitrary; here it is true ENU turned by -40 degrees (A, the
    rotation kernel -> true, by +40). A vehicle at ~5 m/s accelerates 0.5 m/s^2 East for a second, then North, West,
    South, twice over; the level IMU sees A^T a, the GPS a. From the velocity changes (a 2-D Wahba problem) the
    alignment finds A: (cos_t, sin_t) = (cos 40, sin 40) degrees, to the counts' resolution (0.5 m/s^2 is 835.4
    counts: the rounding turns it by < 0.1 degree)."""
    theta = math.radians(40.0)
    a_rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    start = _still(gps_ve=5.0, gps_speed=5.0, gps_ok=4.5, since_fix=0.0)
    v = np.array([5.0, 0.0])
    steps = []
    for j in range(8):
        a_true = 0.5 * np.array([(1, 0), (0, 1), (-1, 0), (0, -1)][j % 4], dtype=float)
        a_kernel = a_rot.T @ a_true
        samples, dt = _samples(200, accel_g=(a_kernel[0] / G, a_kernel[1] / G, 1.0))
        v = v + a_true
        steps += [("p", samples, dt), ("v", float(v[0]), float(v[1]))]
    trace = run(impl, steps, tmp_path, start=start)
    for k in range(1, len(steps), 2):  # after every fix
        angle = math.atan2(trace.at(k, "sin_t"), trace.at(k, "cos_t"))
        assert math.degrees(angle) == pytest.approx(40.0, abs=0.1)


# ------------------------------------------------------------------------------------------------ position at the fix
def test_position_step_adds_the_imu_to_the_doppler_trapezoid(impl, tmp_path):
    """Level, accelerating East at a = j t (j = 2 m/s^3) for 1 s between two fixes with velocities 0 and j/2: the
    trapezoid T (v0 + v1) / 2 = j/4 m overshoots the true j/6 m by 17 cm; the IMU's correction takes it out, so a fix
    at the true position is no surprise to the position filter. What remains: the counts' rounding (0.6 mm/s^2 per
    count) integrated twice over 1 s, well under a millimetre. Had the step been the trapezoid alone (reference), the
    filter would move by centimetres."""
    j = 2.0
    t = (np.arange(200) + 0.5) * 0.005
    samples = np.stack([np.round(j * t / G * ONE_G), np.zeros_like(t), np.full_like(t, ONE_G), np.zeros_like(t),
                        np.zeros_like(t), np.zeros_like(t)], axis=-1).astype(np.int16)
    dt = np.full(len(t), DT_US, dtype=np.int32)
    start = _still(since_fix=0.0)
    trace = run(impl, [("x", 0.0, 0.0, 0.0, 0.0), ("p", samples, dt), ("x", j / 2, 0.0, j / 6, 0.0)], tmp_path,
                start=start)
    assert trace.at(0, "fix_pxx") == pytest.approx(FCFG.pos_sigma_m**2, rel=1e-6)  # the filter started at the fix
    assert abs(trace.at(-1, "fix_ae")) < 1e-3 and abs(trace.at(-1, "fix_an")) < 1e-6
    without = F.FusedState()
    F.position_update(without, 0.0, 0.0, 0.0, 0.0, FCFG)
    without.since_fix = 1.0
    F.position_update(without, j / 2, 0.0, j / 6, 0.0, FCFG)
    assert abs(without.fix_ae) > 0.02


def test_position_filter_restarts_after_an_outage(impl, tmp_path):
    """A fix 5 s after the previous one (beyond gps_timeout_s: the Doppler cannot carry the position across) restarts
    the filter at the fix itself: offset 0, the position and receiver errors +-pos_sigma_m, perfectly
    anti-correlated."""
    start = _still(fix_pxx=1.0, fix_pxe=-0.5, fix_pee=2.0, fix_ae=0.7, fix_en=0.3, since_fix=5.0)
    trace = run(impl, [("x", 1.0, 0.0, 500.0, 0.0)], tmp_path, start=start)
    assert [trace.at(0, n) for n in ("fix_ae", "fix_an", "fix_ee", "fix_en")] == [0.0, 0.0, 0.0, 0.0]
    var = FCFG.pos_sigma_m**2
    assert trace.at(0, "fix_pxx") == pytest.approx(var, rel=1e-6)
    assert trace.at(0, "fix_pee") == pytest.approx(var, rel=1e-6)
    assert trace.at(0, "fix_pxe") == pytest.approx(-var, rel=1e-6)


def test_a_gentle_start_the_deadband_hides_is_speed_not_an_along_track_bias(impl, tmp_path):
    """A car at 1 m/s by GPS (its speed known) speeds up at 0.025 g, under the deadband (0.031 g): the gate keeps the
    acceleration out of the integrated speed, so each fix 1 s apart finds the speed short by 0.25 m/s. What the
    deadband kept out is counted as the speed's noise at the fix (sb_lost), so the filter takes more of the
    difference for speed, less for an along-track bias (on a town's gentle starts it learned -0.58 m/s^2, and the car's speed grew at
    +0.53 m/s^2 standing at the next lights). The deadband is held at l from the fix (deadband_ramp_s 0): with the
    ramp, a second after a fix it is l / 10 and keeps nothing of 0.025 g out."""
    samples, dt = _samples(200, accel_g=(0.025, 0.0, 1.0))
    steps = []
    for k in range(1, 5):
        steps += [("p", samples, dt), ("v", 1.0 + 0.025 * G * k, 0.0)]
    start = _still(flags=float(F.VEHICLE), since_fix=0.0, gps_ok=0.5, gps_speed=1.0, speed=1.0, align_c=ALIGNED)
    trace = run(impl, steps, tmp_path, params=replace(FCFG, deadband_ramp_s=0.0), start=start)
    assert not np.any(trace.series("flags").astype(int) & (F.AT_REST | F.WALKING))
    assert abs(trace.at(-1, "bias")) < 0.1  # -0.083 m/s^2; -0.127 before the deadband's loss was counted
    assert trace.at(-1, "speed") == pytest.approx(1.0 + 0.1 * G, abs=0.1)
