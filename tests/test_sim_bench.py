"""The benchmark's machinery: method contract (no GPS after the outage start), metrics, replay, CLI."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from codegen.board.loader import load_board
from codegen.cli import main
from codegen.sim import methods as methods_mod
from codegen.sim.mpu6050 import MpuErrors
from codegen.sim.run import RunData, build_run, evaluate, format_table
from conftest import require_shared_data


@pytest.fixture(scope="module")
def board():
    return load_board(None).board


@pytest.fixture(scope="module")
def walk_run(board):
    return build_run("walk", board, seed=2, duration=110.0)


def test_baselines_are_registered():
    assert {"seed", "const-velocity", "hold-last-fix"} <= set(methods_mod.registered_methods())


def _blind_after(run: RunData, start: float) -> RunData:
    """The same run with every fix from `start` on invalid and moved far away: a method must not notice."""
    gps = run.gps
    late = gps.t >= start
    blind = dataclasses.replace(gps, valid=gps.valid & ~late, enu=np.where(late[:, None], 1e6, gps.enu),
                                speed=np.where(late, 99.0, gps.speed), course=np.where(late, 45.0, gps.course))
    return dataclasses.replace(run, gps=blind, cache={})


@pytest.mark.parametrize("name", sorted(methods_mod.registered_methods()))
def test_methods_use_no_gps_after_the_outage_start(walk_run, name):
    fn = methods_mod.registered_methods()[name]
    starts = np.array([25.5, 47.5])
    times = starts[:, None] + np.array([0.0, 10.0, 30.0])
    est = fn(walk_run, starts, times)
    assert est.shape == (2, 3, 2)
    for i, start in enumerate(starts):
        alone = fn(_blind_after(walk_run, start), starts[i : i + 1], times[i : i + 1])
        np.testing.assert_allclose(alone[0], est[i], atol=1e-9)


def test_at_rest_with_perfect_gps_every_method_stays_put(board):
    run = build_run("static", board, seed=1, quality="rtk", duration=90.0, errors=MpuErrors.ideal())
    result = evaluate(run, horizons=(10.0, 30.0))
    for name, err in result.errors.items():
        # the baselines are exact at rest; a plug-in (a filter) may wobble, but not wander off
        assert np.nanmax(err) < (1e-6 if name in ("seed", "const-velocity", "hold-last-fix") else 1.0), name


def test_seed_method_from_its_own_pipeline(board):
    """With an ideal IMU and perfect GPS the seed's method follows a straight push (its own test), within E."""
    run = build_run("push", board, seed=0, quality="rtk", errors=MpuErrors.ideal())
    result = evaluate(run, horizons=(10.0,), methods={"seed": methods_mod.seed_method})
    first = result.push_e["seed"][0]  # the first push goes along x = East: the seed's frame is ENU
    assert first < 0.5
    assert np.all(np.isfinite(result.push_e["seed"]))


def test_fast_orientation_matches_the_reference(walk_run, board):
    from codegen.kernel import reference

    cfg = reference.KernelConfig.from_board(board)
    samples = walk_run.counts[3000:5000]
    dt = np.diff(walk_run.t_us[3000:5001]) * 1e-6
    q0 = reference.quat_normalise(np.array([0.9, 0.1, -0.2, 0.3]))
    bias = np.array([12.0, -40.0, 7.0])
    a_ref, q_ref = reference.enu_acceleration(samples, dt, q0, bias, cfg)
    a, q = methods_mod.enu_acceleration(samples, dt, q0, bias, cfg)
    np.testing.assert_allclose(q, q_ref, atol=1e-9)
    np.testing.assert_allclose(a, a_ref, atol=1e-8)


def test_all_starts_integration_equals_the_reference(walk_run):
    from codegen.kernel import reference

    t, held, dt = methods_mod.seed_acceleration(walk_run)
    t_start = np.array([t[400] - 0.002, t[3000]])
    v0 = np.array([[0.5, -1.0], [1.2, 0.3]])
    times = np.array([[t[1400], t[2400]], [t[3500], t[9000]]])
    got = methods_mod.zoh_from(t, held, dt, t_start, v0, times)
    for i, (s, ends) in enumerate(((400, (1400, 2400)), (3000, (3500, 9000)))):
        for j, e in enumerate(ends):
            v_start = np.append(v0[i], 0.0)
            _, pos = reference.integrate_zoh(held[s:e], dt[s:e], v_start)
            expect = pos[-1, :2] + v0[i] * (t[s] - t_start[i])
            np.testing.assert_allclose(got[i, j], expect, atol=1e-9)


