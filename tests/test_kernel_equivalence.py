"""Reference (NumPy float64) vs C kernel (cffi, float32) vs generated fallback (real MicroPython): one behaviour.

Medians are compared bit for bit with numpy.median on identical float32 inputs; integrated values within the float32
bound derived in tests/kernelkit.py (window_bound). The closed forms each step must meet (a known rotation, a constant
acceleration, the deadband, calibration, the lengths of a degree), on each implementation alone:
tests/test_kernel_physics.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from codegen.kernel import reference as ref
from conftest import require_tool
from kernelkit import (
    Case,
    U,
    make_window,
    run_c,
    run_driver,
    run_reference,
    write_fallback,
)

DEFAULT = ref.KernelConfig()


@pytest.fixture(scope="module")
def kernel():
    require_tool("cc")
    from codegen.kernel.hostkernel import load_kernel

    return load_kernel()


def assert_within(c_out, r_out, factor=1.0, what="C"):
    for w, ((d, v, *_), (rd, rv, _, bp, bv)) in enumerate(zip(c_out, r_out)):
        assert np.all(np.abs(np.asarray(d) - rd) <= factor * bp), f"{what} window {w}: displacement {d} vs {rd} (bound {bp})"
        assert np.all(np.abs(np.asarray(v) - rv) <= factor * bv), f"{what} window {w}: velocity {v} vs {rv} (bound {bv})"


# ----------------------------------------------------------------------------------------------- medians, exact
@pytest.mark.parametrize("b", [1, 2, 3, 16, 512])
def test_block_median_bit_exact(kernel, b):
    rng = np.random.default_rng(b)
    values = (rng.normal(0, 3, 512 * 3 // math.gcd(512, 3) if b == 3 else 512)).astype(np.float32)
    values = values[: len(values) // b * b]
    expected = np.median(values.reshape(-1, b), axis=1).astype(np.float32)
    got = kernel.block_median(values, b)
    assert got.dtype == np.float32
    assert np.array_equal(got.view(np.uint32), expected.view(np.uint32))


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([1, 2, 3, 16, "n"]),
       st.lists(st.floats(-1e6, 1e6, width=32, allow_subnormal=False), min_size=1, max_size=160))
def test_block_median_property(kernel, b, pool):
    b = len(pool) if b == "n" else b
    values = np.array(pool[: len(pool) // b * b], dtype=np.float32)
    assume(len(values) > 0)
    expected = np.median(values.reshape(-1, b), axis=1).astype(np.float32)
    assert np.array_equal(kernel.block_median(values, b), expected)


def test_median_not_multiple_is_an_error(kernel):
    with pytest.raises(ValueError):
        kernel.block_median(np.zeros(17, np.float32), 16)


# ----------------------------------------------------------------------------------------------- edge cases
@pytest.mark.parametrize("value", [-32768, 32767])
def test_saturated_counts(kernel, value):
    counts = np.full((64, 6), value, np.int16)
    dt = np.full(64, 5000, np.int32)
    case = Case(DEFAULT, np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3), [(counts, dt)])
    c_out = run_c(kernel, case)
    assert np.all(np.isfinite(c_out[0][0])) and np.all(np.isfinite(c_out[0][1]))
    assert_within(c_out, run_reference(case))


def test_count_not_multiple_of_block_is_a_clear_error(kernel):
    run = kernel.session()
    with pytest.raises(ValueError, match="multiple of the block"):
        run.process(np.zeros((500, 6), np.int16), np.full(500, 5000))
    with pytest.raises(ValueError, match="multiple of the block"):
        ref.process_window(np.zeros((500, 6)), np.full(500, 5000), [1, 0, 0, 0], [0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="multiple of the block"):
        kernel.session(block=16, window=500)


def test_calibration_tilt_bias_and_motion(kernel):
    rng = np.random.default_rng(3)
    g = np.array([0.3, -0.2, 0.93])
    g /= np.linalg.norm(g)
    still = np.zeros((2000, 6))
    still[:, :3] = g * 16384 + rng.normal(0, 60, (2000, 3))
    still[:, 3:] = [40, -25, 7] + rng.normal(0, 5, (2000, 3))
    still = np.round(still).astype(np.int16)
    run = kernel.session()
    assert run.calibrate(still) is False
    cal = ref.calibrate(still)
    assert not cal.moved
    assert np.allclose(run.q, cal.q, atol=64 * U)
    assert np.allclose(run.gyro_bias_lsb, cal.gyro_bias_lsb, rtol=16 * U)
    mean = still[:, :3].mean(axis=0)
    up = ref.quat_rotate(run.q.astype(np.float64), mean / np.linalg.norm(mean))
    assert np.allclose(up, [0, 0, 1], atol=1e-6)  # a real rotation onto up
    moving = still.copy()
    moving[:, 0] += np.round(rng.normal(0, 0.05 * 16384, 2000)).astype(np.int16)
    assert run.calibrate(moving) is True and ref.calibrate(moving).moved
    upside_down = np.zeros((10, 6), np.int16)
    upside_down[:, 2] = -16384
    run.calibrate(upside_down)
    assert np.allclose(ref.quat_rotate(run.q.astype(np.float64), [0, 0, -1]), [0, 0, 1], atol=1e-6)


def test_rotate_heading_and_latlon(kernel):
    run = kernel.session()
    run.rotate_heading(math.cos(0.5), math.sin(0.5))
    assert np.allclose(run.q, ref.quat_yaw(0.5), atol=4 * U)
    run.rotate_heading(-1.0, 0.0)
    assert np.allclose(np.abs(run.q), np.abs(ref.quat_yaw(0.5 + math.pi)), atol=8 * U)
    rng = np.random.default_rng(11)
    for _ in range(300):
        lat = int(rng.integers(-850_000_000, 850_000_000))
        lon = int(rng.integers(-1_800_000_000, 1_800_000_000))
        east, north = rng.uniform(-20000, 20000, 2)
        expected = ref.offset_latlon_e7(lat, lon, east, north)
        got = kernel.offset_latlon(lat, lon, np.float32(east), np.float32(north))
        # 1 unit (1.1 cm) of rounding, plus float32: |offset| * (few u) in units of 1e-7 degree
        assert abs(got[0] - expected[0]) <= 1 + abs(expected[0] - lat) * 16 * U
        assert abs(got[1] - expected[1]) % 3_600_000_000 <= 1 + abs(expected[1] - lon) * 64 * U / max(
            1e-3, math.cos(math.radians(lat * 1e-7)))
    # a centimetre survives: 1.1 cm North moves the latitude by one unit
    assert kernel.offset_latlon(473_000_000, 85_000_000, 0.0, 0.0112)[0] == 473_000_001


# ----------------------------------------------------------------------------------------------- properties
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    b=st.sampled_from([1, 2, 3, 16, "n"]),
    blocks=st.integers(1, 6),
    accel_range=st.sampled_from([2, 4, 8, 16]),
    gyro_range=st.sampled_from([250, 500, 1000, 2000]),
    jitter=st.integers(0, 2000),
    gravity_axis=st.integers(0, 2),
    seed=st.integers(0, 2**32 - 1),
    deadband=st.sampled_from([0.0, 0.03125, 0.1]),
    windows=st.integers(1, 2),
)
def test_c_matches_reference(kernel, b, blocks, accel_range, gyro_range, jitter, gravity_axis, seed, deadband, windows):
    from codegen.board.model import ACCEL_LSB_PER_G, GYRO_LSB_PER_DPS

    if b == "n":  # one block spanning the whole window
        b = n = 16 * blocks
    else:
        n = b * blocks
    cfg = ref.KernelConfig(block=b, window=n, accel_lsb_per_g=ACCEL_LSB_PER_G[accel_range],
                           gyro_lsb_per_dps=GYRO_LSB_PER_DPS[gyro_range], deadband_g=deadband)
    rng = np.random.default_rng(seed)
    q0 = ref.quat_normalise(rng.normal(size=4))
    case = Case(cfg, q0, rng.normal(0, 20, 3), rng.normal(0, 2, 3),
                [make_window(rng, n, cfg, gravity_axis, jitter_us=jitter) for _ in range(windows)])
    assert_within(run_c(kernel, case), run_reference(case))


# ----------------------------------------------------------------------------------------------- real MicroPython
def _mp_cases():
    rng = np.random.default_rng(2024)
    cases = []
    for b, n, blocks_windows in [(16, 512, 2), (1, 16, 1), (2, 32, 1), (3, 48, 2), (512, 512, 1)]:
        cfg = ref.KernelConfig(block=b, window=n)
        cases.append(Case(cfg, ref.quat_normalise(rng.normal(size=4)), rng.normal(0, 20, 3), rng.normal(0, 1, 3),
                          [make_window(rng, n, cfg, int(rng.integers(3))) for _ in range(blocks_windows)]))
    calib = np.round(np.array([0.1, 0.2, 0.97]) * 16384 + rng.normal(0, 30, (400, 3))).astype(np.int16)
    gyro = np.round(rng.normal(0, 4, (400, 3)) + [12, -30, 5]).astype(np.int16)
    cases.append(Case(DEFAULT, np.zeros(4), np.zeros(3), np.zeros(3),
                      [make_window(rng, 512, DEFAULT, 2)], calib=np.hstack([calib, gyro])))
    sat = np.full((32, 6), -32768, np.int16)
    cases.append(Case(DEFAULT, np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3), [(sat, np.full(32, 5000, np.int32))]))
    return cases


def test_fallback_on_micropython_matches_reference_and_c(kernel, tmp_path):
    require_tool("micropython")
    write_fallback(tmp_path)
    cases = _mp_cases()
    rng = np.random.default_rng(5)
    medians = [(rng.normal(0, 2, 64).astype(np.float32), b) for b in (1, 2, 3, 16, 64) if 64 % b == 0]
    medians.append((rng.normal(0, 2, 48).astype(np.float32), 3))
    answer = run_driver("dr_fallback", tmp_path, cases, medians)
    for (values, b), got in zip(medians, answer["medians"]):
        expected = np.median(values.reshape(-1, b), axis=1).astype(np.float32)
        assert np.array_equal(np.array(got, dtype=np.float32), expected), f"median b={b}"
    for case, mp in zip(cases, answer["cases"]):
        r_out = run_reference(case)
        c_out = run_c(kernel, case)
        mp_out = [(np.array(out[:3]), np.array(out[3:]), np.array(q)) for out, q in mp["windows"]]
        assert_within(mp_out, r_out, what="fallback")
        assert_within(c_out, [(d, v, q, bp, bv) for (d, v, q, *_), (_, _, _, bp, bv) in zip(mp_out, r_out)],
                      factor=2.0, what="C vs fallback")
        if case.calib is not None:
            assert mp["moved"] == int(ref.calibrate(case.calib).moved)


def test_fallback_errors_on_micropython(tmp_path):
    micropython = require_tool("micropython")
    import os
    import subprocess

    write_fallback(tmp_path)
    script = (
        "import dr_fallback as dr\nfrom array import array\n"
        "s = array('f', [0.0] * dr.STATE_LEN)\ndr.init(s)\n"
        "try:\n    dr.process(s, array('h', [0] * 60), array('i', [5000] * 10), array('f', [0.0] * 6))\n"
        "except ValueError as e:\n    print('ValueError', e)\n"
        "try:\n    dr.init(s, 16, 500, 16384.0, 131.0, 0.03125, 0.02)\nexcept ValueError as e:\n    print('ValueError', e)\n"
    )
    done = subprocess.run([micropython, "-c", script], capture_output=True, text=True,
                          env=os.environ | {"MICROPYPATH": str(tmp_path)})
    assert done.stdout.count("ValueError") == 2, done.stdout + done.stderr
    assert "multiple of block" in done.stdout
