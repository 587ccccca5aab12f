"""The error-state Kalman filter for vehicles (codegen/kernel/eskf.py, float64 reference):

- each hand-expanded step against the generic matrix form on random states: the block propagation against
  Phi P Phi^T + Q, the receiver error's step against its own Phi P Phi^T + Q, the sequence of scalar updates against
  the Joseph form (I - K H) P (I - K H)^T + K R K^T with K = P H^T S^-1, and the NHC rows against numerical
  derivatives of the constraint;
- the covariance symmetric positive semi-definite after every step over a simulated car drive with outages (GPS,
  NHC, zero-velocity steps all observed), and a broken one repaired and counted;
- physics: a known constant acceleration and turn through the strapdown step, a stationary device whose vertical
  accelerometer bias the zero-velocity updates find, a mounting yaw error the non-holonomic constraint finds;
- the start: the yaw fit finds the yaw and the offset a calibration in motion leaves, levels that tilt, waits while
  nothing is observable, and starts the real car (car-comma2k19, calibrated on the move) within seconds;
- the method contract: no GPS after an outage's start is used.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from codegen.board.loader import load_board
from codegen.kernel import eskf as E
from codegen.kernel.reference import STANDARD_GRAVITY, KernelConfig
from codegen.sim.run import build_run

CFG = E.EskfConfig()
KCFG = KernelConfig()
CASES = 6


def _random_covariance(rng, n=E.N_ERR, scale=1.0):
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T / n + 0.1 * np.eye(n))


def _random_rotation(rng):
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    return E._rotation(*q), q


@pytest.mark.parametrize("case", range(CASES))
def test_block_propagation_equals_the_matrix_form(case):
    rng = np.random.default_rng(case)
    p = _random_covariance(rng)
    t = rng.uniform(0.02, 0.3)
    r, _ = _random_rotation(rng)
    a = r * t + 0.01 * rng.standard_normal((3, 3))
    b = r * rng.uniform(-0.1, 0.1) + 0.01 * rng.standard_normal((3, 3))
    dv = rng.standard_normal(3) * 3.0
    phi = E.transition(a, b, dv, t)
    clipped = rng.uniform(0.0, 1.0) if case % 2 else 0.0
    want = phi @ p @ phi.T + E.process_noise(t, CFG, clipped)
    got = E.propagate_covariance(p, a, b, dv, t, CFG, clipped)
    assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want))
    assert np.array_equal(got, got.T)


@pytest.mark.parametrize("case", range(CASES))
def test_receiver_error_step_equals_the_matrix_form(case):
    rng = np.random.default_rng(100 + case)
    p = _random_covariance(rng)
    t = rng.uniform(0.2, 5.0)
    got, phi = E.gps_error_step(p, t, CFG)
    f = np.eye(E.N_ERR)
    q = np.zeros((E.N_ERR, E.N_ERR))
    for i, sigma in enumerate((CFG.gps_pos_sigma, CFG.gps_pos_sigma, CFG.gps_up_sigma)):
        f[E.ERR_GE + i, E.ERR_GE + i] = math.exp(-t / CFG.gps_tau_s)
        q[E.ERR_GE + i, E.ERR_GE + i] = sigma * sigma * (1.0 - math.exp(-2.0 * t / CFG.gps_tau_s))
    want = f @ p @ f.T + q
    assert phi == pytest.approx(math.exp(-t / CFG.gps_tau_s), rel=1e-15)
    assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want))


@pytest.mark.parametrize("case", range(CASES))
def test_scalar_updates_equal_the_joseph_form(case):
    rng = np.random.default_rng(200 + case)
    p = _random_covariance(rng, scale=rng.uniform(0.1, 10.0))
    m = int(rng.integers(1, 7))
    h = np.zeros((m, E.N_ERR))
    for row in h:  # sparse rows, as every measurement of the filter has
        cols = rng.choice(E.N_ERR, size=int(rng.integers(1, 7)), replace=False)
        row[cols] = rng.standard_normal(len(cols))
    r = rng.uniform(0.01, 2.0, size=m)
    y = rng.standard_normal(m)
    pk, dx = p, np.zeros(E.N_ERR)
    for i in range(m):
        pk, dx = E.scalar_update(pk, dx, h[i], y[i], r[i])
    s = h @ p @ h.T + np.diag(r)
    k = p @ h.T @ np.linalg.inv(s)
    ikh = np.eye(E.N_ERR) - k @ h
    want = ikh @ p @ ikh.T + k @ np.diag(r) @ k.T
    assert np.max(np.abs(pk - want)) <= 1e-10 * np.max(np.abs(p))
    assert np.max(np.abs(dx - k @ y)) <= 1e-10 * max(1.0, np.max(np.abs(k @ y)))


def _state(rng):
    st = E.EskfState()
    _, q = _random_rotation(rng)
    st.qw, st.qx, st.qy, st.qz = q
    st.ve, st.vn, st.vu = rng.standard_normal(3) * 8.0
    c, _ = _random_rotation(rng)
    st.c = c
    return st


def _vehicle_velocity(st):
    return st.c @ st.rotation().T @ np.array([st.ve, st.vn, st.vu])


@pytest.mark.parametrize("case", range(CASES))
def test_nhc_rows_are_the_constraints_derivative(case):
    """Each column of H against a central difference of v_vehicle[1:3] under the error's injection."""
    rng = np.random.default_rng(300 + case)
    st = _state(rng)
    h, pred = E.nhc_rows(st)
    assert np.allclose(pred, _vehicle_velocity(st)[1:3], atol=1e-12)
    eps = 1e-6
    for col in list(range(E.ERR_V, E.ERR_TH + 3)) + [E.ERR_MU, E.ERR_MU + 1]:
        plus, minus = st.copy(), st.copy()
        dx = np.zeros(E.N_ERR)
        dx[col] = eps
        E.inject(plus, dx)
        E.inject(minus, -dx)
        numeric = (_vehicle_velocity(plus)[1:3] - _vehicle_velocity(minus)[1:3]) / (2 * eps)
        assert np.allclose(h[:, col], numeric, atol=1e-6), col
    others = [c for c in range(E.N_ERR) if not (E.ERR_V <= c < E.ERR_TH + 3 or E.ERR_MU <= c < E.ERR_MU + 2)]
    assert not np.any(h[:, others])


