"""Synthetic runs with known mounting, motion, bias, noise and delay: post's acceptance scenarios.

A vehicle drives on flat ground with smooth speed changes and turns (sums of sinusoids, so every derivative is
exact). The device is fixed in it at a known mounting. The IMU reads specific force in the sensor frame with a
constant bias, MPU-6050-like white noise, int16 quantisation at +-2 g, and timestamps late by `delay`; the gyro the
vehicle's turn rate with a constant bias (what a calibration at rest leaves), white noise and +-250 deg/s counts. The GPS gives
1 Hz epochs with Doppler velocity noise per ENU component and position noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from codegen.board.model import ACCEL_LSB_PER_G, STANDARD_GRAVITY
from codegen.post.geodesy import enu_to_geodetic
from codegen.post.model import GpsSeries, ImuSeries, PostLog

MPU6050_NOISE_DENSITY = 400e-6 * STANDARD_GRAVITY  # m/s^2/sqrt(Hz), datasheet 400 ug/sqrt(Hz)
MPU6050_GYRO_NOISE_DENSITY = np.radians(0.005)  # rad/s/sqrt(Hz), datasheet 0.005 deg/s/sqrt(Hz)
MPU6050_GYRO_LSB_PER_DPS = 131.0  # +-250 deg/s range
ORIGIN = (47.3769, 8.5417, 408.0)  # lat, lon, h of the start
STOP_RAMP = 6.0  # s, the vehicle slows to a stop (and pulls away) over this long


@dataclass
class Scenario:
    duration: float = 600.0  # s
    imu_rate: float = 50.0  # Hz
    gps_rate: float = 1.0  # Hz
    mounting_deg: tuple[float, float, float] = (4.0, -3.0, 25.0)  # roll, pitch, yaw relative to the vehicle
    bias_mg: tuple[float, float, float] = (30.0, -35.0, 20.0)  # |b| = 50 mg
    doppler_sigma: float = 0.1  # m/s per ENU component
    position_sigma: float = 2.0  # m per horizontal component
    delay: float = 0.0  # s, IMU timestamps late by this much
    quantise: bool = True
    seed: int = 1
    gyro_bias_dps: tuple[float, float, float] = (0.4, -0.7, 0.3)  # deg/s, left after a calibration at rest
    stops: tuple[tuple[float, float], ...] = ()  # (start, end) s where the vehicle stands (speed ramps to 0 before)


@dataclass
class Truth:
    scenario: Scenario
    mounting: Rotation

    def _stopped(self, t):
        """(w, dw): the factor on the speed (1 moving, 0 standing; a raised-cosine ramp of `STOP_RAMP` before and
        after each stop) and its time derivative."""
        t = np.asarray(t, dtype=float)
        w, dw = np.ones_like(t), np.zeros_like(t)
        for t0, t1 in self.scenario.stops:
            for edge, sign in ((t0, -1.0), (t1, 1.0)):
                # down over [t0 - ramp, t0], up over [t1, t1 + ramp]
                u = (t - (edge - STOP_RAMP if sign < 0 else edge)) / STOP_RAMP
                inside = (u > 0.0) & (u < 1.0)
                ramp = 0.5 - 0.5 * sign * np.cos(np.pi * u)  # sign<0: 1 -> 0, sign>0: 0 -> 1
                d = 0.5 * sign * np.pi / STOP_RAMP * np.sin(np.pi * u)
                dw = np.where(inside, dw * ramp + w * d, dw)
                w = np.where(inside, w * ramp, w)
            standing = (t >= t0) & (t <= t1)
            w, dw = np.where(standing, 0.0, w), np.where(standing, 0.0, dw)
        return w, dw

    def _speed(self, t):
        if self.scenario.stops:
            s, ds = self._moving_speed(t)
            w, dw = self._stopped(t)
            return s * w, ds * w + s * dw
        return self._moving_speed(t)

    def _heading(self, t):
        """Heading (rad from East) and its rate: a vehicle does not turn while it stands, so with stops the heading is
        the integral of the moving rate times the speed factor."""
        if not self.scenario.stops:
            return self._moving_heading(t)
        t = np.asarray(t, dtype=float)
        fine = np.arange(0.0, self.scenario.duration + 2.0, 1e-3)
        _, dy_fine = self._moving_heading(fine)
        rate = dy_fine * self._stopped(fine)[0]
        y_fine = self._moving_heading(np.zeros(1))[0][0] + np.concatenate(
            [[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * 1e-3)])
        _, dy = self._moving_heading(t)
        return np.interp(t, fine, y_fine), dy * self._stopped(t)[0]

    def _moving_speed(self, t):
        s = 10.0 + 3.0 * np.sin(2 * np.pi * t / 23.0) + 2.0 * np.sin(2 * np.pi * t / 9.0 + 1.0) + 0.6 * np.sin(2 * np.pi * t / 4.1)
        ds = (3.0 * 2 * np.pi / 23.0 * np.cos(2 * np.pi * t / 23.0) + 2.0 * 2 * np.pi / 9.0 * np.cos(2 * np.pi * t / 9.0 + 1.0)
              + 0.6 * 2 * np.pi / 4.1 * np.cos(2 * np.pi * t / 4.1))
        return s, ds

    def _moving_heading(self, t):
        y = 1.2 * np.sin(2 * np.pi * t / 37.0) + 0.8 * np.sin(2 * np.pi * t / 13.0 + 0.5) + 0.02 * t
        dy = 1.2 * 2 * np.pi / 37.0 * np.cos(2 * np.pi * t / 37.0) + 0.8 * 2 * np.pi / 13.0 * np.cos(2 * np.pi * t / 13.0 + 0.5) + 0.02
        return y, dy

    def velocity(self, t):
        s, _ = self._speed(t)
        y, _ = self._heading(t)
        return np.stack([s * np.cos(y), s * np.sin(y), np.zeros_like(t)], axis=-1)

    def acceleration(self, t):
        s, ds = self._speed(t)
        y, dy = self._heading(t)
        return np.stack([ds * np.cos(y) - s * dy * np.sin(y), ds * np.sin(y) + s * dy * np.cos(y), np.zeros_like(t)], axis=-1)

    def position(self, t):
        fine = np.arange(0.0, self.scenario.duration + 2.0, 1e-3)
        v = self.velocity(fine)
        p = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (v[1:] + v[:-1]) * 1e-3, axis=0)])
        return np.stack([np.interp(t, fine, p[:, i]) for i in range(3)], axis=-1)

    def attitude(self, t) -> Rotation:
        """Sensor -> ENU at time t."""
        y, _ = self._heading(np.atleast_1d(t))
        return Rotation.from_euler("z", y[:, None]) * self.mounting

    def rate(self, t) -> np.ndarray:
        """(K,3) angular velocity in the sensor frame, rad/s: the vehicle's yaw rate about ENU up, seen by the mount."""
        _, dy = self._heading(np.atleast_1d(t))
        return self.mounting.inv().apply(np.stack([np.zeros_like(dy), np.zeros_like(dy), dy], axis=-1))

    def euler(self, t) -> np.ndarray:
        """(K,3) roll, pitch, yaw of the sensor in the convention of codegen.post.orientation."""
        zyx = self.attitude(t).as_euler("ZYX")
        return np.stack([zyx[:, 2], zyx[:, 1], zyx[:, 0]], axis=1)


