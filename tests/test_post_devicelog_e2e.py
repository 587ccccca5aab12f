"""`deadreckon post` on the app's own device log, end to end: the generated T-Beam app runs on the emulated board
(codegen/sim/mpsim) through a simulated drive and a simulated walk, fed by the MPU-6050 and NEO-6M models of a
trajectory with known truth, and writes its log (docs/log-format.md v2) across several part files; `post` reads
the run from them and is checked against that truth.

The truth of the delay is found record by record: each logged IMU record is the box mean of `log_every` of the
counts the emulated chip served, so matching the record against the box means of the served counts names the
samples it averages, and their truth times (on UTC: neo6m.DEFAULT_EPOCH + t), less the chip's low-pass filter's
delay (5.1 ms at the T-Beam's DLPF_CFG 3: what a sample holds happened that long before it was read), against the
record's time on `post`'s axis give the delay `post` should find. The mounting's truth is the board's rotation in
the vehicle frame `post` fits (along the track, pitched with its grade), with the accelerometer's own cross-axis
rotation.

Neither run sits rigidly enough for post's rigid mounting fit (its chi2: ~12 on the drive, where GGA climb rates
weighed as Doppler meet a tilt that a level-road fit cannot tell from a horizontal bias; ~36 on the walk, whose hand
tilts the device by ~6 deg RMS within seconds): post orients both with the gyro's integral turned onto ENU by the GPS
(codegen/post/gyroframe.py, chi2 ~1.1), and its mounting is the device's mean orientation along the track.
What is not reached yet is marked xfail (strict: the mark fails once it passes): the walk's mean mounting (1.8 deg
off here, 1.5-3.8 deg on tuning seeds 100-103, its yaw 1-sigma 2.2-2.6 deg: the GPS fixes the gyro frame's yaw through
a walker's small accelerations, 0.14 m/s^2 of Doppler noise per interval against a few tenths of turns and steps).
The drive's mounting within 1 deg is not reached either (strict xfail): 1.68 deg off here, 0.7-1.9 deg on the
seeds docs/post.md lists, in tilt: the MPU-6050 model's gyro cross-axis error, which 1 Hz GPS cannot see (docs/post.md,
`benchmarks/post.py device-matrices`). It passed at 0.91 deg on this seed's drive before the car's cruises wandered
with the traffic: a draw, not a result.
Runtime: about 25 s for the drive and 15 s for the walk (the app's run, then post), x86-64.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import polar
from scipy.spatial.transform import Rotation

from codegen.board.loader import load_board
from codegen.board.model import DLPF_BANDWIDTH_HZ
from codegen.post import PostOptions, process
from codegen.post.devicelog import parse_device_parts, read_device_log, run_parts, to_post_log
from codegen.post.geodesy import geodetic_to_enu
from codegen.post.orientation import euler_matrix, rot_grade, rot_z
from codegen.sim import mpu6050, neo6m, trajectory
from codegen.sim.onmicropython import record_on_micropython
from conftest import require_tool

BOARD = "ttgo-tbeam-v1.1"
DELAY_BOUND = 0.020  # s
MOUNTING_BOUND = 1.0  # deg
VELOCITY_RESIDUAL_BOUND = 0.15  # m/s RMS, horizontal: the synthetic acceptance's (tests/test_post.py)
EPOCH = neo6m.DEFAULT_EPOCH.timestamp()  # UTC of the trajectory's t = 0


class Posted:
    def __init__(self, scenario: str, duration: float, work, seed: int = 0, errors: mpu6050.MpuErrors | None = None):
        require_tool("micropython")  # what record_on_micropython runs: skips locally, fails under CI, without it
        self.seed = seed
        self.loaded = load_board(BOARD)
        self.traj = trajectory.make_scenario(scenario, seed=seed, duration=duration)
        self.rec = record_on_micropython(self.loaded, self.traj, seed=seed, work=work, errors=errors)
        files = sorted(self.rec.logs.glob("dr*.bin"))
        self.parts = run_parts(files[-1])
        self.raw = parse_device_parts(self.parts)
        self.log = to_post_log(self.raw)
        self.result = process(self.log, PostOptions(plots=False))

    def true_delay(self) -> tuple[float, float, float]:
        """(delay s, its spread s, share of records matched): the records' times on post's axis minus the truth
        times of the samples each averages."""
        n = int(self.raw.header["log_every"])
        cum = np.concatenate([np.zeros((1, 6), np.int64), np.cumsum(self.rec.counts.astype(np.int64), axis=0)])
        boxes = (cum[n:] - cum[:-n] + n // 2) // n  # the app's rounding; box j ends at sample j + n - 1
        last = {}
        for j, row in enumerate(map(tuple, boxes)):
            last[row] = -1 if row in last else j + n - 1  # a box seen twice (at rest) names no sample
        ends = np.array([last.get(tuple(r[1:]), -1) for r in self.raw.imu])
        found = ends >= 0
        truth_t = np.array([self.rec.t_us[k - n + 1:k + 1].mean() * 1e-6 for k in ends[found]])
        truth_t -= self.dlpf_delay()  # what a sample holds happened that much before it was read
        assert len(self.log.imu.t) == len(self.raw.imu)  # no record dropped: the times line up with the records
        lag = self.log.imu.t[found] - (EPOCH + truth_t)
        return float(np.median(lag)), float(np.ptp(lag)), float(found.mean())

    def dlpf_delay(self) -> float:
        """s: how far the chip's low-pass filter (DLPF_CFG) holds its samples back behind the motion (0 if off)."""
        if not self.rec.errors.dlpf or self.loaded.board.imu.dlpf not in DLPF_BANDWIDTH_HZ:
            return 0.0
        return mpu6050.dlpf_delay_s(DLPF_BANDWIDTH_HZ[self.loaded.board.imu.dlpf], self.traj.rate_hz)

    def true_mounting(self, min_speed: float) -> Rotation:
        """The board in post's vehicle frame (Rz(track) Ry(grade)), averaged where faster than min_speed, as the
        accelerometer's axes see it (its cross-axis matrix's rotation)."""
        v = self.traj.vel
        speed = np.hypot(v[:, 0], v[:, 1])
        idx = np.flatnonzero(speed > min_speed)[::50]
        frame = rot_z(np.arctan2(v[idx, 1], v[idx, 0])) @ rot_grade(np.arctan2(v[idx, 2], speed[idx]))
        return Rotation.from_matrix(np.transpose(frame, (0, 2, 1)) @ self.traj.rotation(idx) @ self.cross_axis()).mean()

    def cross_axis(self) -> np.ndarray:
        """The rotation of the accelerometer's cross-axis matrix, in the board frame post's log is in."""
        device = mpu6050.draw_device(self.rec.errors, np.random.default_rng(self.seed))  # as simulate_imu drew it
        remap = np.zeros((3, 3))
        for i, (src, sign) in enumerate(self.loaded.board.imu.axis_map):
            remap[src, i] = sign  # sensor = remap @ board
        return polar(np.linalg.inv(remap.T @ device.accel_matrix @ remap))[0]

    def attitude_error_deg(self, min_speed: float) -> np.ndarray:
        """Per logged IMU record where faster than min_speed: the angle (deg) between the orientation post rotated
        it with and the truth's at the record's true time."""
        truth, _, _ = self.true_delay()
        at = np.clip(np.searchsorted(self.traj.t, self.log.imu.t - truth - EPOCH), 0, len(self.traj.t) - 1)
        v = self.traj.vel[at]
        fast = np.hypot(v[:, 0], v[:, 1]) > min_speed
        true = Rotation.from_matrix(self.traj.rotation(at[fast]) @ self.cross_axis())
        post = self.result.gaps.rotation(self.result.imu_t[fast])  # what turned the smoother's accelerations
        return np.degrees((post * true.inv()).magnitude())

    def mounting_error_deg(self, min_speed: float) -> float:
        m = self.result.orientation.mounting
        assert m is not None
        fitted = Rotation.from_matrix(euler_matrix(*m.euler))
        return float(np.degrees((fitted.inv() * self.true_mounting(min_speed)).magnitude()))

    def path_errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal errors (m) of post's path and of the GPS fixes themselves, against the truth."""
        res = self.result
        offset = geodetic_to_enu(np.array([self.rec.gps.origin[0]]), np.array([self.rec.gps.origin[1]]),
                                 np.array([res.origin[2]]), res.origin)[0, :2]  # the truth's origin in post's frame
        t = res.track.t - EPOCH
        inside = (t > self.traj.t[0]) & (t < self.traj.t[-1]) & ~res.gaps.inside(res.track.t)
        path = res.track.pos[inside, :2] - (self.traj.at(t[inside])[:, :2] + offset)
        fixes = res.gps_enu[:, :2] - (self.traj.at(self.log.gps.t - EPOCH)[:, :2] + offset)
        return np.hypot(*path.T), np.hypot(*fixes.T)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    return Posted("car", 420.0, tmp_path_factory.mktemp("drive"))


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    return Posted("walk", 300.0, tmp_path_factory.mktemp("walk"))