def test_metrics_table(walk_run):
    result = evaluate(walk_run, horizons=(10.0, 30.0))
    text = format_table([result])
    assert "10 s med" in text and "30 s med" in text
    for name in ("seed", "const-velocity", "hold-last-fix"):
        assert name in text
    # the error at the moment of loss is the last fix's own error, identical for every method but fused, which
    # starts from the fix smoothed with the Doppler (codegen.kernel.fused.position_update): metres from it, not more
    # (eskf and eskf-c on a walk are fused with fused_platform: pedestrian, and start there too)
    zero = {name: err[:, 0] for name, err in result.errors.items()}
    for name, err in zero.items():
        if name not in ("fused", "eskf", "eskf-c"):
            np.testing.assert_allclose(err, zero["hold-last-fix"], atol=1e-9)
    from codegen.kernel import fused

    idx = walk_run.gps.last_valid_before(result.starts)
    t_fix = walk_run.gps.t[idx][:, None]
    moved = fused.estimate(walk_run, result.starts, t_fix)[:, 0] - walk_run.gps.enu[idx, :2]
    offset = np.linalg.norm(moved, axis=-1)
    sigma = fused.FusedConfig.from_board(walk_run.board).pos_sigma_m
    assert np.all(offset < 3 * sigma) and np.all(offset > 0.0), offset
    # hold-last-fix grows with walking distance: ~1.4 m/s
    assert 5.0 < np.nanmedian(result.errors["hold-last-fix"][:, 1]) < 25.0


def test_replay_walk(board):
    require_shared_data("gnss-imu-walk", "imu_1730_sf.csv")
    from codegen.sim import replay

    t, accel, gyro, truth = replay.load_walk(require_shared_data("gnss-imu-walk"))
    rate = (len(t) - 1) / t[-1]
    assert 140 < rate < 175 and 125 < t[-1] < 140
    assert 10.0 < truth.rest_s < 15.0  # standing still at the start: room for the 10 s calibration
    np.testing.assert_allclose(np.linalg.norm(accel[:1000].mean(axis=0)), 1.0, atol=0.03)
    run = build_run("replay-walk", board, seed=0, walk_dir=require_shared_data("gnss-imu-walk"))
    assert run.counts.dtype == np.int16
    result = evaluate(run, horizons=(10.0, 30.0), step=4.0)
    assert np.sum(np.isfinite(result.errors["seed"][:, -1])) >= 10


def test_cli_simulate(capsys, tmp_path):
    plot = tmp_path / "walk.png"
    code = main(["simulate", "--scenario", "static", "--outage", "20", "--plot", str(plot),
                 "--method", "hold-last-fix", "--method", "seed"])
    out = capsys.readouterr().out
    assert code == 0
    assert "hold-last-fix" in out and "20 s med" in out
    assert plot.stat().st_size > 10_000
    from PIL import Image

    with Image.open(plot) as image:  # three panels side by side: the run, the outage zoomed, the error curves
        assert image.width > 2.5 * image.height


def test_cli_simulate_user_errors(capsys):
    assert main(["simulate", "--scenario", "static", "--outage", "500"]) == 2
    assert "error:" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "static", "--method", "nope"]) == 2
    assert "unknown method" in capsys.readouterr().err


def test_cli_simulate_replay_walk_from_data_folder(capsys, tmp_path):
    """--data points replay-walk at the recording wherever it is (an installed deadreckon has no ../shared)."""
    walk = require_shared_data("gnss-imu-walk")
    code = main(["simulate", "--scenario", "replay-walk", "--data", str(walk), "--outage", "10",
                 "--method", "hold-last-fix"])
    out = capsys.readouterr().out
    assert code == 0
    assert "replay-walk" in out and "hold-last-fix" in out


