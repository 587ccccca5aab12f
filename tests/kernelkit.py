"""Helpers for the kernel tests: input vectors, the derived float32 error bound, running the generated fallback
(or the x64 natmod) under the real `micropython` command.

The error bound (`window_bound`) is a running (Higham-style) worst-case analysis of the float32 kernel against the
float64 reference on identical inputs, written next to the C code it describes; u = 2^-24 is the float32 unit
roundoff. It is derived from the operations, not fitted to the results:

  orientation (dr_gyro_step): per sample the quaternion product is 4 components of 4-term dot products (<= 8u in
    norm for unit factors), dq from the cos/sin series (<= 4u plus the truncation |h|^6/720 the reference does not
    have), the one-step renormalisation (<= 6u), and the rate omega = (count - bias) * scale carries <= 6u relative,
    i.e. <= 6u |omega| dt of angle (the bias, rounded to float32, adds u |bias|):
    E_q,k+1 = E_q,k + 18u + 3u (|omega_k| + |bias|) dt_k + |h_k|^6/720 (quaternion norm).
  acceleration (dr_quat_rotate - g): R(q) f = q f q*, so a quaternion off by E_q moves it by <= 2 E_q |f|; the scale
    (reciprocal + product, 5u), the 15-multiply rotation (<= 10u) and a non-unit q (<= 4u) give 19u|f|, and the
    gravity subtraction u(g + |a|):  da_k = |f_k| (2 E_q,k + 19u) + u (g + |a_k|).
  median: 1-Lipschitz in the max norm, so dm_j <= max over the block of da_k; where the reference median lies within
    dm_j of the deadband l, one side may zero it and the other not: dm_j += l.
  integration over a block of T = block_us * 1e-6f (relative error 2u):
    E_v += dm T + 3u |m| T + u |v|;   E_p += E_v T + dm T^2 / 2 + 4u (|v| T + |m| T^2 / 2 + |p|).
The fallback under a double-precision MicroPython rounds less than the C (only its array('f') stores), so the same
bound holds for it; C against fallback is held to twice the bound.
"""

from __future__ import annotations

import json
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codegen.kernel import reference as ref
from codegen.tools import find_tool

U = 2.0**-24  # float32 unit roundoff
ROOT = Path(__file__).resolve().parent.parent
DRIVER = Path(__file__).resolve().parent / "mp_kernel_driver.py"


@dataclass
class Case:
    """One run: a configuration, an initial orientation/bias/velocity (or calibration samples), and windows."""

    cfg: ref.KernelConfig
    q0: np.ndarray
    bias: np.ndarray
    v0: np.ndarray
    windows: list = field(default_factory=list)  # [(samples (N, 6) int16, dt_us (N,) int32)]
    calib: np.ndarray | None = None


def f32(x):
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def make_window(rng, count, cfg: ref.KernelConfig, gravity_axis=2, accel_sigma_g=0.3, gyro_dps=60.0, jitter_us=800,
                period_us=5000):
    """Random raw counts (count, 6) with gravity on one axis plus noise, and jittered hold times (count,)."""
    acc = rng.normal(0.0, accel_sigma_g, (count, 3))
    acc[:, gravity_axis] += 1.0
    gyr = rng.normal(0.0, gyro_dps / 2, (count, 3))
    counts = np.empty((count, 6))
    counts[:, :3] = acc * cfg.accel_lsb_per_g
    counts[:, 3:] = gyr * cfg.gyro_lsb_per_dps
    samples = np.clip(np.round(counts), -32768, 32767).astype(np.int16)
    dt = rng.integers(period_us - jitter_us, period_us + jitter_us + 1, count).astype(np.int32)
    return samples, dt


