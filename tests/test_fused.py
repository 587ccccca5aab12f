"""The fused algorithm: reference (codegen/kernel/fused.py, float64) vs the C kernel (native_ext/dr_fused.c,
float32, through cffi), on simulated streams driven exactly as the app drives the kernel (calibrate, windows of
samples, one GPS update per fix); the filters against the truth of a simulated car and receiver; the C as C
(sanitizers, the ESP32 object). Each step's test from physics, on every implementation: tests/test_fused_physics.py.

Tolerances, derived rather than picked: the C kernel rounds every operation to float32 (relative eps 2^-24 ~ 6e-8).
The orientation and the filters are contracting (tilt correction, renormalisation, gains < 1), so their rounding
stays at a few hundred eps of the value; the position is a running sum of N steps, whose rounding error is at most
N eps |p| (each addition rounds once). A threshold decision (rest, walking) taken differently by the two would show
as a difference far above these bounds, and the flags are compared exactly as well.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from codegen.board.loader import default_board, load_board
from codegen.kernel import fused as F
from codegen.kernel.reference import KernelConfig, quat_from_rotvec, quat_to_matrix

EPS32 = 2.0**-24
BOARD = default_board()
KCFG = KernelConfig.from_board(BOARD)
FCFG = F.FusedConfig.from_board(BOARD)
Q = slice(0, 4)


@pytest.fixture(scope="module")
def fk():
    from codegen.kernel.hostfused import load_fused

    return load_fused()


def _stream(scenario, seed, duration):
    from codegen.sim.run import build_run

    run = build_run(scenario, BOARD, seed=seed, duration=duration)
    return run


def _assert_heading_close(got, want, n_samples):
    """The travel direction and the turn hold, float32 against float64. u and the held angle take one rounded
    rotation per sample (n eps) of the rate about Up, which carries the quaternion's error (its bound). The smoothed
    rate forgets its errors: rates below ~1 rad/s rounded to float32 (6e-8 relative), plus q's error (1.2e-4)
    times the rates about the horizontal axes (well under 0.1 rad/s while walking), so 1e-5."""
    u = [F.IDX["ux"], F.IDX["uy"], F.IDX["held"]]
    np.testing.assert_allclose(got[u], want[u], atol=n_samples * EPS32 + 500 * EPS32 * 4)
    assert abs(got[F.IDX["rate_up"]] - want[F.IDX["rate_up"]]) < 1e-5


def _drive(run, ref, c, start_s, stop_s, fcfg=FCFG, dark=(0.0, 0.0)):
    """Samples from start_s to stop_s in the windows between GPS fixes, a GPS update at each fix; yields after
    each fix (the app's order): the reference's and the C's outputs, and the reference's flags of every sample."""
    t = run.t_us * 1e-6
    dt = np.diff(run.t_us)
    k = int(np.searchsorted(t, start_s))
    vel = run.gps.device_velocity()
    for j in range(int(math.ceil(start_s)), int(stop_s)):
        stop = int(np.searchsorted(t, float(j)))
        if stop > k:
            out_r, flags = F.process(ref, run.counts[k:stop], dt[k:stop], KCFG, fcfg)
            out_c = c.process(run.counts[k:stop], dt[k:stop])
            k = stop
            yield out_r, out_c, flags
        if dark[0] <= j < dark[1]:  # an outage: no fix reaches either
            continue
        d = run.gps.enu[j, :2] - run.gps.enu[j - 1, :2]
        F.position_update(ref, float(vel[j, 0]), float(vel[j, 1]), float(d[0]), float(d[1]), fcfg)
        c.position(float(vel[j, 0]), float(vel[j, 1]), float(d[0]), float(d[1]))
        F.gps_update(ref, float(vel[j, 0]), float(vel[j, 1]), fcfg)
        c.gps(float(vel[j, 0]), float(vel[j, 1]))


@pytest.mark.parametrize("scenario,seed,median,dark", [("walk", 11, False, ()), ("walk", 30, False, ()),
                                                        ("car", 12, False, ()), ("car", 13, True, ()),
                                                        ("car", 12, False, (25.0, 35.0))],
                         ids=["walk-11", "walk-30", "car-12", "car-13-median", "car-12-outage"])
def test_c_matches_reference_on_a_simulated_run(fk, scenario, seed, median, dark):
    """The C kernel against the reference, fix by fix; `dark`: an outage (s), whose end restarts the speed/bias and
    position filters from the fix (the restart once lost most of the speed variance's digits in float32)."""
    fcfg = replace(FCFG, median=1.0) if median else FCFG
    run = _stream(scenario, seed, 50.0)
    t = run.t_us * 1e-6
    n_cal = int(np.searchsorted(t, 10.0))
    ref = F.FusedState()
    moved_r = F.calibrate(ref, run.counts[:n_cal], KCFG)
    c = fk.session(fcfg)
    moved_c = c.calibrate(run.counts[:n_cal])
    assert moved_r == moved_c
    # calibration means: sums of up to 2000 counts in float32, relative error ~ eps per addition of the float sum
    np.testing.assert_allclose(c.state_vector(), ref.vector(), rtol=0, atol=2000 * EPS32 * 2 * 32768 / 2000 + 1e-6)
    n = 0
    path = 0.0
    steps = []
    seen = 0
    for out_r, out_c, flags in _drive(run, ref, c, 10.0, 49.0, fcfg, dark or (0.0, 0.0)):
        seen |= int(np.bitwise_or.reduce(flags))
        n += 200
        path += float(np.hypot(out_r[0], out_r[1]))
        sv = c.state_vector()
        rv = ref.vector()
        assert int(sv[F.IDX["flags"]]) == int(rv[F.IDX["flags"]])
        np.testing.assert_allclose(sv[Q], rv[Q], atol=500 * EPS32 * 4)
        _assert_heading_close(sv, rv, n)
        bound = n * EPS32 * max(path, 1.0) + 1e-4
        assert abs(sv[F.IDX["pe"]] - rv[F.IDX["pe"]]) < bound
        assert abs(sv[F.IDX["pn"]] - rv[F.IDX["pn"]]) < bound
        np.testing.assert_allclose(out_c[3:5], out_r[3:5], atol=1e-3 * (1 + np.abs(out_r[3:5]).max()))
        fix = [F.IDX[name] for name in ("fix_ae", "fix_an", "fix_ee", "fix_en")]
        np.testing.assert_allclose(sv[fix], rv[fix], atol=1e-4)  # metres: a few float32 steps of ~10 m
        steps.append((int(rv[F.IDX["flags"]]), float(rv[F.IDX["speed"]])))
    assert path > 20.0  # the run really moved
    if seed == 11:  # this walk turns at 28.7-31.7 s: the turn hold's both branches ran, in both
        assert seen & 4
    if seed == 30:  # this walk stops at 34.9 s: the walker's speed went to 0 with his steps, in both
        assert any(f0 & 2 and not f1 & 3 and v1 == 0.0 for (f0, _), (f1, v1) in zip(steps, steps[1:]))


def _rest_samples(n, tilt=(0.0, 0.0, 0.0), gyro=(0, 0, 0)):
    """n raw samples at rest with the body tilted by the rotation vector `tilt` (rad), accel 1 g."""
    r = quat_to_matrix(quat_from_rotvec(np.array(tilt)))
    f = r.T @ np.array([0.0, 0.0, KCFG.accel_lsb_per_g])
    return np.tile(np.concatenate([np.round(f), gyro]).astype(np.int16), (n, 1))


def test_config_rejects_a_zero_time_constant(fk):
    with pytest.raises(ValueError):
        fk.session(replace(FCFG, tilt_tau_s=0.0))
    with pytest.raises(ValueError):
        fk.session(replace(FCFG, kf_vel_sigma_ms=0.0))
    with pytest.raises(ValueError):
        fk.session(replace(FCFG, turn_start_dps=5.0, turn_end_dps=8.0))


def test_median_option_refuses_a_block_longer_than_its_ring(fk):
    long_block = replace(KCFG, block=64)
    st = F.FusedState()
    with pytest.raises(ValueError, match="block <= 32"):
        F.process(st, _rest_samples(4), np.full(4, 5000, dtype=np.int32), long_block, replace(FCFG, median=1.0))
    c = fk.session(replace(FCFG, median=1.0))
    c.kcfg.block = 64  # a board validation refuses this (rules: fused_median needs b <= 32); the C checks too
    before = c.state_vector()
    with pytest.raises(ValueError, match="error -1"):  # DR_ERR_BLOCK, nothing changed
        c.process(_rest_samples(4), np.full(4, 5000, dtype=np.int32))
    np.testing.assert_array_equal(c.state_vector(), before)


def test_position_filter_smooths_the_fixes_and_the_c_kernel_agrees(fk):
    """A receiver moving at 10 m/s East whose fixes carry a Gauss-Markov error (2.1 m, 60 s) and whose Doppler
    carries 0.1 m/s white noise: over 600 fixes the smoothed positions (fix + fix_ae, fix_an) are closer to the
    truth than the fixes, by the filter's own prediction (steady state ~1.5 m per axis against 2.1 m), and the C
    kernel's filter follows the reference's."""
    rng = np.random.default_rng(3)
    n = 600
    truth = np.stack([10.0 * np.arange(n), np.zeros(n)], axis=-1)
    phi = math.exp(-1.0 / 60.0)
    err = np.zeros((n, 2))
    err[0] = rng.standard_normal(2) * 2.1
    for k in range(1, n):
        err[k] = phi * err[k - 1] + rng.standard_normal(2) * 2.1 * math.sqrt(1 - phi * phi)
    fixes = truth + err
    vel = np.array([10.0, 0.0]) + rng.standard_normal((n, 2)) * 0.1
    ref = F.FusedState()
    c = fk.session()
    raw, smooth = [], []
    for k in range(n):
        d = fixes[k] - fixes[k - 1] if k else np.zeros(2)
        ref.since_fix = 1.0 if k else 0.0
        sv = c.state_vector()
        sv[F.IDX["since_fix"]] = ref.since_fix
        c.set_state_vector(sv)
        F.position_update(ref, vel[k, 0], vel[k, 1], d[0], d[1], FCFG)
        c.position(vel[k, 0], vel[k, 1], d[0], d[1])
        ref.gps_ve, ref.gps_vn = vel[k]
        c.gps(vel[k, 0], vel[k, 1])
        assert c.state_vector()[F.IDX["fix_ae"]] == pytest.approx(ref.fix_ae, abs=1e-3)
        assert c.state_vector()[F.IDX["fix_an"]] == pytest.approx(ref.fix_an, abs=1e-3)
        if k >= 100:  # past the start-up
            raw.append(np.linalg.norm(err[k]))
            smooth.append(np.linalg.norm(fixes[k] + (ref.fix_ae, ref.fix_an) - truth[k]))
    rms_smooth = np.sqrt(np.mean(np.square(smooth)) / 2)  # per axis
    rms_raw = np.sqrt(np.mean(np.square(raw)) / 2)
    # the filter is consistent: what it achieved is what its covariance says (500 fixes, ~8 correlation times:
    # the realised RMS is itself uncertain by ~20%), and that is well below the raw fixes' error
    assert rms_smooth == pytest.approx(math.sqrt(ref.fix_pxx), rel=0.2), (rms_smooth, math.sqrt(ref.fix_pxx))
    assert rms_smooth < 0.85 * rms_raw, (rms_smooth, rms_raw)


def _car_with_offsets(offset_ms2, seed=5, duration=240.0, mount="dashboard"):
    """A simulated car whose MPU-6050 is perfect except for a constant accelerometer offset (board frame = sensor
    frame on the default board), flat on a dashboard (or, mount "any", turned any way up) of a car that does not
    shake, with its open-sky GPS: the filter's step alone, under the conditions its equations assume."""
    from codegen.sim import mpu6050, neo6m, trajectory
    from codegen.sim.run import RunData

    assert [tuple(a) for a in BOARD.imu.axis_map] == [(0, 1), (1, 1), (2, 1)]
    traj = trajectory.car(seed=seed, duration=duration, mount=mount, vibration=False)
    device = mpu6050.DeviceErrors(np.asarray(offset_ms2, dtype=float), np.zeros(3), np.eye(3), np.eye(3))
    t_us, counts = mpu6050.simulate_imu(traj, BOARD, seed=seed, errors=mpu6050.MpuErrors.ideal(), device=device)
    gps = neo6m.simulate_gps(traj, seed=seed + 1000, rate_hz=BOARD.gps.rate_hz)
    return RunData("car", BOARD, seed, t_us, counts, gps, traj)


def test_filter_learns_the_accelerometer_offsets_and_the_c_kernel_agrees(fk):
    """Calibration folds a 40/-30 mg offset into the tilt; the car's turns under GPS separate them: the filter's
    offsets converge to the truth, the gravity leak it leaves is far below the offset, and the C kernel's filter
    state follows the reference's."""
    offset = np.array([0.04, -0.03, 0.02]) * 9.80665
    run = _car_with_offsets(offset)
    t, dt_us, snaps, _, _ = F._fused_pass(run, FCFG)
    last = max(snaps)
    _, st = snaps[last]
    assert abs(st.bax - offset[0]) < 0.1 * abs(offset[0]) and abs(st.bay - offset[1]) < 0.1 * abs(offset[1])
    # the same stream through the C kernel, driven as the app drives it
    n_cal = int(np.searchsorted(t, BOARD.algorithm.calibration_s))
    c = fk.session()
    c.calibrate(run.counts[:n_cal])
    k = n_cal
    vel = run.gps.device_velocity()
    for j in sorted(snaps):
        stop = snaps[j][0]
        if stop > k:
            c.process(run.counts[k:stop], dt_us[k:stop])
            k = stop
        c.gps(float(vel[j, 0]), float(vel[j, 1]))
    sv = c.state_vector()
    for name in ("bax", "bay"):
        assert sv[F.IDX[name]] == pytest.approx(getattr(st, name), abs=0.01 * np.abs(offset).max())
    for name in F.COVARIANCE_FIELDS:
        assert sv[F.IDX[name]] == pytest.approx(getattr(st, name), rel=1e-2, abs=1e-6)


def test_filter_without_offsets_stays_near_zero():
    """No offset, no tilt error: the filter must not invent one (|b| well below the 50 mg initial sigma)."""
    run = _car_with_offsets([0.0, 0.0, 0.0], seed=6)
    _, _, snaps, _, _ = F._fused_pass(run, FCFG)
    _, st = snaps[max(snaps)]
    assert math.hypot(st.bax, st.bay) < 0.002 * 9.80665  # 2 mg: a 25th of the filter's initial 50 mg sigma


def test_filter_learns_the_z_axis_offset_of_a_device_on_its_side():
    """Mounted any way up (this seed: the device's x axis nearly straight down, its z axis horizontal), the offsets
    of all three axes leak into the horizontal when the car turns; the filter learns the part across gravity to 2 %
    (0.62 m/s^2 of it; the 4-state filter had no z offset to put its share in). The part along gravity stays
    unseen, and leaks nothing while the device keeps its tilt."""
    offset = np.array([0.04, -0.03, 0.05]) * 9.80665
    run = _car_with_offsets(offset, seed=6, mount="any")
    up = run.truth.rotation(0)[2]
    assert abs(up[2]) < 0.2  # the z axis lies (nearly) horizontal
    _, _, snaps, _, _ = F._fused_pass(run, FCFG)
    _, st = snaps[max(snaps)]
    err = np.array([st.bax, st.bay, st.baz]) - offset
    across = lambda v: v - (v @ up) * up  # noqa: E731
    assert np.linalg.norm(across(err)) < 0.02 * np.linalg.norm(across(offset))


def test_filter_off_leaves_the_offsets_alone():
    run = _car_with_offsets([0.3, 0.2, 0.0], seed=7, duration=120.0)
    _, _, snaps, _, _ = F._fused_pass(run, replace(FCFG, kf_bias_init_g=0.0))
    _, st = snaps[max(snaps)]
    assert st.bax == 0.0 and st.bay == 0.0 and st.p22 == 0.0


def _fused_sources(tmp_path):
    from codegen.kernel.hostfused import SOURCES, fused_sources

    for name, content in fused_sources().items():
        (tmp_path / name).write_bytes(content)
    return SOURCES


def _run(cmd):
    import subprocess

    done = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    assert done.returncode == 0, f"{' '.join(map(str, cmd))}\n{done.stdout}\n{done.stderr}"
    return done.stdout


def test_xtensa_esp32_fused_object_has_no_undefined_symbols(tmp_path):
    """dr_fused.c with the kernel it calls, for the ESP32 through clang-22/llc-22 (as tests/test_kernel_c.py): no
    soft-float or libm helper (no float division, no double), no .data/.bss."""
    from conftest import require_tool

    clang, llc = require_tool("clang-22"), require_tool("llc-22")
    link, nm, size = require_tool("llvm-link-22"), require_tool("llvm-nm-22"), require_tool("llvm-size-22")
    sources = _fused_sources(tmp_path)
    irs = []
    for source in sources:
        ir = tmp_path / (source + ".ll")
        _run([clang, "--target=xtensa", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Os",
              "-ffreestanding", "-I", tmp_path, "-S", "-emit-llvm", tmp_path / source, "-o", ir])
        irs.append(ir)
    linked = tmp_path / "fused.ll"
    _run([link, "-S", *irs, "-o", linked])
    obj = tmp_path / "fused_esp32.o"
    _run([llc, "-mtriple=xtensa", "-mcpu=esp32", "-O2", "-function-sections", "-filetype=obj", linked, "-o", obj])
    assert _run([nm, "-u", obj]).split() == []
    rows = _run([size, "-A", obj]).splitlines()
    data = sum(int(r.split()[1]) for r in rows if r.startswith((".data", ".bss")) and len(r.split()) > 1)
    assert data == 0


def test_fused_c_under_sanitizers(tmp_path):
    """The harness of benchmarks/fused.py under AddressSanitizer and UndefinedBehaviorSanitizer."""
    from codegen.paths import native_ext_dir
    from conftest import require_tool

    cc = require_tool("cc")
    sources = _fused_sources(tmp_path)
    binary = tmp_path / "bench_fused"
    _run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-g", "-O1", "-fsanitize=address,undefined",
          "-fno-sanitize-recover=all", "-I", tmp_path, native_ext_dir() / "tests" / "bench_fused.c",
          *[tmp_path / s for s in sources], "-o", binary])
    out = _run([binary, "3"]).split()
    assert len(out) == 3 and all(math.isfinite(float(x)) for x in out)