def test_drive_log_is_one_run_read_from_its_parts(drive):
    assert len(drive.parts) >= 3  # the run rotated across files: post read them as one
    assert drive.raw.version == 2 and drive.raw.header["run"] == "1"
    assert len(read_device_log(drive.rec.logs).imu.t) == len(drive.log.imu.t)  # the folder: the same run
    t = np.array([r[0] for r in drive.raw.imu])
    step = np.diff(t)
    period = 1e6 * int(drive.raw.header["log_every"]) / float(drive.raw.header["imu_rate_hz"])
    assert np.all(step > 0) and np.median(step) == pytest.approx(period, rel=0.01)  # one clock through the parts
    assert drive.log.gps.t[-1] - drive.log.gps.t[0] > 400.0


def test_drive_delay_within_twenty_milliseconds(drive):
    truth, spread, matched = drive.true_delay()
    assert matched > 0.99 and spread < 1e-3
    assert drive.result.delay_estimate is not None
    assert abs(drive.result.delay - truth) <= DELAY_BOUND, (drive.result.delay, truth)


@pytest.mark.xfail(strict=True, reason="a drive: the gyro's cross-axis error (the MPU-6050 model's +-2 %) tilts the "
                   "gyro frame's mean mounting by 1.68 deg; 1 Hz GPS does not see it")
