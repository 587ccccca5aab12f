"""Simulator invariants: exact truth, the MPU-6050 model's counts and noise, the NEO-6M model and its NMEA."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from codegen.board.loader import load_board
from codegen.board.model import ACCEL_LSB_PER_G, STANDARD_GRAVITY
from codegen.kernel import reference
from codegen.sim import mpu6050, neo6m, trajectory
from codegen.sim.mpu6050 import MpuErrors, simulate_imu


@pytest.fixture(scope="module")
def board():
    return load_board(None).board


@pytest.fixture(scope="module")
def short_walk():
    return trajectory.walk(duration=40.0, seed=3)


def test_truth_is_self_consistent(short_walk):
    tr = short_walk
    dt = 1.0 / tr.rate_hz
    # velocity integrates to position, acceleration to velocity (trapezoid on the 1 kHz grid)
    v_int = np.cumsum(0.5 * (tr.acc[1:] + tr.acc[:-1]) * dt, axis=0) + tr.vel[0]
    assert np.max(np.abs(v_int - tr.vel[1:])) < 2e-3
    # the body rates, integrated with the reference's quaternion update, reproduce the orientation
    k = 10_000
    q0 = reference.matrix_to_quat(tr.rotation(0))
    mid = 0.5 * (tr.gyro[:k] + tr.gyro[1 : k + 1])
    q = reference.gyro_integrate(q0, mid, np.full(k, dt))[-1]
    r_err = reference.quat_to_matrix(q).T @ tr.rotation(k)
    assert np.degrees(np.arccos(np.clip((np.trace(r_err) - 1) / 2, -1, 1))) < 0.01


@pytest.mark.parametrize("name", trajectory.SCENARIOS)
def test_scenarios_start_at_rest_and_are_seeded(name):
    a = trajectory.make_scenario(name, seed=7, duration=60.0)
    b = trajectory.make_scenario(name, seed=7, duration=60.0)
    np.testing.assert_array_equal(a.pos, b.pos)
    rest = a.t < a.rest_s - 2.5
    f = a.specific_force()
    if a.events.get("engine_on_s", np.inf) < a.rest_s:  # a car whose engine runs: it shakes, it goes nowhere
        assert np.ptp(a.pos[rest], axis=0).max() < 1e-4
        assert np.degrees(np.sqrt(np.mean(np.sum(a.gyro[rest] ** 2, axis=1)))) < 2.0
        np.testing.assert_allclose(np.linalg.norm(f[rest], axis=1), STANDARD_GRAVITY, rtol=0.05)
        return
    assert np.max(np.abs(a.vel[rest])) < 1e-9 and np.max(np.abs(a.gyro[rest])) < 1e-9
    np.testing.assert_allclose(np.linalg.norm(f[rest], axis=1), STANDARD_GRAVITY, rtol=1e-9)


def test_ideal_output_at_rest_integrates_to_zero(board):
    tr = trajectory.static(duration=30.0, seed=2)
    t_us, counts = simulate_imu(tr, board, seed=1, errors=MpuErrors.ideal())
    assert counts.dtype == np.int16 and t_us.dtype == np.int64
    assert np.all(np.diff(t_us) == 5000)  # 200 Hz, no jitter
    assert np.all(counts == counts[0])  # no noise: every sample identical
    cfg = reference.KernelConfig.from_board(board)
    cal = reference.calibrate(counts[:2000], cfg)
    assert not cal.moved
    dt = np.diff(t_us)[: len(counts) - 1] * 1e-6
    a, _ = reference.enu_acceleration(counts[:-1], dt, cal.q, cal.gyro_bias_lsb, cfg)
    _, pos = reference.integrate_zoh(a, dt)
    assert np.max(np.abs(pos[-1, :2])) < 1e-9


def test_ideal_output_moving_integrates_to_truth(board, short_walk):
    """Counts of the ideal model, rotated by the true orientation, integrate back to the true path."""
    tr = short_walk
    t_us, counts = simulate_imu(tr, board, seed=1, errors=MpuErrors.ideal())
    f, w = mpu6050.counts_to_si(counts, board)
    t = t_us * 1e-6
    idx = np.minimum(np.round(t * tr.rate_hz).astype(int), len(tr.t) - 1)
    a = np.einsum("nij,nj->ni", tr.rotation(idx), f)
    a[:, 2] -= STANDARD_GRAVITY
    start = np.searchsorted(t, 15.0)
    stop = np.searchsorted(t, 35.0)
    # centred sampling: each sample's acceleration held over the half-steps either side (trapezoid-like)
    dt = np.diff(t[start:stop])
    acc = 0.5 * (a[start : stop - 1] + a[start + 1 : stop])
    _, pos = reference.integrate_zoh(acc, dt, tr.vel[idx[start]])
    moved = tr.pos[idx[stop - 1], :2] - tr.pos[idx[start], :2]
    assert np.linalg.norm(moved) > 15.0
    assert np.linalg.norm(pos[-1, :2] - moved) < 0.05


def test_saturation_and_quantisation(board):
    n = 2001
    t = np.arange(n) / 1000.0
    acc = np.zeros((n, 3))
    acc[:, 0] = 3.0 * STANDARD_GRAVITY  # beyond the +-2 g range
    zero = np.zeros((n, 3))
    gyro = np.tile(np.radians([300.0, -300.0, 1.0]), (n, 1))  # beyond +-250 deg/s on x and y
    tr = trajectory.Trajectory("sat", t, zero, zero, acc, zero, gyro, 0.0)
    _, counts = simulate_imu(tr, board, errors=MpuErrors.ideal())
    assert np.all(counts[:, 0] == 32767)
    assert np.all(counts[:, 2] == int(ACCEL_LSB_PER_G[2]))  # +1 g on z, exactly
    assert np.all(counts[:, 3] == 32767) and np.all(counts[:, 4] == -32768)
    assert np.all(counts[:, 5] == 131)


def test_axis_remap_is_undone(board):
    turned = board.model_copy(update={"imu": board.imu.model_copy(update={"axes": ("-y", "x", "z")})})
    tr = trajectory.walk(duration=15.0, seed=1)
    _, plain = simulate_imu(tr, board, errors=MpuErrors.ideal())
    _, raw = simulate_imu(tr, turned, errors=MpuErrors.ideal())
    assert not np.array_equal(plain, raw)
    np.testing.assert_array_equal(reference.remap_axes(raw, turned.imu.axis_map), plain)


def _allan(x: np.ndarray, rate: float, tau: float) -> np.ndarray:
    m = int(round(tau * rate))
    k = len(x) // m
    means = x[: k * m].reshape(k, m, -1).mean(axis=1)
    return np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2, axis=0))


def test_allan_deviation_matches_noise_density(board):
    """White region of the Allan deviation: sigma(tau) = density / sqrt(2 tau) (one-sided density)."""
    errors = MpuErrors().noise_only()
    tr = trajectory.static(duration=400.0, seed=0)
    t_us, counts = simulate_imu(tr, board, seed=5, errors=errors)
    f, w = mpu6050.counts_to_si(counts, board)
    rate = 1e6 / np.mean(np.diff(t_us))
    for tau in (0.5, 2.0):
        acc_adev = _allan(f, rate, tau) / STANDARD_GRAVITY * 1e6  # ug
        gyro_adev = np.degrees(_allan(w, rate, tau))  # deg/s
        np.testing.assert_allclose(acc_adev, errors.accel_noise_ug_rthz / np.sqrt(2 * tau), rtol=0.2)
        np.testing.assert_allclose(gyro_adev, errors.gyro_noise_dps_rthz / np.sqrt(2 * tau), rtol=0.2)


def test_device_errors_stay_within_datasheet_bounds():
    rng = np.random.default_rng(0)
    errors = MpuErrors()
    for _ in range(200):
        d = mpu6050.draw_device(errors, rng)
        assert np.all(np.abs(d.accel_offset) <= np.array([50, 50, 80]) * 1e-3 * STANDARD_GRAVITY)
        assert np.all(np.abs(np.degrees(d.gyro_offset)) <= 20.0)
        assert np.all(np.abs(np.diag(d.accel_matrix) - 1) <= 0.03)
        assert np.all(np.abs(d.gyro_matrix - np.diag(np.diag(d.gyro_matrix))) <= 0.02)


def test_jittered_timestamps_increase(board):
    tr = trajectory.static(duration=20.0)
    t_us, _ = simulate_imu(tr, board, seed=3)
    steps = np.diff(t_us)
    assert np.all(steps > 0)
    assert abs(np.mean(steps) - 5000) < 5 and np.std(steps) > 20


def test_nmea_checksums_and_round_trip():
    tr = trajectory.car(duration=200.0, seed=4)
    track = neo6m.simulate_gps(tr, seed=2, outages=[(50.0, 70.0)])
    lines = neo6m.nmea_sentences(track)
    assert all(line.startswith(b"$GP") and line.endswith(b"\r\n") for line in lines)
    assert {line[3:6] for line in lines} == {b"RMC", b"VTG", b"GGA", b"GSA"}
    assert all(len(line) <= 82 for line in lines)  # NMEA 0183 maximum sentence length
    fixes = neo6m.parse_nmea(lines)
    assert len(fixes) == len(track.t)
    valid = np.array([f.valid for f in fixes])
    np.testing.assert_array_equal(valid, track.valid)
    assert not valid[55] and valid[49] and valid[70]
    lat = np.array([f.lat for f in fixes if f.valid])
    lon = np.array([f.lon for f in fixes if f.valid])
    assert np.max(np.abs(lat - track.lat[track.valid])) < 1e-5 / 60 * 0.51
    assert np.max(np.abs(lon - track.lon[track.valid])) < 1e-5 / 60 * 0.51
    speed = np.array([f.speed for f in fixes if f.valid])
    np.testing.assert_allclose(speed, track.speed[track.valid], atol=0.0006)
    # back to the truth, within the model's errors
    enu = neo6m.geodetic_to_enu(lat, lon, np.zeros_like(lat), track.origin)
    truth = tr.at(track.t[track.valid])
    err = np.linalg.norm(enu[:, :2] - truth[:, :2], axis=1)
    sigma = 2.5 / neo6m.CEP_PER_SIGMA
    assert np.max(err) < 5 * sigma
    true_speed = np.linalg.norm(tr.velocity_at(track.t[track.valid])[:, :2], axis=1)
    assert np.max(np.abs(speed - true_speed)) < 5 * 0.1 * np.sqrt(2)
    course = [f.course for f in fixes if f.valid]
    slow = true_speed < 0.3
    assert all(c is None for c, s in zip(course, slow) if s)


def test_position_error_statistics_match_cep():
    tr = trajectory.static(duration=4000.0, rate=10.0)
    for quality in ("open-sky", "poor"):
        track = neo6m.simulate_gps(tr, seed=11, quality=quality)
        err = np.linalg.norm(track.enu[:, :2] - tr.at(track.t)[:, :2], axis=1)
        cep = neo6m.QUALITY[quality][0]
        assert 0.7 * cep < np.median(err) < 1.4 * cep


@settings(max_examples=300, deadline=None)
@given(st.floats(-89.9999, 89.9999), st.floats(-179.9999, 179.9999), st.floats(0, 80), st.floats(0, 359.99))
def test_nmea_fields_round_trip_anywhere(lat, lon, speed, course):
    one = trajectory.static(duration=1.0, rate=10.0)
    track = neo6m.simulate_gps(one, quality="rtk", origin=(lat, lon, 100.0))
    track.speed[:], track.course[:] = speed, course
    lines = neo6m.nmea_sentences(track)
    fix = neo6m.parse_nmea(lines)[0]
    assert abs(fix.lat - track.lat[0]) <= 0.51e-5 / 60 and abs(fix.lon - track.lon[0]) <= 0.51e-5 / 60
    # course has 2 decimals: at most half a unit off (0.875 -> 0.88), plus the parse's float rounding
    assert abs(fix.speed - speed) < 0.0006 and abs(fix.course - course) <= 0.005 + 1e-12
    for line in lines:
        fields = line.decode().split(",")
        if fields[0] == "$GPRMC":
            assert float(fields[3][2:]) < 60 and float(fields[5][3:]) < 60


def test_nmea_minutes_carry_into_degrees():
    assert neo6m._lat_field(40.9999999999) == "4100.00000,N"
    assert neo6m._lon_field(-105.99999999999) == "10600.00000,W"
    assert neo6m._lat_field(-0.5) == "0030.00000,S"