def test_cli_simulate_replay_walk_names_the_missing_file_and_the_option(capsys, tmp_path):
    partial = tmp_path / "walk"
    partial.mkdir()
    (partial / "imu_1730_sf.csv").write_text("0,0,0,1,0,0,0\n")
    assert main(["simulate", "--scenario", "replay-walk", "--data", str(partial)]) == 2
    err = capsys.readouterr().err
    assert f"{partial} has no gnss_1730_sf.pos (--data)" in err and "hint: --data DIR" in err
    assert main(["simulate", "--scenario", "replay-walk", "--data", str(tmp_path / "absent")]) == 2
    assert "is not a folder (--data)" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "static", "--data", str(partial)]) == 2
    assert "--data is the recorded walk's folder" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "walk", "--on-micropython", "--data", str(partial)]) == 2
    assert "--on-micropython does not run" in capsys.readouterr().err


def test_on_micropython_the_app_follows_the_reference(capsys, tmp_path):
    """The generated app on the unix-port MicroPython, fed by the models, lands where its method's reference does."""
    from conftest import require_tool

    require_tool("micropython")
    from codegen.sim import trajectory
    from codegen.sim.onmicropython import run_on_micropython

    # a quick run: 2 s calibration (a board extending the default), walking from 4 s, GPS lost at 8.5 s
    yaml = tmp_path / "fastcal.yaml"
    yaml.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-fastcal\nalgorithm:\n  calibration_s: 2.0\n")
    walk = trajectory.walk(duration=20.0, rest_s=4.0, seed=1)
    rows = run_on_micropython(load_board(yaml), "walk", 5.0, (2.5, 5.0), seed=1, work=tmp_path / "run",
                              t_loss=8.5, traj=walk)
    out = capsys.readouterr().out
    print(out)
    mode = load_board(yaml).board.algorithm.mode  # the method the app runs (fused by default)
    assert "app (MicroPython)" in out and f"{mode} (reference)" in out
    app, ref = rows["app (MicroPython)"], rows[f"{mode} (reference)"]
    board = load_board(yaml).board
    # 2.5 s in, the app still shows its last fix (it declares the fix lost after gps.fix_timeout_s); by 5 s it dead
    # reckons, and the screen may show a position up to one refresh old, from the last fix, whose sentences arrive
    # 0.1 s after its epoch (the emulated chip serves each moment's sample: the IMU does not lag the truth): at a
    # walker's 1.6 m/s at most, that is the bound
    assert board.gps.fix_timeout_s < 5.0
    lag_s = board.display.refresh_ms / 1000 + 0.1
    assert abs(app[-1] - ref[-1]) < 1.6 * lag_s + 0.1, (app, ref)
    assert abs(app[0] - rows["hold-last-fix (reference)"][0]) < 1.6 * lag_s + 0.1, app


def test_replay_car(board):
    """The real car as the device would see it: the board's IMU rate, 1 Hz fixes on whole UTC seconds, the pose as
    truth; the baselines land where a car at 8-20 m/s puts them."""
    from codegen.sim.run import REAL_CAR

    folder = require_shared_data("car-comma2k19", "processed_log").parent
    run = build_run(REAL_CAR, board, seed=0, car_dir=folder)
    assert run.counts.dtype == np.int16
    np.testing.assert_allclose(np.median(np.diff(run.t_us)), 1e6 / board.imu.sample_rate_hz, rtol=1e-3)
    assert 55 <= len(run.gps.t) <= 61 and np.all(np.abs(np.diff(run.gps.t) - 1.0) < 0.2)
    # a level car, forward-left-up: gravity on the board's +z
    f = run.counts[:2000, :3].mean(axis=0)
    assert f[2] > 0.95 * np.linalg.norm(f)
    result = evaluate(run, (10.0,), methods={m: methods_mod.METHODS[m] for m in ("hold-last-fix", "const-velocity")},
                      step=5.0)
    hold, cv = (np.nanmedian(result.errors[m][:, 1]) for m in ("hold-last-fix", "const-velocity"))
    assert 100.0 < hold < 230.0 and cv < 40.0, (hold, cv)