def test_drive_mounting_within_one_degree(drive):
    assert drive.mounting_error_deg(min_speed=2.0) <= MOUNTING_BOUND


def test_drive_path_within_the_acceptance_bounds(drive):
    res = drive.result
    horizontal = np.sqrt(np.nanmean(res.velocity_residual[:, :2] ** 2))
    assert horizontal <= VELOCITY_RESIDUAL_BOUND
    path, fixes = drive.path_errors()
    # the NEO-6M model's fixes carry metres of correlated error that no smoother removes: the path is held to be
    # no worse than the fixes it is drawn through, and within their 1-sigma (UERE 2.5 m x HDOP) everywhere
    assert np.sqrt(np.mean(path**2)) <= np.sqrt(np.mean(fixes**2)) + 0.1
    assert path.max() <= 2.0 * 2.5 * 1.2 + 1.0


def test_walk_log_is_one_run(walk):
    assert len(walk.parts) >= 2 and walk.raw.version == 2
    truth, spread, matched = walk.true_delay()
    assert matched > 0.99 and spread < 1e-3


def test_walk_delay_within_twenty_milliseconds(walk):
    truth, _, _ = walk.true_delay()
    assert abs(walk.result.delay - truth) <= DELAY_BOUND


@pytest.mark.xfail(strict=True, reason="a hand-held walk: the gyro frame's mean mounting is 1.8 deg off (its yaw is "
                   "fixed by a walker's small accelerations against the Doppler's noise)")
def test_walk_mounting_within_one_degree(walk):
    assert walk.mounting_error_deg(min_speed=0.5) <= MOUNTING_BOUND


def test_walk_path_within_the_acceptance_bounds(walk):
    horizontal = np.sqrt(np.nanmean(walk.result.velocity_residual[:, :2] ** 2))
    assert horizontal <= VELOCITY_RESIDUAL_BOUND
