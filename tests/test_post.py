"""The post-processor's acceptance on synthetic runs: known mounting and motion, 0.1 m/s Doppler noise, 50 mg
accelerometer bias, an injected delay. The run goes through the CSV pair and the CLI, as a user's would; the bounds
are written in each test below."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from codegen.cli import main
from codegen.post import PostOptions, process
from codegen.post.orientation import FLAG_STATIONARY, FLAG_YAW_HELD, wrap
from codegen.post.synthetic import Scenario, make_run, write_csv_pair

INJECTED_DELAY = 0.137  # s, not a multiple of the 20 ms IMU period


def _read_angles(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    num = lambda key: np.array([float(r[key]) if r[key] else np.nan for r in rows])  # noqa: E731
    return {k: num(k) for k in ("t", "roll_deg", "pitch_deg", "yaw_deg", "lm_vs_wahba_deg")}, [r["flags"] for r in rows]


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    scenario = Scenario(delay=INJECTED_DELAY)
    log, truth = make_run(scenario)
    assert np.linalg.norm(scenario.bias_mg) >= 50.0  # the 50 mg
    folder = tmp_path_factory.mktemp("synthetic")
    imu, gps = write_csv_pair(log, folder)
    out = folder / "out"
    assert main(["post", str(imu), "--gps", str(gps), "-o", str(out), "--no-plots"]) == 0
    angles, flags = _read_angles(out / "angles.csv")
    summary = json.loads((out / "report.json").read_text())
    return scenario, truth, angles, flags, summary, out


def _errors(truth, angles):
    ok = np.isfinite(angles["roll_deg"])
    t = angles["t"][ok]
    est = np.radians(np.stack([angles["roll_deg"], angles["pitch_deg"], angles["yaw_deg"]], axis=1)[ok])
    err = np.degrees(wrap(est - truth.euler(t)))
    horizontal = np.hypot(*truth.acceleration(t)[:, :2].T)
    return err, horizontal


def test_roll_and_pitch_within_half_a_degree(cli_run):
    _, truth, angles, _, _, _ = cli_run
    err, _ = _errors(truth, angles)
    assert len(err) > 500
    assert np.abs(err[:, 0]).max() <= 0.5
    assert np.abs(err[:, 1]).max() <= 0.5


def test_yaw_within_two_degrees_where_horizontal_acceleration_is_at_least_half_a_metre(cli_run):
    _, truth, angles, _, _, _ = cli_run
    err, horizontal = _errors(truth, angles)
    moving = horizontal >= 0.5
    assert moving.sum() > 300
    assert np.abs(err[moving, 2]).max() <= 2.0


def test_lm_agrees_with_closed_form_within_a_tenth_of_a_degree(cli_run):
    _, _, angles, flags, summary, _ = cli_run
    d = angles["lm_vs_wahba_deg"]
    assert np.nanmax(d) <= 0.1
    assert summary["lm_vs_wahba_max_deg"] <= 0.1
    assert not any("lm-wahba" in f for f in flags)


def test_velocity_residual_rms_at_most_fifteen_centimetres_per_second(cli_run):
    _, _, _, _, summary, _ = cli_run
    assert summary["velocity_residual_rms_mps"] <= 0.15


def test_injected_delay_recovered_within_one_imu_sample(cli_run):
    scenario, _, _, _, summary, _ = cli_run
    assert summary["delay_estimated"]
    assert abs(summary["delay_s"] - scenario.delay) <= 1.0 / scenario.imu_rate


def test_outputs_are_written_and_readable(cli_run):
    _, _, _, _, summary, out = cli_run
    import xml.etree.ElementTree as ET

    for name in ("trajectory.csv", "trajectory.gpx", "angles.csv", "report.txt", "report.json"):
        assert (out / name).stat().st_size > 0
    points = ET.parse(out / "trajectory.gpx").getroot().findall(".//{http://www.topografix.com/GPX/1/1}trkpt")
    assert len(points) > 10 * summary["duration_s"] * 0.9
    lat = np.array([float(p.get("lat")) for p in points])
    assert np.all(np.abs(lat - 47.3769) < 0.1)
    text = (out / "report.txt").read_text()
    assert "delay" in text and "velocity" in text


def test_bias_is_estimated_from_a_rigidly_mounted_run(cli_run):
    scenario, _, _, _, summary, _ = cli_run
    bias_mg = np.array(summary["accel_bias_sensor_mps2"]) / 9.80665e-3
    assert not summary["bias_rejected"]
    assert np.abs(bias_mg - np.array(scenario.bias_mg)).max() < 10.0


def test_other_mounting_and_seed_no_delay():
    """A device mounted facing backwards-left, tilted: same bounds, through the library."""
    scenario = Scenario(mounting_deg=(-6.0, 8.0, -130.0), bias_mg=(-20.0, 40.0, -23.0), seed=7, duration=400.0)
    log, truth = make_run(scenario)
    result = process(log, PostOptions())
    o = result.orientation
    err = np.degrees(wrap(o.euler[o.valid] - truth.euler(o.t[o.valid])))
    horizontal = np.hypot(*truth.acceleration(o.t[o.valid])[:, :2].T)
    assert np.abs(err[:, :2]).max() <= 0.5
    assert np.abs(err[horizontal >= 0.5, 2]).max() <= 2.0
    assert np.nanmax(o.lm_vs_wahba_deg) <= 0.1
    assert result.velocity_residual_rms <= 0.15
    assert abs(result.delay) <= 1.0 / scenario.imu_rate


def test_standing_still_holds_yaw_and_flags_the_intervals():
    """No horizontal acceleration: roll and pitch from gravity alone, yaw held and flagged, never a guess."""
    from scipy.spatial.transform import Rotation

    from codegen.post.model import GpsSeries, ImuSeries, PostLog

    t = np.arange(0.0, 60.0, 0.02)
    rot = Rotation.from_euler("ZYX", [40.0, 3.0, -5.0], degrees=True)
    acc = np.tile(rot.inv().apply([0.0, 0.0, 9.80665]), (len(t), 1))
    acc += np.random.default_rng(0).normal(0.0, 0.02, acc.shape)
    tg = np.arange(1.0, 59.0, 1.0)
    m = len(tg)
    vel = np.random.default_rng(1).normal(0.0, 0.02, (m, 3))
    gps = GpsSeries(tg, np.full(m, 47.0), np.full(m, 8.0), np.full(m, np.nan), vel, np.full((m, 3), 0.1),
                    np.tile([2.5, 2.5, np.nan], (m, 1)), np.zeros(m, dtype=int))
    result = process(PostLog("still", ImuSeries(t, acc), gps), PostOptions(delay=0.0))
    o = result.orientation
    held = [FLAG_YAW_HELD in f for f in o.flags[1:]]
    assert all(held)
    assert all(FLAG_STATIONARY in f for f in o.flags[1:])
    e = np.degrees(o.euler[o.valid])
    assert np.abs(e[:, 0] + 5.0).max() < 0.5 and np.abs(e[:, 1] - 3.0).max() < 0.5
    assert np.ptp(e[:, 2]) < 1e-6  # yaw carried, not fitted to noise


def test_device_standing_on_its_end_is_solved_and_flagged():
    """Pitch near 90 deg (x axis up): Euler roll and yaw are not separable, the rotation still is."""
    from scipy.spatial.transform import Rotation

    log, truth = make_run(Scenario(duration=150.0, mounting_deg=(10.0, 88.0, 30.0), seed=3))
    result = process(log, PostOptions())
    o = result.orientation
    e = o.euler[o.valid]
    est = Rotation.from_euler("ZYX", np.stack([e[:, 2], e[:, 1], e[:, 0]], axis=1))
    error = np.degrees((est * truth.attitude(o.t[o.valid]).inv()).magnitude())
    assert error.max() < 2.0
    assert all("gimbal" in f for f in np.array(o.flags, dtype=object)[o.valid])
