"""Delay between the IMU and GPS streams by cross-correlation (method step 1).

For a trial lag tau, the IMU's velocity change over each GPS interval is the integral of the ENU acceleration over
[t_k + tau, t_k+1 + tau]; the GPS's is v_k+1 - v_k. The lag that makes the two sequences agree best (least squares
after removing each sequence's mean, which absorbs a constant bias; each axis of each interval weighted by the
inverse variance of its GPS velocity change, so a noisy climb rate does not outvote the Doppler) is the delay: IMU timestamps are late by tau,
and t_imu - tau puts them on GPS time. A grid at the IMU sample period finds the peak, a bounded scalar search
refines it (the zero-order-hold integral is continuous in tau).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from codegen.post.orientation import cumulative_integral


@dataclass
class DelayEstimate:
    delay: float  # s, IMU timestamps late by this much
    lags: np.ndarray  # s, grid
    cost: np.ndarray  # normalised misfit on the grid (1 = no better than zero IMU signal)
    correlation: float  # correlation coefficient at the delay
    sigma: float  # s, 1-sigma from the curvature of the misfit
    at_edge: bool = False  # the best lag is the grid's first or last: the delay lies at or beyond the search range


def estimate_delay(imu_t: np.ndarray, acc_enu: np.ndarray, gps_t: np.ndarray, gps_vel: np.ndarray,
                   max_lag: float = 1.0, gps_sigma_vel: np.ndarray | None = None) -> DelayEstimate:
    """gps_sigma_vel: (M, 3) 1-sigma of the GPS velocities (m/s); None weighs every axis alike."""
    nodes, cum = cumulative_integral(imu_t, acc_enu)
    step = float(np.median(np.diff(imu_t)))
    t0, t1 = gps_t[:-1], gps_t[1:]
    inside = (t0 - max_lag >= imu_t[0]) & (t1 + max_lag <= imu_t[-1]) & (t1 - t0 < 5 * np.median(t1 - t0))
    if inside.sum() < 5:
        inside = (t0 >= imu_t[0]) & (t1 <= imu_t[-1])
        max_lag = 0.0
    t0, t1 = t0[inside], t1[inside]
    dv_gps = np.diff(gps_vel, axis=0)[inside]
    dv_gps = dv_gps - dv_gps.mean(axis=0)
    if gps_sigma_vel is None:
        weight = np.ones_like(dv_gps)
    else:
        variance = gps_sigma_vel[:-1] ** 2 + gps_sigma_vel[1:] ** 2
        weight = (1.0 / variance)[inside]
        weight = weight / weight.mean()
    norm = float(np.sum(weight * dv_gps**2))

    def dv_imu(tau):
        c0 = np.stack([np.interp(t0 + tau, nodes, cum[:, i]) for i in range(3)], axis=1)
        c1 = np.stack([np.interp(t1 + tau, nodes, cum[:, i]) for i in range(3)], axis=1)
        d = c1 - c0
        return d - d.mean(axis=0)

    def cost(tau):
        return float(np.sum(weight * (dv_imu(tau) - dv_gps) ** 2)) / norm

    lags = np.arange(-max_lag, max_lag + 0.5 * step, step) if max_lag > 0 else np.array([0.0])
    per_interval = np.array([np.sum(weight * (dv_imu(tau) - dv_gps) ** 2, axis=1) for tau in lags]) / norm
    costs = per_interval.sum(axis=1)
    best = int(np.argmin(costs))
    if 0 < best < len(lags) - 1:
        refined = minimize_scalar(cost, bounds=(lags[best - 1], lags[best + 1]), method="bounded",
                                  options={"xatol": step / 100})
        delay = float(refined.x)
    else:
        delay = float(lags[best])
    d = dv_imu(delay)
    corr = float(np.sum(weight * d * dv_gps) / np.sqrt(np.sum(weight * d * d) * norm)) if norm > 0 else 0.0
    # curvature of the misfit -> 1-sigma of the lag (misfit scaled so its minimum is a unit-variance chi-square)
    h = step
    c0, cp, cm = cost(delay), cost(delay + h), cost(delay - h)
    curvature = (cp + cm - 2 * c0) / h**2
    dof = max(d.size - 1, 1)
    sigma = float(np.sqrt(2.0 * c0 / dof / curvature)) if curvature > 0 and c0 > 0 else float("inf")
    # the curvature trusts white residuals; motion the model misses is not white, so also resample the intervals in
    # blocks and take the spread of the best lag (a broad or two-humped misfit shows here)
    sigma = max(sigma, _block_bootstrap_sigma(lags, per_interval))
    return DelayEstimate(delay, lags, costs, corr, sigma, at_edge=len(lags) > 1 and best in (0, len(lags) - 1))


BOOTSTRAP_DRAWS = 200
BOOTSTRAP_BLOCK = 10  # intervals


def _block_bootstrap_sigma(lags: np.ndarray, per_interval: np.ndarray, seed: int = 0) -> float:
    n = per_interval.shape[1]
    if len(lags) < 3 or n < 2 * BOOTSTRAP_BLOCK:
        return 0.0
    rng = np.random.default_rng(seed)
    starts = np.arange(0, n - BOOTSTRAP_BLOCK + 1)
    block_cost = np.stack([per_interval[:, s:s + BOOTSTRAP_BLOCK].sum(axis=1) for s in starts], axis=1)
    picks = rng.integers(0, len(starts), (BOOTSTRAP_DRAWS, max(1, n // BOOTSTRAP_BLOCK)))
    best = lags[np.argmin(block_cost[:, picks].sum(axis=2), axis=0)]
    return float(np.std(best))