def test_table_ci_gives_mean_and_worst(walk_run):
    from codegen.sim.run import format_table_ci

    result = evaluate(walk_run, horizons=(10.0, 30.0),
                      methods={m: methods_mod.METHODS[m] for m in ("hold-last-fix", "const-velocity")})
    text = format_table_ci([result], resamples=50)
    rows = [line.split() for line in text.splitlines()]
    worst = [r for r in rows if r and r[0] == "worst"]
    mean = [r for r in rows if r and r[0] == "mean"]
    assert len(worst) == len(mean) == 2
    for row, name in zip(worst, ("hold-last-fix", "const-velocity")):
        assert float(row[1]) == pytest.approx(np.nanmax(result.errors[name][:, 1]), abs=0.05)
        assert float(row[4]) == pytest.approx(np.nanmax(result.errors[name][:, 2]), abs=0.05)
    for row, name in zip(mean, ("hold-last-fix", "const-velocity")):
        assert float(row[1]) == pytest.approx(np.nanmean(result.errors[name][:, 1]), abs=0.05)


def test_benchmark_forces_each_platform(board):
    """benchmarks/accuracy.py runs fused with fused_platform forced beside the board's own: each variant runs the
    fused pass with that platform, and a pedestrian's model of a car is not the vehicle's."""
    import sys

    from codegen.kernel import fused
    from codegen.kernel.layout import FUSED
    from codegen.sim.run import REAL_CAR
    from conftest import ROOT

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import accuracy

    run = build_run(REAL_CAR, board, seed=0, car_dir=require_shared_data("car-comma2k19", "processed_log").parent)
    chosen = {m: accuracy.benchmark_methods()[m] for m in ("fused", "fused-vehicle", "fused-pedestrian")}
    result = evaluate(run, (10.0,), methods=chosen, step=5.0)
    platforms = sorted(int(key[1].platform) for key in run.cache if key[0] == "fused_pass" and key[1] is not None)
    assert platforms == sorted(FUSED.param("platform").code(p) for p in accuracy.PLATFORMS)
    assert fused.FusedConfig.from_board(board).platform == FUSED.param("platform").code("auto")
    assert not np.allclose(result.errors["fused-pedestrian"], result.errors["fused-vehicle"])


def test_benchmark_names_a_missing_recording_before_any_work(monkeypatch, tmp_path, capsys):
    """A benchmark run where ../shared/data is not beside the checkout (a git worktree elsewhere) stops at once with
    the folder or file it lacks and a hint, not with a traceback minutes into the run; the recordings where they
    are pass the check."""
    import sys

    from codegen.sim import comma, replay
    from codegen.sim.run import REAL_CAR, missing_recordings
    from conftest import ROOT

    require_shared_data("car-comma2k19", "processed_log")
    require_shared_data("gnss-imu-walk", replay.IMU_FILE)
    assert missing_recordings(["walk", "replay-walk", REAL_CAR]) is None
    car = tmp_path / "car"
    (car / "processed_log" / "IMU" / "accelerometer").mkdir(parents=True)
    (car / "processed_log" / "IMU" / "accelerometer" / "t").write_bytes(b"")
    monkeypatch.setattr(comma, "default_car_dir", lambda: car)
    monkeypatch.setattr(replay, "default_walk_dir", lambda: tmp_path / "no-walk")
    assert missing_recordings(["walk", "car"]) is None  # simulated scenarios read nothing
    text = missing_recordings(["walk", REAL_CAR, "replay-walk"])
    assert f"replay-car: {car} lacks processed_log/IMU/accelerometer/value" in text
    assert f"replay-walk: the folder {tmp_path / 'no-walk'} is missing" in text
    assert "hint:" in text
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import accuracy

    def no_work(*args):
        raise AssertionError("a job started before the check")

    monkeypatch.setattr(accuracy, "_run_all", no_work)
    with pytest.raises(SystemExit) as stop:
        accuracy.main(["--scenario", "walk", "--scenario", REAL_CAR])
    assert str(stop.value) == missing_recordings([REAL_CAR])
