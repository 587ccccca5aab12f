"""The gyro frame (codegen/post/gyroframe.py) from physics: a device that wanders in the vehicle by degrees within
seconds (as a hand does), with an MPU-6050's gyro offset (tens of deg/s, not calibrated) and accelerometer bias;
its orientation, both biases and the run's delay are known. A rigidly mounted device keeps the rigid fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from codegen.board.model import STANDARD_GRAVITY
from codegen.post import PostOptions, process
from codegen.post.gyroframe import fit_gyro_frame, gyro_bias_at_stands, gyro_integral
from codegen.post.model import ImuSeries, PostLog
from codegen.post.orientation import build_intervals, euler_matrix, fit_mounting
from codegen.post.synthetic import MPU6050_GYRO_NOISE_DENSITY, MPU6050_NOISE_DENSITY, Scenario, make_run

GYRO_BIAS = np.radians([-19.3, 12.5, 16.5])  # rad/s: an uncalibrated MPU-6050's offset
ACC_BIAS = np.array([0.13, -0.23, -0.72])  # m/s^2, sensor frame
STOPS = ((10.0, 40.0), (300.0, 320.0))  # s: the vehicle stands (and the device with it: no wander there)
DELAY = 0.080  # s


def _wander(t: np.ndarray, factor: np.ndarray) -> Rotation:
    """The device's turn in the vehicle frame: up to ~8 deg about each axis, periods of 3-11 s, none while standing."""
    rotvec = np.stack([np.radians(5.0) * np.sin(2 * np.pi * t / 3.1) + np.radians(3.0) * np.sin(2 * np.pi * t / 7.7),
                       np.radians(6.0) * np.sin(2 * np.pi * t / 4.3 + 1.0),
                       np.radians(8.0) * np.sin(2 * np.pi * t / 10.9 + 2.0)], axis=1)
    return Rotation.from_rotvec(rotvec * factor[:, None])


@pytest.fixture(scope="module")
def wandering():
    """(log, truth attitude at the IMU's true sample times, true sample times): the synthetic vehicle run with the
    device wandering in it; specific force and gyro rates from that attitude, noise as an MPU-6050's."""
    log, truth = make_run(Scenario(duration=420.0, stops=STOPS, seed=3))
    t = np.arange(0.0, 420.0, 1.0 / 50.0)
    fine_dt = 1e-3

    def attitude(at):
        yaw, _ = truth._heading(at)
        return Rotation.from_euler("z", yaw[:, None]) * _wander(at, truth._stopped(at)[0]) * truth.mounting

    r0, r1 = attitude(t - 0.5 * fine_dt), attitude(t + 0.5 * fine_dt)
    rate = (r0.inv() * r1).as_rotvec() / fine_dt  # body rate, sensor frame
    r = attitude(t)
    rng = np.random.default_rng(7)
    f = r.inv().apply(truth.acceleration(t) + [0.0, 0.0, STANDARD_GRAVITY]) + ACC_BIAS
    f += rng.normal(0.0, MPU6050_NOISE_DENSITY * np.sqrt(25.0), f.shape)
    gyro = rate + GYRO_BIAS + rng.normal(0.0, MPU6050_GYRO_NOISE_DENSITY * np.sqrt(25.0), rate.shape)
    return PostLog("wandering", ImuSeries(t + DELAY, f, gyro), log.gps), r, t


def test_the_gyro_bias_comes_from_the_stands(wandering):
    log, _, t = wandering
    bias, epochs = gyro_bias_at_stands(t, log.imu.gyro, log.gps.t, log.gps.vel)
    assert epochs >= 10
    assert np.degrees(np.abs(bias - GYRO_BIAS)).max() < 0.02


def test_gyro_integral_turns_as_the_rates_say():
    t = np.arange(0.0, 10.0, 0.02)
    rate = np.tile(np.radians([0.0, 0.0, 9.0]), (len(t), 1))  # 9 deg/s about z
    g = gyro_integral(t, rate)
    assert np.degrees(g[-1].magnitude()) == pytest.approx(9.0 * t[-1], rel=1e-9)
    assert np.allclose(g[-1].as_rotvec()[:2], 0.0)


def test_the_frame_follows_the_wander_and_finds_the_accelerometer_bias(wandering):
    log, attitude, t = wandering
    gps = log.gps
    iv = build_intervals(t, log.imu.acc, gps.t, gps.vel, gps.sigma_vel, 0.5)
    rigid = fit_mounting(iv, True, 0.05 * STANDARD_GRAVITY, 2.0)
    assert rigid.chi2 > 9.0  # the case the frame is for: the rigid model fits poorly (OrientationOptions.poor_fit_chi2)
    frame = fit_gyro_frame(t, log.imu.acc, log.imu.gyro, iv, gps.t, gps.vel, gps.sigma_vel)
    assert frame is not None and frame.chi2 < 2.0
    assert np.abs(frame.bias - ACC_BIAS).max() < 0.03
    moving = np.hypot(*iv.track.velocity(t).T) > 0.5
    error = np.degrees((frame.rotation() * attitude.inv()).magnitude())[moving]
    assert np.median(error) < 0.5 and np.percentile(error, 95) < 1.0
    # the wander's ~8 deg are followed: the rigid track frame is off by that much
    enu = frame.enu(log.imu.acc)
    true_enu = attitude.apply(log.imu.acc - ACC_BIAS) - [0.0, 0.0, STANDARD_GRAVITY]
    assert np.sqrt(np.mean((enu - true_enu)[moving, :2] ** 2)) < 0.1


def test_post_uses_the_frame_for_a_wandering_device(wandering):
    log, attitude, t = wandering
    result = process(log, PostOptions(plots=False))
    assert result.gyro_frame is not None
    assert any("does not sit rigidly" in note for note in result.notes)
    assert abs(result.delay - DELAY) < 0.010
    m = result.orientation.mounting
    assert not m.bias_rejected and np.abs(m.bias - ACC_BIAS).max() < 0.03
    # the mounting is the device's mean orientation in the track frame: the wander's mean, which is the mounting
    # itself here (sinusoids over whole periods average to little)
    _, truth = make_run(Scenario(duration=420.0, stops=STOPS, seed=3))
    fitted = Rotation.from_matrix(euler_matrix(*m.euler))
    assert np.degrees((fitted.inv() * truth.mounting).magnitude()) < 1.0
    assert np.sqrt(np.nanmean(result.velocity_residual[:, :2] ** 2)) < 0.15


def test_a_rigid_device_keeps_the_rigid_fit():
    log, truth = make_run(Scenario(duration=420.0, stops=STOPS, seed=3))
    result = process(log, PostOptions(plots=False))
    assert result.gyro_frame is None
    assert result.orientation.mounting.chi2 < 2.0
