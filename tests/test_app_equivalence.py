"""The positions the app computes in IMU mode (algorithm `seed`) equal the reference pipeline on the same samples,
within the kernel issue's derived float32 bound (tests/kernelkit.window_bound), with the generated fallback and with
the x64 natmod. (The default `fused` method's own equivalence is the kernel issue's; here it runs in test_app_sim.)

The app runs unmodified; a wrapper script only taps `dr.process` and the app's hooks to record, per window, the
kernel state going in, the samples and intervals the app collected, the kernel's output, and the position the app
then shows. The host replays the same inputs through codegen/kernel/reference.py:
- per window: reference(samples, dt, q0, v0, bias of the app) vs the app's output, within window_bound;
- chained: the reference run alone from its own calibration, orientation and velocity carried window to window
  (errors composed: a velocity error dv0 adds dv0*T of displacement), against the app's accumulated ENU offset;
- the shown lat/lon equals reference offset_latlon_e7(anchor, app's ENU offset) to the rounding unit.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from codegen.board.loader import load_board
from codegen.kernel import reference as ref
from codegen.sim.harness import (
    TICKS_PERIOD,
    generate_app,
    imu_counts,
    nmea_epoch,
    run_app,
    tbeam_scenario,
    write_counts,
    write_stream,
)
from codegen.tools import tool_env
from conftest import mpy_dir, require_tool
from kernelkit import window_bound

RATE = 200.0

TAP = r"""
import struct
import app

dump = open(DUMP, "wb")
dr = app.dr
orig = dr.process


def process(state, samples, dt_us, out):
    dump.write(b"P")
    dump.write(struct.pack("<10f", *[state[i] for i in range(dr.Q, dr.Q + 4)] +
                           [state[i] for i in range(dr.V, dr.V + 3)] +
                           [state[i] for i in range(dr.GYRO_BIAS, dr.GYRO_BIAS + 3)]))
    dump.write(bytes(samples))
    dump.write(bytes(dt_us))
    orig(state, samples, dt_us, out)
    dump.write(struct.pack("<6f", *out))


def on_window(a, samples, dt_us, out):
    anchor = a.anchor or (0, 0)
    pos = a.position or (0, 0)
    dump.write(b"A" + struct.pack("<Biiii3d", a.mode, anchor[0], anchor[1], pos[0], pos[1], *a.enu))
    dump.flush()


