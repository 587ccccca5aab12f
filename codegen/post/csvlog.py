"""The plain CSV pair: `t,ax,ay,az[,gx,gy,gz]` (s, g, deg/s) and `t,lat,lon,sog,cog,climb` (s, deg, m/s, deg from
North, m/s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from codegen.board.model import STANDARD_GRAVITY
from codegen.post.model import GpsSeries, ImuSeries
from codegen.post.table import Table, check_increasing, check_range, read_table

IMU_COLUMNS = ("t", "ax", "ay", "az")
GYRO_COLUMNS = ("gx", "gy", "gz")  # deg/s, optional: the orientation across GPS gaps
GPS_COLUMNS = ("t", "lat", "lon", "sog", "cog", "climb")
DEFAULT_DOPPLER_SIGMA = 0.1  # m/s, u-blox 6 velocity accuracy (NEO-6M datasheet: 0.1 m/s)
DEFAULT_POSITION_SIGMA = 2.5  # m, u-blox 6 horizontal CEP
MAX_ACCEL_G = 64.0  # g: four times the MPU-6050's widest range; beyond it a value is not a reading
MAX_RATE_DPS = 8000.0  # deg/s: four times the MPU-6050's widest range


def read_imu_csv(path: Path) -> tuple[ImuSeries, list[str]]:
    table = read_table(path, "IMU log", IMU_COLUMNS, optional=GYRO_COLUMNS)
    check_increasing(table, "IMU log")
    for column in IMU_COLUMNS[1:]:
        check_range(table, "IMU log", column, -MAX_ACCEL_G, MAX_ACCEL_G, "g",
                    f"accelerations are in g; an MPU-6050 reads at most 16 g, a log at most {MAX_ACCEL_G:g}")
    for column in GYRO_COLUMNS:
        if column in table.columns:
            check_range(table, "IMU log", column, -MAX_RATE_DPS, MAX_RATE_DPS, "deg/s",
                        f"rates are in degrees per second; an MPU-6050 reads at most 2000, a log at most "
                        f"{MAX_RATE_DPS:g}")
    c = table.columns
    acc = np.stack([c["ax"], c["ay"], c["az"]], axis=1) * STANDARD_GRAVITY
    gyro = np.radians(np.stack([c[k] for k in GYRO_COLUMNS], axis=1)) if all(k in c for k in GYRO_COLUMNS) else None
    return ImuSeries(c["t"], acc, gyro), table.notes


MAX_SPEED = 600.0  # m/s: faster than an airliner is not a GPS speed logger's reading


def check_gps_ranges(table: Table, what: str) -> None:
    check_range(table, what, "lat", -90.0, 90.0, "deg", "latitude is in degrees, -90..90 (south negative)")
    check_range(table, what, "lon", -180.0, 180.0, "deg", "longitude is in degrees, -180..180 (west negative)")
    check_range(table, what, "sog", 0.0, MAX_SPEED, "m/s", "speed over ground is in m/s and never negative")
    check_range(table, what, "climb", -MAX_SPEED, MAX_SPEED, "m/s", "climb rate is in m/s")


def velocity_from_sog_cog(sog, cog_deg, climb) -> np.ndarray:
    """ENU velocity: v_E = SOG sin(COG), v_N = SOG cos(COG), v_U = climb."""
    cog = np.radians(cog_deg)
    return np.stack([sog * np.sin(cog), sog * np.cos(cog), climb], axis=1)


def average_duplicate_epochs(t: np.ndarray, *columns: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Collapse rows with equal t into their mean (t must be non-decreasing)."""
    unique, start = np.unique(t, return_index=True)
    if len(unique) == len(t):
        return t, list(columns)
    counts = np.diff(np.append(start, len(t)))
    out = [np.add.reduceat(col, start, axis=0) / counts.reshape((-1,) + (1,) * (col.ndim - 1)) for col in columns]
    return unique, out


def read_gps_csv(path: Path, doppler_sigma: float = DEFAULT_DOPPLER_SIGMA,
                 position_sigma: float = DEFAULT_POSITION_SIGMA) -> tuple[GpsSeries, list[str]]:
    table = read_table(path, "GPS log", GPS_COLUMNS, optional=("alt", "h"))
    check_increasing(table, "GPS log", strict=False)
    check_gps_ranges(table, "GPS log")
    c = table.columns
    vel = velocity_from_sog_cog(c["sog"], c["cog"], c["climb"])
    h = c.get("alt", c.get("h", np.full(len(table), np.nan)))
    n_rows = len(table)
    t, (lat, lon, h, vel) = average_duplicate_epochs(c["t"], c["lat"], c["lon"], h, vel)
    notes = list(table.notes)
    if len(t) < n_rows:
        notes.append(f"{path}: averaged {n_rows - len(t)} duplicate GPS epoch(s)")
    m = len(t)
    sigma_pos = np.tile([position_sigma, position_sigma, np.nan if np.isnan(h).all() else 2 * position_sigma], (m, 1))
    gps = GpsSeries(t, lat, lon, h, vel, np.full((m, 3), doppler_sigma), sigma_pos, np.zeros(m, dtype=int))
    return gps, notes