# --------------------------------------------------------------------------------------------- PSD over a drive
@pytest.fixture(scope="module")
def board():
    return load_board(None).board


@pytest.fixture(scope="module")
def car_run(board):
    return build_run("car", board, seed=2, duration=150.0)


def _psd(p):
    scale = np.max(np.abs(p))
    return np.array_equal(p, p.T) and np.linalg.eigvalsh(p)[0] >= -E.PSD_TOL * scale


def test_covariance_stays_psd_over_a_drive_with_outages(car_run):
    steps = {"predict": 0, "update": 0}
    bad = []

    def check(st, step):
        steps[step] += 1
        if not _psd(st.p):
            bad.append(step)

    counts = {"nhc": 0, "zupt": 0}
    nhc, zupt = E.nhc_update, E.zero_velocity_update

    def count_nhc(st, cfg):
        counts["nhc"] += 1
        nhc(st, cfg)

    def count_zupt(st, cfg):
        counts["zupt"] += 1
        zupt(st, cfg)

    previous = E.observe_covariances(check)
    E.nhc_update, E.zero_velocity_update = count_nhc, count_zupt
    try:
        starts = np.arange(30.5, 90.0, 10.0)
        times = starts[:, None] + np.array([10.0, 30.0, 60.0])[None, :]
        est = E.estimate(car_run, starts, times)
    finally:
        E.observe_covariances(previous)
        E.nhc_update, E.zero_velocity_update = nhc, zupt
    snaps = car_run.cache[("eskf_pass", CFG)][4]
    last = snaps[max(snaps)][1]
    assert last.aligned and last.cov_repairs == 0
    assert steps["predict"] > 1000 and steps["update"] > 500 and counts["nhc"] > 500 and counts["zupt"] > 10
    assert not bad
    err = np.linalg.norm(est - car_run.truth.at(times)[..., :2], axis=-1)
    assert np.median(err[:, 0]) < 10.0  # 10 s into an outage: a working filter, not a diverged one


def test_a_broken_covariance_is_repaired_and_counted():
    st = E.EskfState()
    st.aligned = True
    st.p = E._prior(st, CFG)
    st.p[E.ERR_V, E.ERR_V] = -1.0
    st.acc_t = 0.1
    st.acc_a = 0.1 * np.eye(3)
    E.propagate(st, CFG)
    assert st.cov_repairs == 1.0
    assert np.array_equal(st.p, E._prior(st, CFG))