def on_cal(a, calib, moved):
    s = a.state
    dump.write(b"C" + struct.pack("<IB", len(calib) // 6, moved))
    dump.write(bytes(calib))
    dump.write(struct.pack("<7f", *[s[i] for i in range(dr.Q, dr.Q + 4)] +
                           [s[i] for i in range(dr.GYRO_BIAS, dr.GYRO_BIAS + 3)]))


dr.process = process
a = app.App()
a.on_window = on_window
a.on_calibrated = on_cal
print("KERNEL", app.KERNEL)
a.run()
"""


def read_dump(path: Path, window: int):
    data = path.read_bytes()
    i = 0
    cal = None
    windows = []
    while i < len(data):
        kind = data[i : i + 1]
        i += 1
        if kind == b"C":
            count, moved = struct.unpack_from("<IB", data, i)
            i += 5
            calib = np.frombuffer(data, "<i2", count * 6, i).reshape(-1, 6)
            i += count * 12
            vals = struct.unpack_from("<7f", data, i)
            i += 28
            cal = (calib, moved, np.array(vals[:4]), np.array(vals[4:]))
        elif kind == b"P":
            state = struct.unpack_from("<10f", data, i)
            i += 40
            samples = np.frombuffer(data, "<i2", window * 6, i).reshape(-1, 6)
            i += window * 12
            dt = np.frombuffer(data, "<i4", window, i)
            i += window * 4
            out = struct.unpack_from("<6f", data, i)
            i += 24
            windows.append({"q0": np.array(state[:4]), "v0": np.array(state[4:7]), "bias": np.array(state[7:]),
                            "samples": samples, "dt": dt, "out": np.array(out)})
        elif kind == b"A":
            mode, alat, alon, plat, plon, e, n, u = struct.unpack_from("<Biiii3d", data, i)
            i += struct.calcsize("<Biiii3d")
            windows[-1].update(mode=mode, anchor=(alat, alon), pos=(plat, plon), enu=np.array([e, n, u]))
        else:
            raise AssertionError(f"bad dump record {kind!r} at {i - 1}")
    return cal, windows


def motion_counts(duration):
    counts = imu_counts(duration, RATE, seed=7, noise_counts=20,
                        pushes=[(16, 18, 0, 0.6), (19, 20, 1, -0.8), (24, 25.5, 0, -0.4), (27, 28, 2, 0.3)])
    t = np.arange(len(counts)) / RATE
    turn = (t >= 21) & (t < 23)
    counts[turn, 5] += int(30 * 131)  # 30 deg/s about z for 2 s
    counts[(t >= 25) & (t < 26), 3] += int(5 * 131)  # a small roll: gravity leaks into the horizontal axes
    return counts


def natmod_dir(tmp_path: Path, out: Path) -> Path:
    mpy = mpy_dir()
    mpy_cross = require_tool("mpy-cross")
    require_tool("make")
    done = subprocess.run(["make", f"MPY_DIR={mpy}", "ARCH=x64", f"MPY_CROSS={mpy_cross}", f"PYTHON={sys.executable}"],
                          cwd=out / "native", capture_output=True, text=True, env=tool_env())
    assert done.returncode == 0, done.stdout + done.stderr
    target = tmp_path / "natmod"
    target.mkdir()
    (target / "dr_native.mpy").write_bytes((out / "native" / "dr_native.mpy").read_bytes())
    return target


@pytest.mark.parametrize("kernel", ["python", "native"])
def test_imu_positions_equal_reference(kernel, tmp_path):
    micropython = require_tool("micropython")
    yaml = tmp_path / "tbeam-seed.yaml"
    yaml.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-seed\nalgorithm:\n  mode: seed\n")
    out = generate_app(yaml, tmp_path / "out")
    extra = [natmod_dir(tmp_path, out)] if kernel == "native" else []
    board = load_board(yaml).board
    cfg = ref.KernelConfig.from_board(board)
    duration = 36
    counts = write_counts(tmp_path / "imu.bin", motion_counts(duration))
    # a fix 1..13 s (still), then none: IMU mode from ~16 s
    gps = write_stream(tmp_path / "gps.txt", [(t, nmea_epoch(t, 48.8583701, 2.2944813, alt=35.0)) for t in range(1, 13)])
    scenario = tbeam_scenario(tmp_path, counts, gps, duration, ticks_start_us=TICKS_PERIOD - 25_000_000)
    script = tmp_path / "tap.py"
    script.write_text(f"DUMP = {str(tmp_path / 'dump.bin')!r}\n" + TAP)
    run = run_app(micropython, out, scenario, tmp_path / "w", script=str(script), extra_path=extra)
    assert run.returncode == 0, run.stderr + run.stdout[-1500:]
    assert f"KERNEL {kernel}" in run.stdout
    cal, windows = read_dump(tmp_path / "dump.bin", cfg.window)

    # calibration: same tilt and bias as the reference on the same samples
    calib, moved, q_app, bias_app = cal
    rc = ref.calibrate(calib, cfg)
    assert moved == rc.moved == 0
    assert np.allclose(q_app, rc.q, atol=1e-6) and np.allclose(bias_app, rc.gyro_bias_lsb, atol=1e-3)

    imu_windows = [w for w in windows if w["mode"] == 1]
    assert len(imu_windows) >= 6, [w["mode"] for w in windows]

    # per window, from the app's own state
    for k, w in enumerate(windows):
        bp, bv, _, res = window_bound(w["samples"], w["dt"], w["q0"], w["v0"], w["bias"], cfg)
        assert np.all(np.abs(w["out"][:3] - res.displacement) <= bp), (k, w["out"], res.displacement, bp)
        assert np.all(np.abs(w["out"][3:] - res.velocity) <= bv), (k, w["out"], res.velocity, bv)

    # chained: the reference alone from its calibration, the app's accumulated IMU-mode offset
    q, v = rc.q, np.zeros(3)
    theta, e_v = 0.0, 0.0
    enu_ref, e_p = np.zeros(3), 0.0
    moved_any = False
    for w in windows:
        if w["mode"] == 0:  # GPS mode: velocity follows the (still) GPS, the offset is reset at each fix
            v, e_v = np.zeros(3), 0.0
            enu_ref[:] = 0.0
            e_p = 0.0
        bp, bv, theta, res = window_bound(w["samples"], w["dt"], q, v, rc.gyro_bias_lsb, cfg, theta0=theta)
        span = w["dt"].sum() * 1e-6
        if w["mode"] == 1:
            enu_ref += res.displacement
            e_p += bp + e_v * span
            assert np.all(np.abs(w["enu"] - enu_ref) <= e_p + 1e-9), (w["enu"], enu_ref, e_p)
            moved_any |= bool(np.abs(enu_ref[:2]).max() > 1.0)
            lat, lon = ref.offset_latlon_e7(*w["anchor"], float(w["enu"][0]), float(w["enu"][1]))
            assert abs(w["pos"][0] - lat) <= 1 and abs(w["pos"][1] - lon) <= 1
        e_v += bv
        q, v = res.q, res.velocity
    assert moved_any  # the comparison covered real motion, not zeros
