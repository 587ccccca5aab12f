"""Orientation from the gyro's integral, turned onto ENU by the GPS: for a device that does not sit rigidly.

The whole-run mounting (orientation.fit_mounting) takes the device to be fixed in a frame that follows the track.
A device in a hand wanders about that frame (degrees of tilt over seconds) and lets gravity into the horizontal
accelerations by g times the wander; one GPS interval per second cannot follow it, so the rigid fit leaves a chi2 of
tens and its bias and angles soak up the wander. The gyro follows it. With G(t) the gyro's integral (sensor -> a
frame fixed when the log starts, the gyro's bias removed), the device's orientation is R(t) = O(t) G(t), where the
offset O turns the gyro's frame onto ENU and changes only as fast as the gyro's remaining error drifts it. So per GPS
interval k, with the accelerometer bias b in the sensor frame:

    O(t_k) mean_k(G (a - b)) = A_k + g z           A_k the GPS acceleration, as in orientation.py

O is solved over windows of `WINDOW` s (per-axis weighted least squares, each axis by its GPS velocities' 1-sigma,
so a climb rate from GGA altitudes does not outvote the Doppler) and Slerped between their centres; b, which enters
linearly, by least squares given O; the two alternately. A body-fixed bias is told from a tilt of O by the device's
turns (the bias turns with the device, O does not), which a rigid fit cannot do: there a tilt and a bias are both
fixed in the vehicle.

The gyro's bias comes first, from the log's quietest stands under GPS (GPS speed below STILL_GPS_SPEED; the epochs
whose gyro varies over STILL_WINDOW at most `QUIET_FACTOR` times as much as at the quietest one: a hand at a crossing
still turns the device by tenths of a degree per second, a table does not, and one such epoch among a few quiet ones
moves a median by as much). Without a stand under GPS there is no gyro frame: the rigid fit stands (and where the
quietest stand was a hand's, the gyro frame fails the chi2 test the rigid fit failed, and is not used).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation, Slerp

from codegen.board.model import STANDARD_GRAVITY
from codegen.post.orientation import (
    UP,
    Intervals,
    Mounting,
    cumulative_integral,
    interval_means,
    rot_grade,
    rot_z,
)
from codegen.post.stands import STILL_GPS_SPEED, STILL_WINDOW

WINDOW = 120.0  # s: each offset O is solved from the intervals within half of this of its centre (triangle weight)
QUIET_FACTOR = 3.0  # stand epochs whose gyro varies at most this many times the quietest one's teach its bias
MIN_QUIET_EPOCHS = 1
MIN_WINDOW_SAMPLES = 10  # IMU samples a stand epoch's window needs
MIN_WINDOW_INTERVALS = 10  # usable intervals a window needs to fix its offset
BIAS_ITERATIONS = 20
BIAS_TOLERANCE = 1e-5  # m/s^2: the alternation stops when the bias moves less than this
DOPPLER_FLOOR = 0.01  # m/s, added in quadrature to each velocity's 1-sigma (a perfect GPS would weigh infinitely)


def gyro_bias_at_stands(t: np.ndarray, gyro: np.ndarray, gps_t: np.ndarray,
                        gps_vel: np.ndarray) -> Optional[tuple[np.ndarray, int]]:
    """(gyro bias rad/s in the sensor frame, epochs it came from): the median of the gyro's mean over STILL_WINDOW
    at the quiet stand epochs, or None where the run has fewer than MIN_QUIET_EPOCHS of them."""
    speed = np.hypot(gps_vel[:, 0], gps_vel[:, 1])
    stand_t = gps_t[speed < STILL_GPS_SPEED]
    lo = np.searchsorted(t, stand_t - 0.5 * STILL_WINDOW)
    hi = np.searchsorted(t, stand_t + 0.5 * STILL_WINDOW)
    full = hi - lo >= MIN_WINDOW_SAMPLES  # a window the log's start or end cuts is still a stand's
    if full.sum() < MIN_QUIET_EPOCHS:
        return None
    means = np.array([gyro[a:b].mean(axis=0) for a, b in zip(lo[full], hi[full])])
    spread = np.array([np.linalg.norm(gyro[a:b].std(axis=0)) for a, b in zip(lo[full], hi[full])])
    quiet = spread <= QUIET_FACTOR * spread.min()
    if quiet.sum() < MIN_QUIET_EPOCHS:
        return None
    return np.median(means[quiet], axis=0), int(quiet.sum())


def gyro_integral(t: np.ndarray, rate: np.ndarray) -> Rotation:
    """G at each sample time (identity at the first): the rate over each step the mean of the samples at its ends."""
    half = 0.5 * (rate[1:] + rate[:-1]) * np.diff(t)[:, None]
    steps = Rotation.from_rotvec(half).as_quat()
    quats = np.empty((len(t), 4))
    x, y, z, w = 0.0, 0.0, 0.0, 1.0
    quats[0] = (x, y, z, w)
    for k, (x2, y2, z2, w2) in enumerate(steps, start=1):  # q = q * step, scalar-last (scipy's order)
        x, y, z, w = (w * x2 + x * w2 + y * z2 - z * y2, w * y2 - x * z2 + y * w2 + z * x2,
                      w * z2 + x * y2 - y * x2 + z * w2, w * w2 - x * x2 - y * y2 - z * z2)
        quats[k] = (x, y, z, w)
    return Rotation.from_quat(quats)


@dataclass
class GyroFrame:
    t: np.ndarray  # (N,) s, the IMU sample times it was built on
    integral: Rotation  # G at t
    centres: np.ndarray  # s, the windows' centres
    offsets: Rotation  # O at the centres
    gyro_bias: np.ndarray  # (3,) rad/s, sensor frame, removed before integrating
    bias: np.ndarray  # (3,) m/s^2, accelerometer bias, sensor frame
    sigma_bias: np.ndarray  # (3,) m/s^2, 1-sigma (scaled by chi2 where above 1)
    chi2: float  # reduced chi-square of the per-axis weighted fit
    used: int  # intervals fitted
    quiet_epochs: int  # stand epochs the gyro's bias came from
    yaw_sigma: float  # rad: 1-sigma of one offset's yaw from all the GPS intervals, 1 / sqrt(sum |A_h|^2 / sigma_h^2)
    _offset: Optional[Slerp] = field(default=None, repr=False)  # built on first use
    _integral: Optional[Slerp] = field(default=None, repr=False)

    def offset(self, at: np.ndarray) -> Rotation:
        if self._offset is None:
            self._offset = Slerp(self.centres, self.offsets)
        return self._offset(np.clip(at, self.centres[0], self.centres[-1]))

    def rotation(self) -> Rotation:
        """Sensor -> ENU at each of `t`."""
        return self.offset(self.t) * self.integral

    def rotation_at(self, at: np.ndarray) -> Rotation:
        """Sensor -> ENU at times `at` within `t` (the integral Slerped between its samples)."""
        at = np.clip(np.asarray(at, dtype=float), self.t[0], self.t[-1])
        if self._integral is None:
            self._integral = Slerp(self.t, self.integral)
        return self.offset(at) * self._integral(at)

    def enu(self, acc: np.ndarray) -> np.ndarray:
        """(N,3) m/s^2: the accelerations at `t`, bias removed, in ENU, gravity removed."""
        return self.rotation().apply(acc - self.bias) - STANDARD_GRAVITY * UP

    def mounting(self, iv: Intervals, min_speed: float) -> Optional[Mounting]:
        """The device's mean orientation in the vehicle frame (Rz(track) Ry(grade), as fit_mounting's) over the
        samples where the track is faster than `min_speed`, as a Mounting with this frame's bias. Its 1-sigma: the
        device's wander about that mean over the root of the number of intervals (their errors taken as independent)
        and, for the yaw, also `yaw_sigma` (how well the GPS turns the frame about the vertical at all). None where
        nothing moves."""
        speed = np.hypot(*iv.track.velocity(self.t).T)
        fast = speed > min_speed
        if fast.sum() < 2:
            return None
        chi, _ = iv.track.yaw(self.t[fast])
        grade = np.interp(self.t[fast], iv.mid, iv.grade) if iv.grade is not None else np.zeros(fast.sum())
        frame = rot_z(chi) @ rot_grade(grade)
        carried = Rotation.from_matrix(np.transpose(frame, (0, 2, 1)) @ self.rotation()[fast].as_matrix())
        mean = carried.mean()
        spread = (carried * mean.inv()).as_rotvec()
        n = max(int(np.sum(iv.usable & iv.moving)), 1)
        sigma = np.sqrt(np.mean(spread**2, axis=0) / n)
        sigma[2] = np.hypot(sigma[2], self.yaw_sigma)
        zyx = mean.as_euler("ZYX")
        return Mounting(np.array([zyx[2], zyx[1], zyx[0]]), self.bias.copy(), sigma, self.sigma_bias.copy(),
                        self.chi2, self.used)


def fit_gyro_frame(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, iv: Intervals, gps_t: np.ndarray,
                   gps_vel: np.ndarray, gps_sigma_vel: np.ndarray) -> Optional[GyroFrame]:
    """The gyro frame on the IMU samples (t, acc, gyro) and the GPS intervals `iv` built on the same t; None where
    the gyro's bias cannot be learnt (no quiet stands) or too few intervals are usable."""
    found = gyro_bias_at_stands(t, gyro, gps_t, gps_vel)
    use = iv.usable
    if found is None or use.sum() < MIN_WINDOW_INTERVALS:
        return None
    gyro_bias, quiet = found
    integral = gyro_integral(t, gyro - gyro_bias)
    g = integral.as_matrix()
    nodes, cum = cumulative_integral(t, integral.apply(acc))
    mean_ga = interval_means(nodes, cum, iv.t0, iv.t1)  # (K,3) mean of G a
    mean_g = np.stack([interval_means(nodes, cumulative_integral(t, g[:, :, c])[1], iv.t0, iv.t1)
                       for c in range(3)], axis=2)  # (K,3,3) mean of G
    target = iv.gps_accel + STANDARD_GRAVITY * UP
    dt = (iv.t1 - iv.t0)[:, None]
    sigma = np.sqrt(gps_sigma_vel[:-1] ** 2 + gps_sigma_vel[1:] ** 2 + 2 * DOPPLER_FLOOR**2) / dt  # (K,3) m/s^2
    span = iv.t1[use][-1] - iv.t0[use][0]
    count = max(int(np.ceil(2.0 * span / WINDOW)), 1)
    centres = np.linspace(iv.mid[use][0], iv.mid[use][-1], count + 1) if count > 1 else iv.mid[use][[0, -1]]
    half = max(0.5 * WINDOW, 0.5 * float(np.diff(centres).max()) + 1.0)
    bias = np.zeros(3)
    offsets = None
    for _ in range(BIAS_ITERATIONS):
        m = mean_ga - np.einsum("kij,j->ki", mean_g, bias)
        solved = []
        for c in centres:
            w = use & (np.abs(iv.mid - c) <= half)
            if w.sum() < MIN_WINDOW_INTERVALS:
                w = use & (np.abs(iv.mid - c) <= np.sort(np.abs(iv.mid[use] - c))[MIN_WINDOW_INTERVALS - 1])
            scale = np.sqrt(np.clip(1.0 - np.abs(iv.mid[w] - c) / half, 0.05, 1.0))[:, None] / sigma[w]
            start = Rotation.align_vectors(target[w], m[w], weights=(scale[:, 0]) ** 2)[0]

            def residual(x, mw=m[w], tw=target[w], sw=scale):
                return ((Rotation.from_rotvec(x).apply(mw) - tw) * sw).ravel()

            solved.append(Rotation.from_rotvec(least_squares(residual, start.as_rotvec(), method="lm").x))
        offsets = Rotation.concatenate(solved)
        frame = GyroFrame(t, integral, centres, offsets, gyro_bias, bias, np.zeros(3), np.nan, int(use.sum()), quiet,
                          np.nan)
        o = frame.offset(iv.mid[use]).as_matrix()
        design = (np.einsum("kij,kjl->kil", o, mean_g[use]) / sigma[use][:, :, None]).reshape(-1, 3)
        rhs = ((np.einsum("kij,kj->ki", o, mean_ga[use]) - target[use]) / sigma[use]).ravel()
        new = np.linalg.lstsq(design, rhs, rcond=None)[0]
        moved = float(np.linalg.norm(new - bias))
        bias = new
        if moved < BIAS_TOLERANCE:
            break
    m = mean_ga - np.einsum("kij,j->ki", mean_g, bias)
    o = frame.offset(iv.mid[use]).as_matrix()
    res = (np.einsum("kij,kj->ki", o, m[use]) - target[use]) / sigma[use]
    dof = max(res.size - 3 * len(centres) - 3, 1)
    chi2 = float(np.sum(res**2) / dof)
    try:
        cov = np.linalg.inv(design.T @ design) * max(chi2, 1.0)
        sigma_bias = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sigma_bias = np.full(3, np.inf)
    # a yaw error d of the offset leaves |A_h| d in each interval's horizontal residual (the lower bound of one
    # offset over the whole run: the windows' own offsets are each worse, their mean about this)
    information = np.sum((iv.gps_accel[use, 0] ** 2 + iv.gps_accel[use, 1] ** 2)
                         / (0.5 * (sigma[use, 0] ** 2 + sigma[use, 1] ** 2)))
    yaw_sigma = float(1.0 / np.sqrt(information)) if information > 0 else float("inf")
    return GyroFrame(t, integral, centres, offsets, gyro_bias, bias, sigma_bias, chi2, int(use.sum()), quiet,
                     yaw_sigma)