# --------------------------------------------------------------------------------------------- physics
def _started(yaw=0.0, vel=(0.0, 0.0)):
    st = E.EskfState()
    st.qw, st.qz = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    E.start(st, 0.0, (0.0, 0.0, 0.0), vel, CFG)
    return st


def test_constant_acceleration_and_turn_through_the_strapdown_step():
    """Level, facing North-West (yaw 45 deg from East), 1.5 m/s^2 along body x for 8 s: v = a t, p = a t^2 / 2
    along that heading; then a constant rate about z turns the heading by rate x time."""
    st = _started(yaw=math.radians(135.0))
    n, dt, a = 1600, 0.005, 1.5
    cfg = E.EskfConfig(nhc_dt_s=1e9)  # the strapdown step alone (no pseudo-measurement)
    E.mechanise(st, [[a, 0.0, STANDARD_GRAVITY]] * n, [[0.0, 0.0, 0.0]] * n, [dt] * n, KCFG, cfg)
    heading = np.array([math.cos(math.radians(135.0)), math.sin(math.radians(135.0))])
    t = n * dt
    assert np.allclose([st.ve, st.vn], a * t * heading, atol=1e-9)
    assert np.allclose([st.pe, st.pn], 0.5 * a * t * t * heading, atol=1e-7)
    assert abs(st.vu) < 1e-9 and abs(st.pu) < 1e-9
    rate_counts = 20.0 * KCFG.gyro_lsb_per_dps  # 20 deg/s
    E.mechanise(st, [[0.0, 0.0, STANDARD_GRAVITY]] * 400, [[0.0, 0.0, rate_counts]] * 400, [dt] * 400, KCFG, cfg)
    yaw = math.degrees(math.atan2(2 * (st.qw * st.qz + st.qx * st.qy), 1 - 2 * (st.qy ** 2 + st.qz ** 2)))
    step = math.radians(20.0) * dt  # the normalised first-order step turns by 2 atan(step / 2) = step - step^3 / 12
    assert abs(yaw - (135.0 + 20.0 * 400 * dt)) <= 1.01 * 400 * math.degrees(step ** 3 / 12.0)


def _rest_counts(rng, offset_ms2, scale, n=400):
    """n raw samples (int16 counts, [ax ay az gx gy gz]) of a device at rest in a random attitude whose accelerometer
    reads scale * f + offset (m/s^2, body), with noise."""
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    r = E._rotation(*q)
    f = scale * (r.T @ np.array([0.0, 0.0, STANDARD_GRAVITY])) + offset_ms2
    acc = (f + rng.normal(0.0, 0.05, (n, 3))) / KCFG.accel_ms2_per_lsb
    gyr = rng.normal(0.0, 3.0, (n, 3))
    return np.round(np.hstack([acc, gyr])).astype(np.int16)


@pytest.mark.parametrize("case", range(CASES))
def test_calibration_takes_the_accelerometers_error_along_gravity_as_its_bias(case):
    """At rest in any attitude, with the MPU-6050's offsets (up to 80 mg) and scale error (3 %): after calibration
    the bias-corrected mean specific force, turned by the attitude, is gravity exactly, so a device that stays still
    reads no vertical acceleration (before, the mean's length less g read as one until a constraint learnt it)."""
    rng = np.random.default_rng(300 + case)
    offset = rng.uniform(-1.0, 1.0, 3) * np.array([0.05, 0.05, 0.08]) * STANDARD_GRAVITY
    counts = _rest_counts(rng, offset, 1.0 + rng.uniform(-0.03, 0.03))
    st = E.EskfState()
    E.calibrate(st, counts, KCFG)
    mean = counts[:, :3].mean(axis=0) * KCFG.accel_ms2_per_lsb
    level = st.rotation() @ (mean - np.array([st.bax, st.bay, st.baz]))
    assert np.allclose(level, [0.0, 0.0, STANDARD_GRAVITY], atol=1e-9)
    assert abs(np.linalg.norm(mean) - STANDARD_GRAVITY) > 0.05  # the case has an error along gravity to take


