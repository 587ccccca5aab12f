"""Kalman filter + Rauch-Tung-Striebel smoother over position, velocity and accelerometer bias (method step 7).

Each ENU axis is an independent three-state model driven by the rotated, gravity-free accelerations:

    p' = v,   v' = a_enu - b + w_a,   b' = w_b        (w_a, w_b white, spectral densities q_a, q_b)

Nodes are a regular grid (`rate`) merged with the GPS epochs (an epoch is processed at its own time, not at the
nearest sample). Between nodes the IMU samples enter as their exact zero-order-hold velocity and position increments
(codegen.kernel.reference.integrate_zoh), so the filter's cost does not grow with the IMU rate. GPS velocities, and
positions where given, update the state with their own 1-sigma.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from codegen.kernel.reference import integrate_zoh
from codegen.post.orientation import sample_edges


@dataclass
class SmootherOptions:
    accel_noise: float = 0.05  # m/s^2/sqrt(Hz): accelerometer noise plus orientation error, on the velocity
    bias_walk: float = 0.002  # m/s^2/sqrt(s): how fast the ENU accelerometer bias may wander
    initial_bias_sigma: float = 0.2  # m/s^2
    use_positions: bool = True
    rate: float = 10.0  # Hz, filter nodes between GPS epochs (the trajectory's rows)


@dataclass
class SmootherResult:
    t: np.ndarray  # (T,) node times, s
    pos: np.ndarray  # (T,3) ENU m
    vel: np.ndarray  # (T,3) ENU m/s
    bias: np.ndarray  # (T,3) ENU m/s^2
    sigma_pos: np.ndarray  # (T,3)
    sigma_vel: np.ndarray  # (T,3)
    gps_index: np.ndarray  # (M,) node index of each GPS epoch used (-1 when outside)
    filtered_vel: np.ndarray  # (T,3) forward-filter velocity (before smoothing)
    covariance: Optional[np.ndarray] = None  # (T,3,3,3) per node and axis: smoothed covariance of (p, v, b)
    filtered_covariance: Optional[np.ndarray] = None  # (T,3,3,3): the forward filter's, after the node's updates


def _transition(dt: float) -> tuple[np.ndarray, None]:
    return np.array([[1.0, dt, -0.5 * dt * dt], [0.0, 1.0, -dt], [0.0, 0.0, 1.0]]), None


def _process_noise(dt: float, qa: float, qb: float) -> np.ndarray:
    d2, d3, d4, d5 = dt**2, dt**3, dt**4, dt**5
    q_acc = qa * np.array([[d3 / 3, d2 / 2, 0.0], [d2 / 2, dt, 0.0], [0.0, 0.0, 0.0]])
    q_bias = qb * np.array([[d5 / 20, d4 / 8, -d3 / 6], [d4 / 8, d3 / 3, -d2 / 2], [-d3 / 6, -d2 / 2, dt]])
    return q_acc + q_bias


NODE_SNAP = 0.25  # of a grid step: a grid node this close to a GPS epoch is replaced by the epoch


def node_times(start: float, end: float, rate: float, epochs: np.ndarray) -> np.ndarray:
    """Filter nodes: the grid start + k / rate (each node computed from k, never by adding steps) up to `end`, merged
    with the GPS epochs; a grid node within `NODE_SNAP` steps of an epoch gives way to it, so no two nodes (and no two
    trajectory rows) stand for the same moment."""
    step = 1.0 / rate
    grid = start + np.arange(int(np.floor((end - start) * rate + 1e-9)) + 1) * step
    if end - grid[-1] > NODE_SNAP * step:
        grid = np.append(grid, end)
    epochs = np.asarray(epochs, dtype=float)
    if len(epochs):
        at = np.clip(np.searchsorted(epochs, grid), 1, len(epochs) - 1) if len(epochs) > 1 else np.zeros(len(grid), int)
        nearest = np.minimum(np.abs(grid - epochs[at]), np.abs(grid - epochs[np.maximum(at - 1, 0)]))
        grid = grid[nearest > NODE_SNAP * step]
    return np.union1d(grid, epochs)


def smooth(imu_t: np.ndarray, acc_enu: np.ndarray, gps_t: np.ndarray, gps_vel: np.ndarray, gps_sigma_vel: np.ndarray,
           gps_pos: Optional[np.ndarray], gps_sigma_pos: Optional[np.ndarray], options: SmootherOptions = SmootherOptions(),
           progress=None, extra_accel_noise: Optional[Callable[[np.ndarray], np.ndarray]] = None,
           zero_velocity: Optional[Callable[[np.ndarray], np.ndarray]] = None) -> SmootherResult:
    """One KF + RTS pass from the first to the last GPS epoch inside the IMU span. Between epochs (a gap of any
    length included) the state is carried by the IMU alone; `extra_accel_noise(t)` gives, per node, an added
    acceleration noise (m/s^2/sqrt(Hz), per axis) for the step that ends there: where the ENU accelerations are less
    certain than `accel_noise` says (orientation interpolated across a GPS gap), the 1-sigma grows with it.
    `zero_velocity(t)` gives, per node, the 1-sigma (m/s) of a zero-velocity pseudo-measurement there (NaN: none):
    where the device stood inside a gap (codegen.post.stands)."""
    start, end = max(imu_t[0], gps_t[0]), min(imu_t[-1], gps_t[-1])
    inside = (gps_t >= start) & (gps_t <= end)
    nodes = node_times(start, end, options.rate, gps_t[inside])
    n = len(nodes)
    extra = np.zeros((n, 3)) if extra_accel_noise is None else np.broadcast_to(extra_accel_noise(nodes), (n, 3))
    still_sigma = np.full(n, np.nan) if zero_velocity is None else np.asarray(zero_velocity(nodes), dtype=float)
    # exact ZOH increments of the IMU input between consecutive nodes
    edges = sample_edges(imu_t)
    cum_v, cum_p = integrate_zoh(acc_enu, np.diff(edges), np.zeros(3))
    seg = np.clip(np.searchsorted(edges, nodes, side="right") - 1, 0, len(acc_enu) - 1)
    tau = (nodes - edges[seg])[:, None]
    vel_at = cum_v[seg] + acc_enu[seg] * tau
    pos_at = cum_p[seg] + cum_v[seg] * tau + 0.5 * acc_enu[seg] * tau**2
    gps_index = np.full(len(gps_t), -1)
    gps_index[inside] = np.searchsorted(nodes, gps_t[inside])
    meas_at = np.full(n, -1)
    meas_at[gps_index[inside]] = np.flatnonzero(inside)
    use_pos = options.use_positions and gps_pos is not None

    qa, qb = options.accel_noise**2, options.bias_walk**2
    x = np.zeros((3, 3))  # axis, state
    first = int(np.flatnonzero(inside)[0])
    x[:, 1] = gps_vel[first]
    if use_pos:
        x[:, 0] = np.nan_to_num(gps_pos[first])
    p0 = np.zeros((3, 3, 3))
    p0[:, 0, 0] = 1.0 if not use_pos else np.nan_to_num(gps_sigma_pos[first], nan=1e3) ** 2
    p0[:, 1, 1] = gps_sigma_vel[first] ** 2
    p0[:, 2, 2] = options.initial_bias_sigma**2
    xs_f = np.empty((n, 3, 3))
    ps_f = np.empty((n, 3, 3, 3))
    xs_p = np.empty((n, 3, 3))
    ps_p = np.empty((n, 3, 3, 3))
    fs = np.empty((n, 3, 3))
    p = p0
    cache: dict[float, tuple] = {}
    report_every = max(1, n // 20)
    for i in range(n):
        if i > 0:
            dt = nodes[i] - nodes[i - 1]
            key = round(dt, 9)
            if key not in cache:
                f, _ = _transition(dt)
                cache[key] = (f, _process_noise(dt, qa, qb), _process_noise(dt, 1.0, 0.0))
            f, q, q_unit = cache[key]
            if extra[i].any():
                q = q + (extra[i] ** 2)[:, None, None] * q_unit
            dv = vel_at[i] - vel_at[i - 1]
            dp = pos_at[i] - pos_at[i - 1] - vel_at[i - 1] * dt
            x = x @ f.T
            x[:, 0] += dp
            x[:, 1] += dv
            p = f @ p @ f.T + q
            fs[i] = f
        else:
            fs[i] = np.eye(3)
        xs_p[i], ps_p[i] = x, p
        m = meas_at[i]
        if m >= 0:
            x, p = _update(x, p, 1, gps_vel[m], gps_sigma_vel[m])
            if use_pos:
                x, p = _update(x, p, 0, gps_pos[m], gps_sigma_pos[m])
        if np.isfinite(still_sigma[i]):
            x, p = _update(x, p, 1, np.zeros(3), np.full(3, still_sigma[i]))
        xs_f[i], ps_f[i] = x, p
        if progress and i % report_every == 0:
            progress("filter", i / n)
    # RTS backwards
    xs, ps = xs_f.copy(), ps_f.copy()
    for i in range(n - 2, -1, -1):
        f = fs[i + 1]
        c = ps_f[i] @ f.T @ np.linalg.inv(ps_p[i + 1])
        xs[i] = xs_f[i] + np.einsum("aij,aj->ai", c, xs[i + 1] - xs_p[i + 1])
        ps[i] = ps_f[i] + c @ (ps[i + 1] - ps_p[i + 1]) @ np.transpose(c, (0, 2, 1))
        if progress and i % report_every == 0:
            progress("smoother", 1.0 - i / n)
    if progress:
        progress("smoother", 1.0)
    sd = np.sqrt(np.maximum(np.diagonal(ps, axis1=2, axis2=3), 0.0))
    return SmootherResult(nodes, xs[:, :, 0], xs[:, :, 1], xs[:, :, 2], sd[:, :, 0], sd[:, :, 1], gps_index,
                          xs_f[:, :, 1], ps, ps_f)


def _update(x, p, state: int, z: np.ndarray, sigma: np.ndarray):
    """Scalar update of one state on each axis where z and sigma are finite."""
    ok = np.isfinite(z) & np.isfinite(sigma)
    if not ok.any():
        return x, p
    x, p = x.copy(), p.copy()
    for axis in np.flatnonzero(ok):
        h_p = p[axis, state, :]
        s = h_p[state] + sigma[axis] ** 2
        k = h_p / s
        x[axis] = x[axis] + k * (z[axis] - x[axis, state])
        p[axis] = p[axis] - np.outer(k, h_p)
    return x, p
