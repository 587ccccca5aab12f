"""What a device's accelerometer shows of its carrier: the features the fused method's platform and rest decisions
read, computed the same way from a simulated stream and from a real recording, so the two can be compared.

Per window (2 s by default, the fused method's vibration_tau_s) of the specific force's norm |f|:

- shaking: the standard deviation of |f| about its running mean (a first-order high-pass at 1 / (2 pi 0.5 s),
  the fused method's stat_tau_s), in mg: what its rest limit (rest_accel_g) and walking limit (walk_accel_g) compare;
- high-frequency share: the variance of |f| above 8 Hz (two first-order high-passes at 8 Hz, the fused method's
  vibration_hz) over that shaking's variance: a walker's steps stay below 8 Hz, a vehicle's road, wheels and
  engine reach above.

The filters are the analogue ones, discretised by the bilinear transform at each stream's own rate, so a 104 Hz
recording and the device's 200 Hz stream measure the same thing up to the transform's frequency warp (20 Hz reads
as 22.9 Hz at 104 Hz, 20.7 Hz at 200 Hz). The fused method's per-sample Euler steps of the same filters read lower
shares, the more so at low rates (fused_statistic_share computes them; docs/simulator.md gives both).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import bilinear, lfilter, lfilter_zi

from codegen.board.model import STANDARD_GRAVITY

WINDOW_S = 2.0  # s
SHAKING_TAU_S = 0.5  # s, the running mean's time constant
HIGH_HZ = 8.0  # Hz, where "high frequency" starts
QUIET_MS2 = 0.1  # m/s^2: a car's along-track acceleration under this is a held speed
SETTLE_S = 2.0  # s dropped at the start of a stream while the filters settle


@dataclass(frozen=True)
class WindowFeatures:
    """One row per window: its start (s), mean speed (m/s), shaking (mg) and high-frequency share."""

    start: np.ndarray
    speed: np.ndarray
    shaking_mg: np.ndarray
    high_share: np.ndarray

    def where(self, keep: np.ndarray) -> "WindowFeatures":
        return WindowFeatures(self.start[keep], self.speed[keep], self.shaking_mg[keep], self.high_share[keep])

    def speeds(self, low: float, high: float) -> "WindowFeatures":
        """The windows whose mean speed lies in [low, high) m/s."""
        return self.where((self.speed >= low) & (self.speed < high))


def _high_pass(x: np.ndarray, corner_hz: float, order: int, rate_hz: float) -> np.ndarray:
    """x through `order` first-order analogue high-passes at corner_hz (bilinear transform), from steady state."""
    wc = 2 * np.pi * corner_hz
    num = np.poly1d([1.0, 0.0]) ** order
    den = np.poly1d([1.0, wc]) ** order
    b, a = bilinear(num.coeffs, den.coeffs, fs=rate_hz)
    y, _ = lfilter(b, a, x - x[0], zi=lfilter_zi(b, a) * 0.0)
    return y


def window_features(t_s: np.ndarray, f: np.ndarray, speed: np.ndarray, window_s: float = WINDOW_S,
                    steady_speed: bool = True) -> WindowFeatures:
    """Features of a stream: t_s (N,) s (uniform up to jitter), f (N, 3) specific force m/s^2 in any frame, speed
    (N,) m/s at the same times. With steady_speed only windows whose speed stays within 30 % of their mean (or
    below 0.05 m/s: a stand) are kept, so a window belongs to one regime."""
    t_s = np.asarray(t_s, dtype=float)
    rate = 1.0 / float(np.median(np.diff(t_s)))
    norm = np.linalg.norm(np.asarray(f, dtype=float), axis=1)
    total = _high_pass(norm, 1.0 / (2 * np.pi * SHAKING_TAU_S), 1, rate)
    high = _high_pass(norm, HIGH_HZ, 2, rate)
    per = int(round(window_s * rate))
    first = int(np.searchsorted(t_s, t_s[0] + SETTLE_S))
    k = (len(norm) - first) // per
    cut = slice(first, first + k * per)
    tot2 = np.mean(total[cut].reshape(k, per) ** 2, axis=1)
    high2 = np.mean(high[cut].reshape(k, per) ** 2, axis=1)
    v = np.asarray(speed, dtype=float)[cut].reshape(k, per)
    mean_v = v.mean(axis=1)
    out = WindowFeatures(t_s[cut].reshape(k, per)[:, 0], mean_v, np.sqrt(tot2) / STANDARD_GRAVITY * 1e3,
                         high2 / np.maximum(tot2, 1e-30))
    if not steady_speed:
        return out
    steady = (v.max(axis=1) < 0.05) | ((v.min(axis=1) > 0.7 * mean_v) & (v.max(axis=1) < 1.3 * mean_v))
    return out.where(steady)


def fused_statistic_share(t_s: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The share as the fused method's per-sample steps compute it (codegen.kernel.fused.process: Euler steps of
    the same filters, variances over vibration_tau_s), per sample: what its platform decision compares with
    vibration_ratio. Rate-dependent, unlike window_features: for comparisons with figures taken that way."""
    t_s = np.asarray(t_s, dtype=float)
    dt = float(np.median(np.diff(t_s)))
    norm = np.linalg.norm(np.asarray(f, dtype=float), axis=1)

    def smooth(x, gain):
        gain = min(gain, 1.0)
        return lfilter([gain], [1.0, gain - 1.0], x, zi=[(1.0 - gain) * x[0]])[0]

    d = norm - smooth(norm, dt / SHAKING_TAU_S)
    beta = dt * HIGH_HZ * 2 * np.pi
    h = norm - smooth(norm, beta)
    h = h - smooth(h, beta)
    return smooth(h * h, dt / WINDOW_S) / np.maximum(smooth(d * d, dt / WINDOW_S), 1e-30)