def window_bound(samples, dt_us, q0, v0, bias, cfg: ref.KernelConfig, theta0=0.0, result=None):
    """(bound on |displacement error| per axis (m), bound on |velocity error| (m/s), E_q at the end, reference
    WindowResult) for one window of the float32 kernel against the reference; theta0 is E_q at the start."""
    samples = np.asarray(samples).reshape(-1, 6)
    dt = np.asarray(dt_us, dtype=np.float64) * 1e-6
    res = result or ref.process_window(samples, dt_us, q0, v0, bias, cfg)
    body = ref.remap_axes(samples, cfg.axis_map)
    f_norm = np.linalg.norm(body[:, :3] * cfg.accel_ms2_per_lsb, axis=1)
    omega = np.linalg.norm((body[:, 3:] - bias) * cfg.gyro_rads_per_lsb, axis=1)
    h = 0.5 * omega * dt
    bias_rate = np.linalg.norm(np.asarray(bias, dtype=np.float64)) * cfg.gyro_rads_per_lsb
    step = 18 * U + 3 * U * (omega + bias_rate) * dt + h**6 / 720
    e_q = theta0 + np.concatenate([[0.0], np.cumsum(step)])
    a, _ = ref.enu_acceleration(samples, dt, q0, bias, cfg)
    da = f_norm * (2 * e_q[:-1] + 19 * U) + U * (ref.STANDARD_GRAVITY + np.abs(a).max(axis=1))
    b = cfg.block
    e_v = 0.0
    e_p = 0.0
    v = np.abs(np.asarray(v0, dtype=np.float64)).max()
    p = 0.0
    l = cfg.deadband_ms2
    for j in range(len(samples) // b):
        t = dt[j * b : (j + 1) * b].sum()
        dm = da[j * b : (j + 1) * b].max()
        m_raw = np.abs(res.raw_medians[j])
        if np.any(np.abs(m_raw - l) <= dm):
            dm += l
        m = np.abs(res.medians[j]).max()
        e_v += dm * t + 3 * U * m * t + U * v
        e_p += e_v * t + dm * t * t / 2 + 4 * U * (v * t + m * t * t / 2 + p)
        p += v * t + m * t * t / 2
        v += m * t
    # the reference itself (float64, per-sample sums) rounds at ~1e-16 relative: negligible but not zero
    return e_p + 1e-12 * (1 + p), e_v + 1e-12 * (1 + v), e_q[-1], res


def micropython() -> str | None:
    return find_tool("micropython")


def write_fallback(folder: Path, loaded=None) -> Path:
    """Render the board's dr_fallback.py (as `deadreckon generate` does) into folder."""
    from codegen.board.loader import load_board
    from codegen.generate import render_tree

    tree = render_tree(loaded if loaded is not None else load_board())
    path = Path(folder) / "dr_fallback.py"
    path.write_bytes(tree["app/dr_fallback.py"].content)
    return path


def case_to_json(case: Case) -> dict:
    c = case.cfg
    return {
        "config": [c.block, c.window, c.accel_lsb_per_g, c.gyro_lsb_per_dps, c.deadband_g, c.motion_threshold_g],
        "q0": [float(x) for x in f32(case.q0)],
        "bias": [float(x) for x in f32(case.bias)],
        "v0": [float(x) for x in f32(case.v0)],
        "calib": None if case.calib is None else [int(x) for x in np.asarray(case.calib).ravel()],
        "windows": [[[int(x) for x in np.asarray(s).ravel()], [int(x) for x in np.asarray(d).ravel()]]
                    for s, d in case.windows],
    }


def run_driver(module: str, module_dir: Path, cases: list[Case], medians: list | None = None, work: Path = None,
               timeout: float = 600, latlon: list | None = None) -> dict:
    """Run tests/mp_kernel_driver.py under `micropython` with `module` (dr_fallback or dr_native) importable from
    module_dir. medians: [(values float32 array, b)]; latlon: [(lat_e7, lon_e7, east_m, north_m)] for
    offset_latlon. Returns the driver's JSON answer."""
    work = Path(work or module_dir)
    payload = {"cases": [case_to_json(c) for c in cases],
               "medians": [[[float(x) for x in np.asarray(v, dtype=np.float32)], int(b)] for v, b in medians or []],
               "latlon": [[int(a), int(b), float(e), float(n)] for a, b, e, n in latlon or []]}
    (work / "input.json").write_text(json.dumps(payload))
    env = dict(os.environ, MICROPYPATH=f"{module_dir}:.frozen")
    done = subprocess.run([micropython(), "-X", "heapsize=64M", str(DRIVER), module, str(work / "input.json")],
                          capture_output=True, text=True, env=env, timeout=timeout)
    if done.returncode:
        raise AssertionError(f"micropython driver failed ({done.returncode}):\n{done.stdout[-2000:]}\n"
                             f"{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_c(kernel, case: Case):
    """The C kernel (cffi) on a case: list of (displacement, velocity, q) float32 per window."""
    c = case.cfg
    run = kernel.session(block=c.block, window=c.window, accel_lsb_per_g=c.accel_lsb_per_g,
                         gyro_lsb_per_dps=c.gyro_lsb_per_dps, deadband_g=c.deadband_g,
                         motion_threshold_g=c.motion_threshold_g, axis_map=c.axis_map)
    if case.calib is not None:
        run.calibrate(case.calib)
    else:
        run.q = f32(case.q0)
        run.gyro_bias_lsb = f32(case.bias)
    run.set_velocity(*[float(x) for x in f32(case.v0)])
    out = []
    for samples, dt in case.windows:
        d, v, m = run.process(samples, dt)
        out.append((d.astype(np.float64), v.astype(np.float64), run.q.astype(np.float64), m))
    return out


def run_reference(case: Case):
    """Reference on a case, with the error bound of every window: list of (disp, vel, q, bound_p, bound_v)."""
    c = case.cfg
    if case.calib is not None:
        cal = ref.calibrate(case.calib, c)
        q, bias = cal.q, cal.gyro_bias_lsb
    else:
        q, bias = f32(case.q0), f32(case.bias)
    v = f32(case.v0)
    theta = 0.0 if case.calib is None else 64 * U  # the calibration's tilt: a sqrt, a normalisation, means
    out = []
    for samples, dt in case.windows:
        bp, bv, theta, res = window_bound(samples, dt, q, v, bias, c, theta)
        out.append((res.displacement, res.velocity, res.q, bp, bv))
        q, v = res.q, res.velocity
    return out