def make_run(scenario: Scenario = Scenario()) -> tuple[PostLog, Truth]:
    rng = np.random.default_rng(scenario.seed)
    m = scenario.mounting_deg
    truth = Truth(scenario, Rotation.from_euler("ZYX", [m[2], m[1], m[0]], degrees=True))
    # IMU
    t_true = np.arange(0.0, scenario.duration, 1.0 / scenario.imu_rate)
    f_enu = truth.acceleration(t_true) + STANDARD_GRAVITY * np.array([0.0, 0.0, 1.0])
    f_sensor = truth.attitude(t_true).inv().apply(f_enu)
    f_sensor += np.array(scenario.bias_mg) * 1e-3 * STANDARD_GRAVITY
    f_sensor += rng.normal(0.0, MPU6050_NOISE_DENSITY * np.sqrt(scenario.imu_rate / 2), f_sensor.shape)
    if scenario.quantise:
        lsb = STANDARD_GRAVITY / ACCEL_LSB_PER_G[2]
        f_sensor = np.clip(np.round(f_sensor / lsb), -32768, 32767) * lsb
    # gyro from its own random stream, so adding it left every other draw of a seed as it was
    gyro_rng = np.random.default_rng([scenario.seed, 1])
    gyro = truth.rate(t_true) + np.radians(np.array(scenario.gyro_bias_dps))
    gyro += gyro_rng.normal(0.0, MPU6050_GYRO_NOISE_DENSITY * np.sqrt(scenario.imu_rate / 2), gyro.shape)
    if scenario.quantise:
        lsb = np.radians(1.0 / MPU6050_GYRO_LSB_PER_DPS)
        gyro = np.clip(np.round(gyro / lsb), -32768, 32767) * lsb
    imu = ImuSeries(t_true + scenario.delay, f_sensor, gyro)
    # GPS, epochs inside the IMU span
    t_gps = np.arange(1.0, scenario.duration - 1.0, 1.0 / scenario.gps_rate)
    vel = truth.velocity(t_gps) + rng.normal(0.0, scenario.doppler_sigma, (len(t_gps), 3))
    pos = truth.position(t_gps)
    pos[:, :2] += rng.normal(0.0, scenario.position_sigma, (len(t_gps), 2))
    lat, lon, h = enu_to_geodetic(pos, ORIGIN)
    k = len(t_gps)
    gps = GpsSeries(t_gps, lat, lon, np.full(k, np.nan), vel, np.full((k, 3), scenario.doppler_sigma),
                    np.tile([scenario.position_sigma, scenario.position_sigma, np.nan], (k, 1)), np.zeros(k, dtype=int))
    return PostLog("synthetic", imu, gps), truth