def test_zero_velocity_updates_find_a_vertical_accelerometer_bias():
    """A level device at rest whose accelerometer reads 0.08 m/s^2 too much on its up axis (a bias that came after
    the calibration): the zero-velocity updates take the vertical velocity it gathers as that bias."""
    st = _started()
    bias = 0.08
    n, dt = 6000, 0.005  # 30 s
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((n, 3)) * 0.02
    acc = (noise + [0.0, 0.0, STANDARD_GRAVITY + bias]).tolist()
    E.mechanise(st, acc, [[0.0, 0.0, 0.0]] * n, [dt] * n, KCFG, CFG)
    assert st.baz == pytest.approx(bias, abs=0.01)
    assert abs(st.vu) < 0.02
    sigma = math.sqrt(st.p[E.ERR_BA + 2, E.ERR_BA + 2])
    assert sigma < 0.2 * CFG.init_accel_bias_ms2


def test_the_constraint_finds_a_mounting_yaw_error():
    """Driving North, level, at 10 +- 2 m/s (a surge of 0.63 m/s^2 every 20 s: the GPS velocity's changes against
    the specific force fix the body's heading), GPS every second: the filter's mounting starts 3 degrees off in yaw
    (the vehicle's forward axis is the body's x axis, the filter thinks it turned); the lateral velocity the
    constraint then sees is that angle, and the filter learns it."""
    st = _started(yaw=math.radians(90.0), vel=(0.0, 10.0))
    err = math.radians(3.0)
    st.c = np.array([[math.cos(err), -math.sin(err), 0.0], [math.sin(err), math.cos(err), 0.0], [0.0, 0.0, 1.0]])
    dt, per_fix, w = 0.005, 200, 2.0 * math.pi / 20.0
    for k in range(1, 121):
        t = (k - 1) + dt * np.arange(per_fix)
        acc = [[2.0 * w * math.cos(w * x), 0.0, STANDARD_GRAVITY] for x in t]
        E.mechanise(st, acc, [[0.0, 0.0, 0.0]] * per_fix, [dt] * per_fix, KCFG, CFG)
        north = 10.0 * k + 2.0 / w * (1.0 - math.cos(w * k))
        E.gps_update(st, float(k), (0.0, north, 0.0), (0.0, 10.0 + 2.0 * math.sin(w * k)), CFG)
    forward = st.c[0]  # the vehicle's x axis in the body frame: body x when the error is gone
    assert math.degrees(abs(math.atan2(forward[1], forward[0]))) < 0.5


# --------------------------------------------------------------------------------------------- the method contract
def test_no_gps_after_the_outage_start_is_used(car_run):
    starts = np.array([40.5, 75.5])
    times = starts[:, None] + np.array([5.0, 20.0])[None, :]
    clean = E.estimate(car_run, starts, times)
    corrupted = build_run("car", car_run.board, seed=2, duration=150.0)
    later = corrupted.gps.t >= starts[0]
    corrupted.gps.enu[later] += 500.0
    corrupted.gps.vel[later] *= -1.0
    corrupted.gps.course[later] = (corrupted.gps.course[later] + 180.0) % 360.0
    got = E.estimate(corrupted, starts[:1], times[:1])
    assert np.array_equal(got[0], clean[0])


# --------------------------------------------------------------------------------------------- the start
def _fit_case(rng, yaw, offset, intervals=12, noise=0.02):
    """A state before the start whose yaw fit has `intervals` fix intervals: the GPS's velocity change dv (ENU), the
    wander frame's du = dv turned by -yaw plus the body-fixed offset integrated over the heading, plus noise. The
    first interval spans a calibration in motion: du 0 there, and the offset is what the GPS saw."""
    st = E.EskfState()
    turn = np.exp(-1j * yaw)
    heading = 0.0
    v = complex(0.0, 15.0)
    st.al_prev = (v.real, v.imag)
    for k in range(intervals):
        heading += rng.normal(0.0, 0.05)
        s = np.exp(1j * heading) * 1.0  # 1 s intervals, the heading steady in each
        dv = complex(*rng.normal(0.0, 0.3, 2))
        if k == 0:
            dv = -offset * np.exp(1j * heading) / turn  # the calibration's mean acceleration, seen by the GPS
            du = 0.0
        else:
            du = dv * turn + offset * s + complex(*rng.normal(0.0, noise, 2))
        st.al_du = np.array([du.real, du.imag])
        st.al_s = np.array([s.real, s.imag])
        st.al_u = np.array([np.cos(heading), np.sin(heading)])
        v += dv
        E._alignment_sums(st, (v.real, v.imag))
    return st


