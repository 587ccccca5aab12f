"""Replay of the real handheld walk in ../shared/data/gnss-imu-walk (rtklibexplorer/GNSS_IMU walk_0827).

The IMU (`imu_1730_sf.csv`: GPS-time stamped, ~167 Hz, accel in g, gyro in rad/s) is degraded to MPU-6050 quality
by codegen.sim.mpu6050.degrade_recording (noise, offsets, scale, cross-axis, drift, int16 counts at the board's
ranges) and keeps its own timestamps. The RTK solution (`gnss_1730_sf.pos`, 4 Hz) gives the truth: positions of
RTK epochs (Q = 1 fixed, ~1 cm; Q = 2 float, the last 46 s of the walk, decimetres at worst, still far below
the metres being measured) and the receiver's Doppler velocities. The device's GPS is the NEO-6M model of
codegen.sim.neo6m sampled at 1 Hz on top of that truth. Time 0 is the first IMU sample.
"""

from __future__ import annotations

import calendar
import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codegen.sim.neo6m import geodetic_to_enu
from codegen.sim.trajectory import SampledTruth

WALK_DIR = ("gnss-imu-walk",)
IMU_FILE = "imu_1730_sf.csv"
POS_FILE = "gnss_1730_sf.pos"


@dataclass(frozen=True)
class RecordedTruth(SampledTruth):
    """Truth from the RTK solution, with the interface of a Trajectory that the GPS model and metrics use."""

    t: np.ndarray  # (K,) s from the first IMU sample
    pos: np.ndarray  # (K, 3) ENU m from the first epoch
    vel: np.ndarray  # (K, 3) ENU m/s (Doppler)
    fixed: np.ndarray  # (K,) bool, an RTK solution (Q = 1 fixed or Q = 2 float), not a single-point fix
    origin: tuple[float, float, float]
    rest_s: float
    name: str = "replay-walk"

    def epochs(self, rate_hz: float) -> np.ndarray:
        """The recording's own epochs decimated to rate_hz (4 Hz -> 1 Hz keeps every 4th), from t >= 0."""
        step = max(1, int(round(1.0 / (rate_hz * np.median(np.diff(self.t))))))
        first = int(np.searchsorted(self.t, 0.0))
        return self.t[first::step]

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def trusted(self, times) -> np.ndarray:
        """True where both neighbouring epochs are RTK solutions (the truth there is good to decimetres)."""
        times = np.asarray(times, dtype=float)
        i = np.clip(np.searchsorted(self.t, times), 1, len(self.t) - 1)
        return self.fixed[i - 1] & self.fixed[i] & (times >= self.t[0]) & (times <= self.t[-1])


def default_walk_dir() -> Path:
    """../shared/data/gnss-imu-walk relative to the project checkout (the package's parent's parent)."""
    return Path(__file__).resolve().parents[3].joinpath("shared", "data", *WALK_DIR)


def _gpst_seconds(date: str, clock: str) -> float:
    whole, _, frac = clock.partition(".")
    stamp = _dt.datetime.strptime(f"{date} {whole}", "%Y/%m/%d %H:%M:%S")
    return calendar.timegm(stamp.timetuple()) + float(f"0.{frac or 0}")


def load_walk(folder: Path | None = None):
    """Read the recording. Returns (imu_t (N,) s from the start, accel (N, 3) g, gyro (N, 3) rad/s, truth)."""
    folder = Path(folder) if folder is not None else default_walk_dir()
    imu = np.loadtxt(folder / IMU_FILE, delimiter=",", usecols=range(7))
    t0 = imu[0, 0]
    rows = []
    for line in (folder / POS_FILE).read_text().splitlines():
        if not line.strip() or line.startswith("%"):
            continue
        f = line.split()
        # GPST, lat, lon, h, Q, ..., vn ve vu at columns 15..17 (after the date and time fields)
        rows.append([_gpst_seconds(f[0], f[1]) - t0, float(f[2]), float(f[3]), float(f[4]), float(f[5]),
                     float(f[15]), float(f[16]), float(f[17])])
    pos = np.array(rows)
    origin = (pos[0, 1], pos[0, 2], pos[0, 3])
    enu = geodetic_to_enu(pos[:, 1], pos[:, 2], pos[:, 3], origin)
    vel = np.stack([pos[:, 6], pos[:, 5], pos[:, 7]], axis=-1)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    moving = np.flatnonzero(speed > 0.3)
    rest_s = float(pos[moving[0], 0]) if len(moving) else float(pos[-1, 0])
    truth = RecordedTruth(pos[:, 0], enu, vel, np.isin(pos[:, 4], (1, 2)), origin, rest_s)
    return imu[:, 0] - t0, imu[:, 1:4], imu[:, 4:7], truth