def along_track_acceleration(t_s: np.ndarray, speed: np.ndarray, smooth_s: float = 1.0):
    """The carrier's along-track acceleration from its speed (a simulated truth's, or a real car's own wheel speed,
    whose bus stamps its samples unevenly): the speed on an even grid at the median step, through a gaussian of
    smooth_s, differentiated. Returns (grid s, m/s^2). What a vehicle's deadband (the board's l on the fused
    method's 0.5 s average) compares: how much of a drive's speed change lies within it."""
    from codegen.sim.trajectory import gaussian_filter1d

    t_s = np.asarray(t_s, dtype=float)
    dt = float(np.median(np.diff(t_s)))
    grid = t_s[0] + dt * np.arange(int(round((t_s[-1] - t_s[0]) / dt)) + 1)
    even = gaussian_filter1d(np.interp(grid, t_s, np.asarray(speed, dtype=float)), smooth_s / dt, mode="nearest")
    return grid, np.gradient(even, dt)


def deadband_shares(a: np.ndarray, deadband_ms2: float) -> np.ndarray:
    """The shares of along-track accelerations `a` under QUIET_MS2 (a held speed), from there to a vehicle's deadband
    (the board's l, in m/s^2: what the deadband takes away) and over it (what it keeps)."""
    q = np.abs(np.asarray(a, dtype=float))
    within = (q >= QUIET_MS2) & (q < deadband_ms2)
    return np.array([np.mean(q < QUIET_MS2), np.mean(within), np.mean(q >= deadband_ms2)])


def car_cruises(tr, margin_s: float = 2.0):
    """A simulated car's speed over ground, its along-track acceleration (along_track_acceleration) and which of its
    samples lie inside a cruise (the trajectory's events["cruises"], margin_s in from each end). Returns (speed m/s,
    acceleration m/s^2, inside)."""
    speed = np.linalg.norm(tr.vel[:, :2], axis=1)
    _, a = along_track_acceleration(tr.t, speed)
    inside = np.zeros(len(tr.t), dtype=bool)
    for begin, end in tr.events["cruises"]:
        inside |= (tr.t > begin + margin_s) & (tr.t < end - margin_s)
    return speed, a, inside