def write_csv_pair(log: PostLog, folder: Path) -> tuple[Path, Path]:
    """Write a run in the plain CSV pair format (what `deadreckon post imu.csv --gps gps.csv` reads)."""
    folder.mkdir(parents=True, exist_ok=True)
    imu_path, gps_path = folder / "imu.csv", folder / "gps.csv"
    acc_g = log.imu.acc / STANDARD_GRAVITY
    with imu_path.open("w") as f:
        if log.imu.gyro is None:
            f.write("t,ax,ay,az\n")
            for t, a in zip(log.imu.t, acc_g):
                f.write(f"{t:.4f},{a[0]:.6f},{a[1]:.6f},{a[2]:.6f}\n")
        else:
            f.write("t,ax,ay,az,gx,gy,gz\n")
            for t, a, w in zip(log.imu.t, acc_g, np.degrees(log.imu.gyro)):
                f.write(f"{t:.4f},{a[0]:.6f},{a[1]:.6f},{a[2]:.6f},{w[0]:.5f},{w[1]:.5f},{w[2]:.5f}\n")
    v = log.gps.vel
    sog = np.hypot(v[:, 0], v[:, 1])
    cog = np.degrees(np.arctan2(v[:, 0], v[:, 1])) % 360.0
    with gps_path.open("w") as f:
        f.write("t,lat,lon,sog,cog,climb\n")
        for i in range(len(log.gps)):
            f.write(f"{log.gps.t[i]:.3f},{log.gps.lat[i]:.8f},{log.gps.lon[i]:.8f},{sog[i]:.4f},{cog[i]:.4f},{v[i, 2]:.4f}\n")
    return imu_path, gps_path
