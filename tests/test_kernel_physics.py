"""The seed kernel's steps against physics and closed forms, each on every implementation on its own.

`impl` is the float64 reference (codegen/kernel/reference.py), the float32 C kernel through cffi (dr_kernel.c) or
the generated fallback on the unix-port `micropython` (tests/mp_kernel_driver.py). No test here compares two
implementations: each is held to a known rotation, a constant acceleration, the deadband, the tilt gravity gives,
the published lengths of a degree. Block medians are held to numpy.median in tests/test_kernel_equivalence.py; the
equivalence of the implementations on random windows is there too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from codegen.kernel import reference as ref
from conftest import require_tool
from kernelkit import Case, U, f32, run_driver, write_fallback

IMPLEMENTATIONS = ("reference", "c", "fallback")
DEFAULT = ref.KernelConfig()
ONE_G = int(DEFAULT.accel_lsb_per_g)  # counts
DT_US = 5000


@dataclass
class Result:
    """One case on one implementation: calibration verdict, orientation and bias (after calibration or as given),
    and (displacement, velocity, q) after each window."""

    moved: bool | None
    q: np.ndarray
    bias: np.ndarray
    windows: list = field(default_factory=list)


def _reference(case: Case) -> Result:
    c = case.cfg
    if case.calib is not None:
        cal = ref.calibrate(case.calib, c)
        result = Result(bool(cal.moved), cal.q, cal.gyro_bias_lsb)
    else:
        result = Result(None, np.asarray(case.q0, float), np.asarray(case.bias, float))
    q, v = result.q, np.asarray(case.v0, float)
    for samples, dt in case.windows:
        res = ref.process_window(samples, dt, q, v, result.bias, c)
        result.windows.append((res.displacement, res.velocity, res.q))
        q, v = res.q, res.velocity
    return result


def _c(case: Case) -> Result:
    from codegen.kernel.hostkernel import load_kernel

    c = case.cfg
    run = load_kernel().session(block=c.block, window=c.window, accel_lsb_per_g=c.accel_lsb_per_g,
                                gyro_lsb_per_dps=c.gyro_lsb_per_dps, deadband_g=c.deadband_g,
                                motion_threshold_g=c.motion_threshold_g, axis_map=c.axis_map)
    moved = None
    if case.calib is not None:
        moved = run.calibrate(case.calib)
    else:
        run.q = f32(case.q0)
        run.gyro_bias_lsb = f32(case.bias)
    result = Result(moved, run.q.astype(float), run.gyro_bias_lsb.astype(float))
    run.set_velocity(*[float(x) for x in f32(case.v0)])
    for samples, dt in case.windows:
        d, v, _ = run.process(samples, dt)
        result.windows.append((d.astype(float), v.astype(float), run.q.astype(float)))
    return result


def run(impl: str, cases: list[Case], work, latlon=()) -> tuple[list[Result], list]:
    """Every case, and offset_latlon of each (lat_e7, lon_e7, east_m, north_m), on `impl`."""
    if impl == "reference":
        return [_reference(c) for c in cases], [ref.offset_latlon_e7(*x) for x in latlon]
    if impl == "c":
        require_tool("cc")
        from codegen.kernel.hostkernel import load_kernel

        kernel = load_kernel()
        return [_c(c) for c in cases], [kernel.offset_latlon(a, b, np.float32(e), np.float32(n))
                                        for a, b, e, n in latlon]
    require_tool("micropython")
    write_fallback(work)
    answer = run_driver("dr_fallback", work, cases, latlon=list(latlon))
    results = []
    for case, got in zip(cases, answer["cases"]):
        cal = got["calibrated"]
        moved = None if got["moved"] is None else bool(got["moved"])
        result = Result(moved, np.array(cal[:4]) if cal else f32(case.q0), np.array(cal[4:]) if cal else f32(case.bias))
        result.windows = [(np.array(out[:3]), np.array(out[3:]), np.array(q)) for out, q in got["windows"]]
        results.append(result)
    return results, [tuple(x) for x in answer["latlon"]]


@pytest.fixture(params=IMPLEMENTATIONS)
def impl(request):
    return request.param


def _window(n, accel_counts=(0, 0, ONE_G), gyro=(0, 0, 0)):
    row = np.concatenate([accel_counts, gyro]).astype(np.int16)
    return np.tile(row, (n, 1)), np.full(n, DT_US, dtype=np.int32)


def test_calibration_levels_gravity_and_takes_the_gyro_bias(impl, tmp_path):
    """At rest, tilted by a known rotation, the gyro reading constant counts: the orientation turns the measured
    specific force onto Up with yaw 0 (the shortest arc: no z component), the gyro bias is those counts. Shaken
    (0.05 g noise on x, above the 0.02 g threshold) it says moved; upside down it still finds Up."""
    tilt = ref.quat_to_matrix(ref.quat_from_rotvec(np.array([0.3, -0.2, 0.0])))
    f = np.round(tilt.T @ [0.0, 0.0, ONE_G])
    gyro = np.array([40, -25, 7])
    still = np.tile(np.concatenate([f, gyro]).astype(np.int16), (400, 1))
    shaken = still.copy()
    shaken[:, 0] += np.round(np.random.default_rng(2).normal(0.0, 0.05 * ONE_G, len(still))).astype(np.int16)
    upside_down = np.tile(np.array([0, 0, -ONE_G, 0, 0, 0], dtype=np.int16), (10, 1))
    cases = [Case(DEFAULT, np.zeros(4), np.zeros(3), np.zeros(3), [], calib=c) for c in (still, shaken, upside_down)]
    (level, moved, flipped), _ = run(impl, cases, tmp_path)
    assert level.moved is False and moved.moved is True and flipped.moved is False
    np.testing.assert_allclose(ref.quat_rotate(level.q, f / np.linalg.norm(f)), [0, 0, 1], atol=1e-6)
    assert abs(level.q[3]) < 1e-7  # yaw 0
    np.testing.assert_allclose(level.bias, gyro, rtol=16 * U)
    np.testing.assert_allclose(ref.quat_rotate(flipped.q, [0, 0, -1.0]), [0, 0, 1], atol=1e-6)


def test_gyro_turns_the_orientation_by_omega_t(impl, tmp_path):
    """90 degree/s about the body axis (1, 2, 2)/3 for 208 samples of 5 ms, from a tilted start: q = q0 (x)
    exp(theta n / 2), theta = omega T = 93.6 degrees. The kernel's 4th-order series for exp is exact to 1e-11 here;
    the bound is float32's, kernelkit's E_q (18 u + 3 u |omega| dt per sample), doubled for an angle."""
    counts = np.array([3930, 7860, 7860])  # |counts| = 11790 = 90 degree/s at 131 counts per degree/s
    omega = math.radians(np.linalg.norm(counts) / DEFAULT.gyro_lsb_per_dps)
    q0 = ref.quat_from_rotvec(np.array([0.3, -0.2, 0.5]))
    samples, dt = _window(208, gyro=counts)
    (result,), _ = run(impl, [Case(DEFAULT, q0, np.zeros(3), np.zeros(3), [(samples, dt)])], tmp_path)
    theta = omega * 208 * 0.005
    n = counts / np.linalg.norm(counts)
    expected = ref.quat_multiply(q0, np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) * n]))
    q = result.windows[-1][2] / np.linalg.norm(result.windows[-1][2])
    angle = 2 * math.acos(min(1.0, abs(float(np.dot(q, expected)))))
    assert angle <= 2 * 208 * (18 * U + 3 * U * omega * 0.005) + 1e-9


def test_constant_acceleration_is_half_a_t_squared(impl, tmp_path):
    """Level (q = identity), 0.25 g East for 512 samples of 5 ms, starting at 1 m/s North: p = v0 T + a T^2 / 2,
    v = v0 + a T (exact for a zero-order hold of a constant acceleration); float32 sums 32 blocks."""
    samples, dt = _window(512, accel_counts=(4096, 0, ONE_G))
    (result,), _ = run(impl, [Case(DEFAULT, np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([0.0, 1.0, 0.0]),
                                   [(samples, dt)])], tmp_path)
    a = 4096 * ref.STANDARD_GRAVITY / ONE_G
    t = 512 * 5e-3
    d, v, _ = result.windows[0]
    assert d[0] == pytest.approx(0.5 * a * t * t, rel=64 * U) and v[0] == pytest.approx(a * t, rel=64 * U)
    assert d[1] == pytest.approx(t, rel=64 * U) and v[1] == pytest.approx(1.0, rel=U)
    assert d[2] == v[2] == 0.0


def test_inside_the_deadband_is_exactly_zero(impl, tmp_path):
    """Accelerations below the deadband (|a| < 0.025 g < l = 0.03125 g) on every axis: every block median is zeroed,
    so the velocity stays exactly what it was and the displacement is v0 T."""
    rng = np.random.default_rng(7)
    samples = np.zeros((512, 6), np.int16)
    samples[:, :3] = rng.integers(-400, 400, (512, 3))
    samples[:, 2] += ONE_G
    dt = np.full(512, DT_US, np.int32)
    (result,), _ = run(impl, [Case(DEFAULT, np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([1.5, -0.5, 0.0]),
                                   [(samples, dt)])], tmp_path)
    d, v, _ = result.windows[0]
    assert list(np.float32(v)) == [np.float32(1.5), np.float32(-0.5), np.float32(0.0)]
    assert d[0] == pytest.approx(1.5 * 2.56, rel=64 * U) and d[1] == pytest.approx(-0.5 * 2.56, rel=64 * U)
    assert d[2] == 0.0


# the length of one degree on the WGS-84 ellipsoid at a latitude (the published table, rounded to the metre)
DEGREE_KM = {0: (110.574, 111.320), 15: (110.649, 107.551), 30: (110.852, 96.486), 45: (111.133, 78.847),
             60: (111.412, 55.800), 75: (111.618, 28.902)}


def test_metres_to_latlon_follow_the_published_lengths_of_a_degree(impl, tmp_path):
    """A hundredth of a degree North (or East) from an anchor at 0-75 degrees latitude, in the metres the published
    WGS-84 table gives for a degree there, moves the latitude (longitude) by 100000 units of 1e-7 degree, to the
    table's rounding (0.5 m a degree) plus one unit. And a centimetre survives: 1.12 cm North moves it by one unit."""
    requests = []
    for lat, (north_km, east_km) in DEGREE_KM.items():
        requests.append((lat * 10_000_000, 85_000_000, 0.0, north_km * 10.0))
        requests.append((lat * 10_000_000, 85_000_000, east_km * 10.0, 0.0))
    requests.append((473_000_000, 85_000_000, 0.0, 0.0112))
    _, got = run(impl, [], tmp_path, latlon=requests)
    for (lat, (north_km, east_km)), moved_north, moved_east in zip(DEGREE_KM.items(), got[0:-1:2], got[1:-1:2]):
        assert abs(moved_north[0] - lat * 10_000_000 - 100_000) <= 1 + 100_000 * 0.0005 / north_km, lat
        assert moved_north[1] == 85_000_000
        assert abs(moved_east[1] - 85_000_000 - 100_000) <= 1 + 100_000 * 0.0005 / east_km, lat
        assert moved_east[0] == lat * 10_000_000
    assert got[-1] == (473_000_001, 85_000_000)
