"""The real car of ../shared/data/car-comma2k19 (commaai/comma2k19 Example_1, segment 40: a Toyota RAV4, 60 s on
a highway at 8-20 m/s): its dash unit's IMU, its u-blox fixes, the car's CAN wheel speed and comma's pose.

    car = load_car()                 # every stream on the device's boot clock, shifted to 0 at the first IMU sample
    car.accel, car.gyro              # (N, 3) m/s^2 specific force and rad/s, forward-right-down, ~104 Hz
    car.truth.at(times)              # the pose (20 Hz, comma's offline INS/GNSS/vision fit) in ENU metres
    device_imu(car, 200.0)           # the IMU as the board reads it: its rate, its frame, in g
    device_fixes(car, 1.0)           # the u-blox fixes a 1 Hz receiver reports, as a GpsTrack

ENU is local metres around the first u-blox fix (codegen.sim.neo6m.geodetic_to_enu, the mapping the device's GPS
positions get too); the pose's ECEF positions and velocities are taken there through geodetic coordinates. The pose
uses the same GNSS, so it is not independent of the fixes; it is smooth to centimetres, far below the metres an
outage is judged by.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codegen.kernel.reference import STANDARD_GRAVITY
from codegen.post.geodesy import ecef_to_geodetic
from codegen.sim.neo6m import COURSE_MIN_SPEED, GpsTrack, enu_to_geodetic, geodetic_to_enu
from codegen.sim.trajectory import SampledTruth

CAR_DIR = ("car-comma2k19",)


# the streams load_car reads, relative to the recording's folder
CAR_FILES = tuple(f"processed_log/{stream}/{part}" for stream in ("IMU/accelerometer", "IMU/gyro_uncalibrated",
                                                                  "CAN/speed", "GNSS/live_gnss_ublox")
                  for part in ("t", "value")) + tuple(
    f"global_pose/{name}" for name in ("frame_times", "frame_positions", "frame_velocities"))


def default_car_dir() -> Path:
    """../shared/data/car-comma2k19 relative to the project checkout."""
    return Path(__file__).resolve().parents[3].joinpath("shared", "data", *CAR_DIR)


def ecef_to_enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3) rotation taking ECEF vectors to East, North, Up at (lat, lon)."""
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    return np.array([[-np.sin(lo), np.cos(lo), 0.0],
                     [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                     [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])


@dataclass(frozen=True)
class PoseTruth(SampledTruth):
    """The pose as truth, with the interface of a Trajectory that the metrics use."""

    t: np.ndarray  # (K,) s
    pos: np.ndarray  # (K, 3) ENU m
    vel: np.ndarray  # (K, 3) ENU m/s
    rest_s: float = 0.0  # the car never stands in this segment
    name: str = "replay-car"

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def trusted(self, times) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        return (times >= self.t[0]) & (times <= self.t[-1])


@dataclass(frozen=True)
class CarRecording:
    t: np.ndarray  # (N,) s, IMU sample times
    accel: np.ndarray  # (N, 3) m/s^2, specific force, forward-right-down (z about -9.8 when level)
    gyro: np.ndarray  # (N, 3) rad/s, forward-right-down, uncalibrated
    can_t: np.ndarray  # (M,) s
    can_speed: np.ndarray  # (M,) m/s, the car's own speed from its bus
    fix_t: np.ndarray  # (K,) s, u-blox epochs (~10 Hz)
    fix_enu: np.ndarray  # (K, 3) m
    fix_speed: np.ndarray  # (K,) m/s, Doppler speed over ground
    fix_course: np.ndarray  # (K,) deg from North, clockwise
    fix_utc_ms: np.ndarray  # (K,) UTC of each epoch, ms since 1970
    origin: tuple[float, float, float]  # the first fix: lat, lon deg, h m
    truth: PoseTruth

    @property
    def rate_hz(self) -> float:
        return (len(self.t) - 1) / float(self.t[-1] - self.t[0])


def _stream(folder: Path, *parts: str) -> tuple[np.ndarray, np.ndarray]:
    where = folder.joinpath("processed_log", *parts)
    return np.load(where / "t"), np.load(where / "value")


def load_car(folder: Path | None = None) -> CarRecording:
    """Read the recording; times in s from the first IMU sample."""
    folder = Path(folder) if folder is not None else default_car_dir()
    t, accel = _stream(folder, "IMU", "accelerometer")
    t_gyro, gyro = _stream(folder, "IMU", "gyro_uncalibrated")
    if len(t_gyro) != len(t) or np.max(np.abs(t_gyro - t)) > 1e-6:
        raise ValueError(f"{folder}: the accelerometer and gyro streams are not sampled together")
    t0 = float(t[0])
    can_t, can = _stream(folder, "CAN", "speed")
    fix_t, fixes = _stream(folder, "GNSS", "live_gnss_ublox")
    origin = (float(fixes[0, 0]), float(fixes[0, 1]), float(fixes[0, 4]))
    fix_enu = geodetic_to_enu(fixes[:, 0], fixes[:, 1], fixes[:, 4], origin)
    pose = folder / "global_pose"
    pose_t = np.load(pose / "frame_times")
    lat, lon, h = ecef_to_geodetic(np.load(pose / "frame_positions"))
    rot = ecef_to_enu_rotation(origin[0], origin[1])
    truth = PoseTruth(pose_t - t0, geodetic_to_enu(lat, lon, h, origin), np.load(pose / "frame_velocities") @ rot.T)
    return CarRecording(t - t0, accel, gyro, can_t - t0, can[:, 0], fix_t - t0, fix_enu, fixes[:, 2],
                        fixes[:, 5] % 360.0, np.round(fixes[:, 3]).astype(np.int64), origin, truth)


def device_imu(car: CarRecording, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The recording as a device at rate_hz would read it: the IMU linearly interpolated to read times every
    1 / rate_hz s (the recording holds nothing above its ~52 Hz Nyquist frequency, where the MPU-6050's DLPF of
    44 Hz would cut anyway), turned from forward-right-down to forward-left-up (the board frame of a device lying
    flat, facing forward: +1 g up at rest). Returns (t s, specific force g (N, 3), rate rad/s (N, 3))."""
    t = np.arange(0.0, float(car.t[-1]), 1.0 / rate_hz)
    flip = np.array([1.0, -1.0, -1.0])
    accel = np.stack([np.interp(t, car.t, car.accel[:, i]) for i in range(3)], axis=-1) * flip
    gyro = np.stack([np.interp(t, car.t, car.gyro[:, i]) for i in range(3)], axis=-1) * flip
    return t, accel / STANDARD_GRAVITY, gyro


def device_fixes(car: CarRecording, rate_hz: float = 1.0):
    """The u-blox epochs a receiver at rate_hz (1 Hz: the NEO-6M's default) would report: those on whole multiples
    of 1 / rate_hz s of UTC (the stream's stamps sit a millisecond before its 100 ms marks: rounded to them first; a
    whole second whose epoch the stream lacks has no fix). Returns a codegen.sim.neo6m.GpsTrack in the recording's
    ENU frame (its velocity from the Doppler speed and course; no climb rate in this stream)."""
    period_ms = int(round(1000.0 / rate_hz))
    keep = np.flatnonzero(np.round(car.fix_utc_ms / 100.0).astype(np.int64) * 100 % period_ms == 0)
    speed, course = car.fix_speed[keep], car.fix_course[keep]
    c = np.radians(course)
    vel = np.stack([speed * np.sin(c), speed * np.cos(c), np.zeros(len(keep))], axis=-1)
    lat, lon, alt = enu_to_geodetic(car.fix_enu[keep], car.origin)
    epoch = _dt.datetime.fromtimestamp(car.fix_utc_ms[keep[0]] / 1000.0, _dt.timezone.utc)
    t = car.fix_t[keep]
    epoch -= _dt.timedelta(seconds=float(t[0]))
    return GpsTrack(t, np.ones(len(keep), dtype=bool), car.fix_enu[keep], vel, lat, lon, alt, speed,
                    np.where(speed >= COURSE_MIN_SPEED, course, np.nan), np.zeros(len(keep), dtype=int),
                    np.full(len(keep), np.nan), car.origin, epoch)