def test_the_per_sample_steps_are_the_same_steps_in_the_same_order_everywhere():
    """docs/fused.md's table, the reference's process, the C's dr_fused_process and the generated fallback's
    fused_process name the same per-sample steps in the same order (codegen.kernel.fused.PER_SAMPLE_STEPS), and each
    has its function: a reader finds a step by its name in all three."""
    import inspect
    import re
    from pathlib import Path

    from codegen.generate import render_tree

    root = Path(__file__).resolve().parents[1]
    steps = list(F.PER_SAMPLE_STEPS)
    assert len(set(steps)) == len(steps)
    assert re.findall(r"^\s+_(\w+)\(lp, st\b", inspect.getsource(F.process), re.M) == steps
    assert all(callable(getattr(F, "_" + name)) for name in steps)
    c = (root / "native_ext" / "dr_fused.c").read_text()
    body = c[c.index("int dr_fused_process("):]
    body = body[:body.index("\n}\n")]
    assert re.findall(r"^\s+dr_fused_(\w+)\((?:kcfg, )?(?:cfg, )?st, &lp\b", body, re.M) == steps
    assert all(re.search(rf"^static inline void dr_fused_{name}\(", c, re.M) for name in steps)
    fallback = render_tree(load_board())["app/dr_fallback.py"].content.decode()
    loop = fallback[fallback.index("def fused_process("):]
    loop = loop[:loop.index("\ndef ")]
    assert re.findall(r"^\s+# step: (\w+)", loop, re.M) == steps
    docs = (root / "docs" / "fused.md").read_text()
    rows = re.findall(r"^\| (\d+) \| (\w+) \| `_(\w+)` \| `dr_fused_(\w+)` \| `# step: (\w+)` \|$", docs, re.M)
    assert [(int(n), name) for n, name, *_ in rows] == list(enumerate(steps, 1))
    assert all(len(set(names)) == 1 for _, *names in rows)
