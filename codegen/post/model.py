"""The data a post-processing run works on: an IMU series and a GPS series on one time axis (seconds).

Readers (`csvlog`, `rtklib`, `devicelog`) produce a `PostLog`; the pipeline never sees file formats.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass
class ImuSeries:
    """Accelerometer samples in the sensor frame.

    t: (N,) s, strictly increasing, on the GPS time axis. acc: (N,3) specific force, m/s^2 (a device at rest, flat,
    reads +g on its up axis). gyro: optional (N,3) rad/s (turns the accelerations across GPS gaps when present).
    """

    t: np.ndarray
    acc: np.ndarray
    gyro: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return len(self.t)

    @property
    def rate_hz(self) -> float:
        return 1.0 / float(np.median(np.diff(self.t))) if len(self.t) > 1 else float("nan")


@dataclass
class GpsSeries:
    """GPS epochs: geodetic position and Doppler velocity in East-North-Up.

    t: (M,) s. lat, lon: degrees; h: metres above the ellipsoid or NaN when the log has none. vel: (M,3) ENU m/s.
    sigma_vel: (M,3) 1-sigma of vel, m/s. sigma_pos: (M,3) 1-sigma of the ENU position, m (NaN: no position).
    quality: (M,) integer solution quality (RTKLIB Q: 1 fixed, 2 float, ...; 0 when unknown).
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    vel: np.ndarray
    sigma_vel: np.ndarray
    sigma_pos: np.ndarray
    quality: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def select(self, mask: np.ndarray) -> "GpsSeries":
        return GpsSeries(
            self.t[mask], self.lat[mask], self.lon[mask], self.h[mask], self.vel[mask],
            self.sigma_vel[mask], self.sigma_pos[mask], self.quality[mask],
        )


@dataclass
class Calibration:
    """Accelerometer correction a_true = scale * (a_raw - offset), per sensor axis; offset in m/s^2."""

    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))

    def apply(self, acc: np.ndarray) -> np.ndarray:
        return (acc - self.offset) * self.scale


@dataclass
class PostLog:
    """One logged run: what a reader found, plus notes (dropped lines, time mapping) for the report."""

    name: str
    imu: ImuSeries
    gps: GpsSeries
    calibration: Optional[Calibration] = None
    notes: list[str] = field(default_factory=list)
    time_scale: str = "relative"  # "gpst": t is GPS time as a Unix-style count (calendar as if UTC); else seconds