@pytest.mark.parametrize("case", range(CASES))
def test_the_yaw_fit_finds_the_yaw_and_the_offset(case):
    """dv = z du + c s by least squares: z's angle is the yaw, -c / z the body-fixed offset, and the yaw's 1-sigma
    covers the error."""
    rng = np.random.default_rng(900 + case)
    yaw = rng.uniform(-math.pi, math.pi)
    offset = complex(*rng.normal(0.0, 0.8, 2))
    st = _fit_case(rng, yaw, offset)
    z, c, sigma = E.alignment_fit(st.al_sums)
    error = abs(math.remainder(math.atan2(z.imag, z.real) - yaw, 2 * math.pi))
    assert error <= max(3.0 * sigma, 1e-6) and sigma < math.radians(3.0)
    assert abs(abs(z) - 1.0) < 0.05
    assert abs(-c / z - offset) < 0.05


def test_the_yaw_fit_waits_without_velocity_change():
    """A run that holds its velocity (and no calibration interval) leaves the yaw undetermined: no start."""
    st = E.EskfState()
    st.al_prev = (0.0, 15.0)
    for _ in range(20):
        st.al_du = np.array([0.3, -0.1])  # an offset, no motion
        st.al_s = np.array([1.0, 0.0])
        E.align(st, 0.0, (0.0, 0.0, 0.0), (0.0, 15.0), CFG)
    assert not st.aligned
    assert E.alignment_fit(st.al_sums) is None or E.alignment_fit(st.al_sums)[2] > math.radians(CFG.align_yaw_sigma_deg)


def test_a_start_on_the_move_levels_the_tilt_it_took_for_gravity():
    """The start turns the attitude by the fitted yaw and levels it by the offset: the wander frame's horizontal
    specific force of a level device whose calibration took a 1.2 m/s^2 acceleration for gravity vanishes."""
    st = E.EskfState()
    accel = 1.2  # m/s^2 forward (body x) during the calibration: the mean specific force tilted by atan(1.2 / g)
    f_cal = np.array([accel, 0.0, STANDARD_GRAVITY])
    q = E.tilt_from_gravity(f_cal)
    st.qw, st.qx, st.qy, st.qz = (float(v) for v in q)
    level = st.rotation() @ np.array([0.0, 0.0, STANDARD_GRAVITY])  # gravity alone, as read after the calibration
    offset = complex(level[0], level[1])  # what the wander frame sees: the offset b at heading 0
    assert abs(offset) > 1.0
    st.al_u = np.array([1.0, 0.0])
    E._turn(st, offset.imag / STANDARD_GRAVITY, -offset.real / STANDARD_GRAVITY, 0.9)
    after = st.rotation() @ np.array([0.0, 0.0, STANDARD_GRAVITY])
    assert math.hypot(after[0], after[1]) < 0.01 * abs(offset)


def test_the_real_car_starts_within_seconds_of_a_calibration_in_motion():
    """car-comma2k19 starts at 8 m/s and calibrates while it speeds up to 20 m/s (its first 10 s): with the
    calibration's fix interval the filter starts by 16 s (the velocity-change correlation alone took until 33 s),
    and its 10 s outages beat the constant-velocity baseline by far."""
    board = load_board(None).board
    run = build_run("replay-car", board, seed=0)
    t, _, _, _, snaps, _ = E._pass(run, CFG)
    started = min(run.gps.t[j] for j, (_, st) in snaps.items() if st.aligned)
    assert started <= 16.0
    from codegen.sim.run import evaluate

    res = evaluate(run, (10.0,), {"eskf": E.estimate, "cv": _constant_velocity}, step=1.0)
    eskf_err, cv_err = (np.nanmedian(res.errors[m][:, 1]) for m in ("eskf", "cv"))
    assert eskf_err < 5.0 and eskf_err < 0.5 * cv_err


def _constant_velocity(run, starts, times):
    from codegen.sim.methods import registered_methods

    return registered_methods()["const-velocity"](run, starts, times)
