"""Where the device stands still inside a GPS gap, told by the IMU, and the zero-velocity pseudo-measurement there.

Across a gap there is no GPS velocity, but a device that stands still says so itself: its accelerometer reads
gravity with only its noise (no steps, no engine) and its gyro reads nothing but its bias. Over a window of
`STILL_WINDOW` around each filter node the spread of |a| and the mean of |gyro| are compared with the same numbers
at the GPS epochs where the run stood (GPS speed below `STILL_GPS_SPEED`): a node whose window is as quiet as the
run's own stands gets a zero-velocity measurement, with the noise those stands show (the RMS of their GPS
velocity). A run that never stands under GPS uses fixed limits, an MPU-6050 at rest with some margin.

This is a measurement with its own noise (the smoother weighs it), not a reset: a stand keeps the bridge where the
device stood and its 1-sigma what the stand allows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

STILL_WINDOW = 1.0  # s, centred on each node
STILL_GPS_SPEED = 0.1  # m/s: GPS epochs slower than this teach what standing looks like
STILL_MARGIN = 1.5  # limit = this times the 90th percentile of the run's own stands
MIN_STAND_EPOCHS = 5  # fewer stand epochs under GPS: use the fixed limits
DEFAULT_ACCEL_SPREAD = 0.08  # m/s^2, |a| standard deviation over the window of a device at rest (fixed limit)
DEFAULT_GYRO_LEVEL = np.radians(1.5)  # rad/s, mean |gyro| at rest: bias and noise (fixed limit)
DEFAULT_VELOCITY_SIGMA = 0.05  # m/s, zero-velocity noise without stands under GPS
MIN_VELOCITY_SIGMA = 0.01  # m/s: a stand under GPS never says the device stands stiller than this


@dataclass
class Stillness:
    accel_limit: float  # m/s^2, spread of |a| over the window
    gyro_limit: Optional[float]  # rad/s, mean |gyro| over the window (None: no gyro in the log)
    velocity_sigma: float  # m/s, per axis, of the zero-velocity measurement
    learnt: bool  # limits from the run's own stands under GPS (else the fixed ones)

    def still(self, imu_t: np.ndarray, acc: np.ndarray, gyro: Optional[np.ndarray], at: np.ndarray) -> np.ndarray:
        """(len(at),) bool: the IMU's window around each time is as quiet as a stand."""
        spread, level = window_stats(imu_t, acc, gyro, at)
        quiet = spread <= self.accel_limit
        if self.gyro_limit is not None and level is not None:
            quiet &= level <= self.gyro_limit
        return quiet


def window_stats(imu_t: np.ndarray, acc: np.ndarray, gyro: Optional[np.ndarray], at: np.ndarray
                 ) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Spread (standard deviation) of |a| and mean |gyro| over `STILL_WINDOW` around each time in `at` (NaN where
    the window holds fewer than 3 samples)."""
    magnitude = np.linalg.norm(acc, axis=1)
    c1 = np.concatenate([[0.0], np.cumsum(magnitude)])
    c2 = np.concatenate([[0.0], np.cumsum(magnitude**2)])
    lo = np.searchsorted(imu_t, at - 0.5 * STILL_WINDOW)
    hi = np.searchsorted(imu_t, at + 0.5 * STILL_WINDOW)
    n = (hi - lo).astype(float)
    ok = n >= 3
    safe = np.where(ok, n, 1.0)
    mean = (c1[hi] - c1[lo]) / safe
    spread = np.sqrt(np.maximum((c2[hi] - c2[lo]) / safe - mean**2, 0.0))
    spread[~ok] = np.nan
    level = None
    if gyro is not None:
        cg = np.concatenate([[0.0], np.cumsum(np.linalg.norm(gyro, axis=1))])
        level = (cg[hi] - cg[lo]) / safe
        level[~ok] = np.nan
    return spread, level


def learn_stillness(imu_t: np.ndarray, acc: np.ndarray, gyro: Optional[np.ndarray], gps_t: np.ndarray,
                    gps_vel: np.ndarray) -> Stillness:
    """The limits and the zero-velocity noise from the GPS epochs where the run stood."""
    speed = np.hypot(gps_vel[:, 0], gps_vel[:, 1])
    inside = (gps_t - 0.5 * STILL_WINDOW >= imu_t[0]) & (gps_t + 0.5 * STILL_WINDOW <= imu_t[-1])
    stand = inside & (speed < STILL_GPS_SPEED)
    if stand.sum() < MIN_STAND_EPOCHS:
        return Stillness(DEFAULT_ACCEL_SPREAD, DEFAULT_GYRO_LEVEL if gyro is not None else None,
                         DEFAULT_VELOCITY_SIGMA, learnt=False)
    spread, level = window_stats(imu_t, acc, gyro, gps_t[stand])
    accel_limit = STILL_MARGIN * float(np.nanpercentile(spread, 90))
    gyro_limit = STILL_MARGIN * float(np.nanpercentile(level, 90)) if level is not None else None
    sigma = float(np.sqrt(np.mean(gps_vel[stand, :2] ** 2)))
    return Stillness(accel_limit, gyro_limit, max(sigma, MIN_VELOCITY_SIGMA), learnt=True)
