"""Position estimators compared by the benchmark: a registry of name -> function.

A method is a function

    estimate(run: RunData, starts: (S,) s, times: (S, H) s) -> (S, H, 2) ENU East/North metres

that, for each outage starting at `starts[i]` (the GPS gives no fix from then on), returns its horizontal position
estimate at the absolute times `times[i]`, in the run's ENU frame (the frame of `run.gps.enu`). The contract that
keeps the comparison honest: for outage i a method may use every IMU sample, but only GPS fixes with
`t < starts[i]` (`run.gps.last_valid_before(starts)` gives the last usable fix); tests/test_sim_bench.py checks
every registered method by corrupting the GPS after the start. Working on all outages at once lets a method share
work that does not depend on the GPS (the seed's orientation and ENU accelerations), so the benchmark stays fast.

The baselines and the seed method are defined here; the fused reference (codegen.kernel.fused) provides its own
`estimate` with this contract and is registered below, so the specification does not depend on the simulator.
A new method joins every table with the decorator:

    @register("name")
    def name(run, starts, times): ...
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from codegen.kernel import eskf, fused, reference
from codegen.kernel.layout import FUSED
from codegen.kernel.reference import KernelConfig

Method = Callable[..., np.ndarray]
METHODS: dict[str, Method] = {}


def register(name: str) -> Callable[[Method], Method]:
    def wrap(fn: Method) -> Method:
        METHODS[name] = fn
        return fn

    return wrap


def registered_methods() -> dict[str, Method]:
    return dict(METHODS)


def _last_fixes(run, starts):
    idx = run.gps.last_valid_before(starts)
    if np.any(idx < 0):
        raise ValueError("an outage starts before the first GPS fix")
    return idx


@register("hold-last-fix")
def hold_last_fix(run, starts, times):
    """Baseline 3: keep showing the last GPS position."""
    idx = _last_fixes(run, starts)
    p = run.gps.enu[idx, :2]
    return np.broadcast_to(p[:, None, :], times.shape + (2,)).copy()


@register("const-velocity")
def constant_velocity(run, starts, times):
    """Baseline 2: extrapolate the last fix along its Doppler velocity (speed + course, as NMEA gives them)."""
    idx = _last_fixes(run, starts)
    p = run.gps.enu[idx, :2]
    v = run.gps.device_velocity()[idx]
    dt = times - run.gps.t[idx][:, None]
    return p[:, None, :] + v[:, None, :] * dt[..., None]


def orientations(q0, omega, dt):
    """reference.gyro_integrate computed by a parallel prefix scan: q_k = q0 (x) d_0 (x) ... (x) d_{k-1} with
    d_j = exp(omega_j dt_j / 2). The same product in another order (log2(N) vectorised steps instead of N Python
    steps), so it agrees with the reference to rounding (tests/test_sim_bench.py holds it to 1e-9)."""
    steps = reference.quat_from_rotvec(np.asarray(omega, dtype=np.float64) * np.asarray(dt)[:, None])
    prefix = np.vstack([reference.quat_normalise(q0)[None, :], steps])
    shift = 1
    while shift < len(prefix):
        prefix[shift:] = reference.quat_multiply(prefix[:-shift], prefix[shift:])
        shift *= 2
    return reference.quat_normalise(prefix)


def enu_acceleration(samples, dt, q0, gyro_bias_lsb, cfg):
    """reference.enu_acceleration (steps 1-3) with the orientation from `orientations` (fast for long runs)."""
    body = reference.remap_axes(samples, cfg.axis_map)
    f = body[:, :3] * cfg.accel_ms2_per_lsb
    omega = (body[:, 3:] - np.asarray(gyro_bias_lsb, dtype=np.float64)) * cfg.gyro_rads_per_lsb
    qs = orientations(q0, omega, dt)
    a = np.einsum("kij,kj->ki", reference.quat_to_matrix(qs[:-1]), f)
    a[:, 2] -= reference.STANDARD_GRAVITY
    return a, qs


def seed_acceleration(run):
    """The seed's IMU pipeline over the whole run (it does not depend on GPS), cached on the run.

    Calibration on the first `algorithm.calibration_s` seconds (tilt, gyro bias), then codegen.kernel.reference steps 1-5
    over the rest: gyro-only orientation from the calibration tilt (yaw 0: the seed never knew North), rotation to
    "ENU", gravity removal, block medians on blocks aligned with the windows, deadband. Returns
    (t (M+1,) s sample times, held (M, 3) m/s^2, dt (M,) s), held[k] acting from t[k] to t[k+1].
    """
    key = "seed_acceleration"
    if key in run.cache:
        return run.cache[key]
    cfg = KernelConfig.from_board(run.board)
    t = run.t_us * 1e-6
    n_cal = int(np.searchsorted(t, run.board.algorithm.calibration_s))
    cal = reference.calibrate(run.counts[:n_cal], cfg)
    samples = run.counts[n_cal:]
    usable = (len(samples) - 1) // cfg.block * cfg.block
    dt = np.diff(t[n_cal:])[:usable]
    a, _ = enu_acceleration(samples[:usable], dt, cal.q, cal.gyro_bias_lsb, cfg)
    held = np.repeat(reference.deadband(reference.block_median(a, cfg.block), cfg.deadband_ms2), cfg.block, axis=0)
    result = (t[n_cal : n_cal + usable + 1], held, dt)
    run.cache[key] = result
    return result


def zoh_from(t, held, dt, t_start, v0, times):
    """Zero-order-hold double integration of `held` from t_start with initial velocity v0 (S, 2), evaluated at
    times (S, H): exactly reference.integrate_zoh on the samples between, computed for all starts from one pass.
    Integration starts at the first sample at or after t_start and stops at the last sample at or before a time."""
    vel, pos = reference.integrate_zoh(held, dt)  # from rest at t[0]: V(k), P(k)
    s = np.clip(np.searchsorted(t, t_start, side="left"), 0, len(t) - 1)
    k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)
    k = np.maximum(k, s[:, None])
    span = t[k] - t[s][:, None]
    disp = pos[k, :2] - pos[s, None, :2] - vel[s, None, :2] * span[..., None]
    # the fix is at t_start, the first sample a little later: the velocity carries the gap too
    return disp + v0[:, None, :] * (times - t_start[:, None])[..., None]


@register("seed")
def seed_method(run, starts, times):
    """Baseline 1: the seed's method as its report describes it. From the last fix and its GPS velocity, integrate
    the seed pipeline's ENU accelerations (gyro-only orientation, block median, deadband, zero-order hold)."""
    idx = _last_fixes(run, starts)
    t, held, dt = seed_acceleration(run)
    t_fix = run.gps.t[idx]
    return run.gps.enu[idx, None, :2] + zoh_from(t, held, dt, t_fix, run.gps.device_velocity()[idx], times)


register("fused")(fused.estimate)

# The carriers the error-state filter is for; a device configured for a pedestrian runs the fused method's
# pedestrian path instead (the scenario stands for that configuration: the filter does not decide the carrier).
VEHICLE_SCENARIOS = ("bike", "car", "car-town", "replay-car")


@register("eskf")
def eskf_method(run, starts, times):
    """The error-state Kalman filter (codegen.kernel.eskf) on a vehicle; fused_platform: pedestrian otherwise."""
    if run.scenario in VEHICLE_SCENARIOS:
        return eskf.estimate(run, starts, times)
    cfg = replace(fused.FusedConfig.from_board(run.board), platform=float(FUSED.param("platform").code("pedestrian")))
    return fused.estimate(run, starts, times, cfg)


@register("eskf-c")
def eskf_c_method(run, starts, times):
    """The error-state filter's float32 C (native_ext/dr_eskf.c through cffi) where "eskf" runs the reference."""
    if run.scenario in VEHICLE_SCENARIOS:
        from codegen.kernel import hosteskf

        return hosteskf.estimate(run, starts, times)
    return eskf_method(run, starts, times)
