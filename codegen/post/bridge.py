"""GPS gaps: where epochs are missing, the orientation the IMU is turned with there, and how uncertain it is.

Outside gaps the orientation is the Slerp between solved GPS intervals (one every epoch). Across a gap there is no
solved interval, so:

- with a gyro, the orientation is the gyro's integral started at the last solved interval before the gap, and turned
  back, in proportion to the time elapsed, by the rotation that separates the integral's end from the first solved
  interval after the gap (a constant gyro bias is removed exactly, to first order, like a cubic Hermite bridge
  removes a constant accelerometer bias);
- without one, the Slerp from the orientation before to the one after: right while the device does not turn, wrong
  by however much it turned in between.

Either way an angle error grows away from the two ends. `GapModel` says how fast, from the run itself: the RMS rate
at which the solved yaw and tilt change from one GPS interval to the next (no gyro), or the gyro noise (gyro). A yaw
error psi turns the horizontal acceleration (mean cos psi, so the input is shrunk by E[cos psi] = exp(-sigma^2 / 2),
the rest is noise); a tilt error theta lets g theta of gravity into the horizontal. The smoother adds that noise
over the gap, so the reported 1-sigma grows where the accelerations are uncertain, and where they say nothing the
bridge falls back to the smooth curve between the two ends (the cubic Hermite bridge of GPS positions and velocity).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from codegen.board.model import STANDARD_GRAVITY
from codegen.post.orientation import cumulative_integral

GAP_EPOCH_FACTOR = 1.5  # an interval this many typical epoch intervals long has at least one epoch missing
GYRO_NOISE_DENSITY = np.radians(0.005)  # rad/s/sqrt(Hz), MPU-6050 datasheet rate noise spectral density
GYRO_BIAS_WINDOW = 5.0  # s, stretches over which the gyro's turn is compared with the solved orientation's
ALIGN_WINDOW = 5.0  # s before and after a gap whose solved orientations the gyro's integral is aligned to
CORRELATION_FRACTION = 0.35  # the angle errors of a gap stay correlated over this fraction of its length
MAX_ANGLE_SIGMA = np.pi  # rad: beyond this an angle is simply unknown


@dataclass
class Gap:
    """Missing GPS epochs between two epochs that are there: t0 (the last before) and t1 (the first after)."""

    index: int  # GPS epoch index of t0
    t0: float
    t1: float
    missing: int  # epochs missing at the typical rate

    @property
    def length(self) -> float:
        return self.t1 - self.t0


def find_gaps(gps_t: np.ndarray, factor: float = GAP_EPOCH_FACTOR) -> list[Gap]:
    """Intervals longer than `factor` typical (median) epoch intervals: at least one epoch is missing there."""
    if len(gps_t) < 2:
        return []
    step = np.diff(gps_t)
    typical = float(np.median(step))
    return [Gap(int(k), float(gps_t[k]), float(gps_t[k + 1]), int(round(step[k] / typical)) - 1)
            for k in np.flatnonzero(step > factor * typical)]


def hermite_bridge(t: np.ndarray, t0: float, p0: np.ndarray, v0: np.ndarray, t1: float, p1: np.ndarray,
                   v1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cubic through positions p0, p1 (m) with velocities v0, v1 (m/s) at t0, t1 (s): positions and velocities
    at t. The GPS-only bridge of a gap, and the minimum-acceleration path between the two ends."""
    h = t1 - t0
    s = ((np.asarray(t, dtype=float) - t0) / h)[:, None]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    d00, d10, d01, d11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
    pos = h00 * p0 + h10 * h * v0 + h01 * p1 + h11 * h * v1
    vel = (d00 * p0 + d01 * p1) / h + d10 * v0 + d11 * v1
    return pos, vel


@dataclass
class Span:
    """Stretch between two solved intervals' midpoints (a, b) that a GPS gap lies in."""

    gap: Gap
    a: float
    b: float
    gyro: bool  # orientation from the gyro (else Slerp)
    rotation: Optional[Callable[[np.ndarray], Rotation]] = None
    end_sigma: Optional[np.ndarray] = None  # (3,) rad, roll/pitch/yaw 1-sigma at the ends (else the model's)
    aligned: str = "both"  # which ends the gyro's integral is aligned at: "both", "before" or "after" (a stand)
    bridged: float = 0.0  # s between the solved intervals around the gap itself (a and b before reaching over stands)


@dataclass
class GapModel:
    """The orientation to turn the accelerations with, and its uncertainty, with GPS gaps bridged."""

    slerp: Callable[[np.ndarray], Rotation]
    spans: list[Span]
    yaw_rate: float  # rad/sqrt(s): random-walk rate of the yaw between solved intervals (see angle_sigma)
    tilt_rate: float  # rad/sqrt(s), of the tilt
    end_sigma: np.ndarray  # (3,) rad, typical 1-sigma of a solved interval's roll, pitch, yaw
    bias_sigma: float = 0.0  # m/s^2, 1-sigma per axis of the accelerometer bias left after its removal
    gyro_bias: Optional[np.ndarray] = None  # (3,) rad/s, sensor frame, removed before integrating
    notes: list[str] = field(default_factory=list)

    def rotation(self, t: np.ndarray) -> Rotation:
        t = np.asarray(t, dtype=float)
        rot = self.slerp(t)
        quat = rot.as_quat()
        for span in self.spans:
            if span.rotation is None:
                continue
            sel = (t > span.a) & (t < span.b)
            if sel.any():
                quat[sel] = span.rotation(t[sel]).as_quat()
        return Rotation.from_quat(quat)

    def angle_sigma(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(yaw, tilt) 1-sigma in rad at t: the solved intervals' own 1-sigma, and inside a gap's span a random-walk
        bridge between its two ends, of the gyro's rate noise (gyro) or of the angles' own rate of change (Slerp)."""
        t = np.asarray(t, dtype=float)
        yaw = np.full(len(t), self.end_sigma[2])
        tilt = np.full(len(t), float(np.hypot(self.end_sigma[0], self.end_sigma[1])))
        for span in self.spans:
            sel = (t > span.a) & (t < span.b)
            if not sel.any():
                continue
            if span.end_sigma is not None:
                yaw[sel] = span.end_sigma[2]
                tilt[sel] = np.hypot(span.end_sigma[0], span.end_sigma[1])
            d0, d1 = t[sel] - span.a, span.b - t[sel]
            if span.gyro:
                # Brownian bridge of the rate noise between two aligned ends, sqrt(s); a random walk from the one
                # aligned end when the other is a stand (its yaw is not solved)
                grow = {"both": np.sqrt(d0 * d1 / (span.b - span.a)), "before": np.sqrt(d0),
                        "after": np.sqrt(d1)}[span.aligned]
                yaw[sel] = np.hypot(yaw[sel], GYRO_NOISE_DENSITY * grow)
                tilt[sel] = np.hypot(tilt[sel], GYRO_NOISE_DENSITY * grow)
            else:
                grow = np.sqrt(d0 * d1 / (span.b - span.a))
                yaw[sel] = np.hypot(yaw[sel], self.yaw_rate * grow)
                tilt[sel] = np.hypot(tilt[sel], self.tilt_rate * grow)
        return np.minimum(yaw, MAX_ANGLE_SIGMA), np.minimum(tilt, MAX_ANGLE_SIGMA)

    def inside(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        out = np.zeros(len(t), dtype=bool)
        for span in self.spans:
            out |= (t > span.a) & (t < span.b)
        return out

    def correlation_time(self, t: np.ndarray) -> np.ndarray:
        """s: how long an angle error at t stays the same (a fraction of the span's length; 0 outside spans)."""
        t = np.asarray(t, dtype=float)
        out = np.zeros(len(t))
        for span in self.spans:
            sel = (t > span.a) & (t < span.b)
            out[sel] = CORRELATION_FRACTION * (span.bridged or (span.b - span.a))  # a stand adds no GPS-less motion
        return out

    def enu(self, t: np.ndarray, acc: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """ENU accelerations without gravity (m/s^2): the sensor's, less `bias`, turned by `rotation`."""
        return self.rotation(t).apply(acc - bias) - np.array([0.0, 0.0, STANDARD_GRAVITY])

    def rotate(self, t: np.ndarray, acc: np.ndarray, bias: np.ndarray, misfit: Optional["ImuMisfit"] = None,
               floor: float = 0.0, gyro_misfit: Optional[Callable[[float], Optional[float]]] = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """ENU accelerations without gravity (m/s^2), the horizontal part shrunk inside the spans by E[cos yaw error],
        and the acceleration noise (m/s^2/sqrt(Hz), (N,3)) the angle errors and the bias leave there.

        The turned part of the acceleration changes as fast as the motion does, so its variance counts over the
        motion's own correlation time (from the accelerations outside the gaps); the gravity a tilt error lets in
        and the bias stay the same over much of a span, so theirs counts over `CORRELATION_FRACTION` of it. What
        stays the same across a gap is a constant acceleration error, which the two ends take out (the smoother's
        bias): of the tilt the ends were aligned with and of the bias only as much counts as the device turns them.
        `misfit` (where GPS covers the run, codegen.post.bridge.ImuMisfit): the IMU's misfit at each gap's time
        scale, in proportion to the gap's own acceleration power, less the smoother's own `floor` density. It
        measures the same slow errors whole (tilt, bias, lever arm, a hand's swing), so the larger of it and the
        tilt and bias terms counts, not their sum. It was measured with the per-interval orientation where GPS covers
        the run, so it counts only in spans whose orientation is interpolated the same way: a gyro span's orientation
        is the gyro's, aligned to several seconds of solved intervals, not the per-interval solution.
        `gyro_misfit(window)` (codegen.post.bridge.GyroTrack.relative_power): the same misfit measured with the
        orientation a gyro span has, over windows of the gap's length where GPS covers the run. In a gyro span the
        tilt and bias terms are an upper bound: they are the fits' marginal 1-sigmas, which cannot tell a horizontal
        bias from a tilt (the solved tilt takes the bias up), while what the gap sees is their sum, the body-fixed
        acceleration error the gyro carries round as the device turns, and that is what the misfit measures; so
        where it is smaller, it counts in their place."""
        a = self.enu(t, acc, bias)
        density = np.zeros_like(a)
        inside = self.inside(t)
        if inside.any():
            motion_time = _correlation_time(t[~inside], a[~inside, :2])
            yaw, tilt = self.angle_sigma(t[inside])
            aligned_tilt = self.aligned_tilt(t[inside])
            shrink = np.exp(-0.5 * yaw**2)
            horizontal = np.hypot(a[inside, 0], a[inside, 1])
            power = self._gap_power(t, a)[inside]  # before the shrink: the motion's own accelerations
            a[inside, :2] *= shrink[:, None]
            # per horizontal axis: half the variance of the turned part; half of the gravity let in by the tilt
            # (the part the ends were aligned with as far as the device turns it, the gyro's growth all); the bias
            # left in the sensor frame, as far as the device turns it within the span (a bias that stays put in
            # ENU is taken out by the two ends)
            turned = np.minimum(1.0, self._turn(t)[inside] + yaw)
            grown = np.maximum(tilt**2 - aligned_tilt**2, 0.0)
            var_fast = 0.5 * horizontal**2 * (1.0 - np.exp(-yaw**2))
            var_slow = 0.5 * STANDARD_GRAVITY**2 * ((aligned_tilt * turned) ** 2 + grown) + (self.bias_sigma * turned) ** 2
            q_slow = var_slow * self.correlation_time(t[inside])
            span_t = t[inside]
            if misfit is not None:
                q_misfit = np.zeros(int(inside.sum()))
                for span in self.spans:
                    if span.gyro:
                        continue
                    sel = (span_t > span.a) & (span_t < span.b)
                    q_misfit[sel] = misfit.relative_power(span.gap.length) * power[sel]
                q_slow = np.maximum(q_slow, q_misfit - floor**2)
            if gyro_misfit is not None:
                for span in self.spans:
                    relative = gyro_misfit(span.gap.length) if span.gyro else None
                    if relative is None:
                        continue
                    sel = (span_t > span.a) & (span_t < span.b)
                    q_slow[sel] = np.minimum(q_slow[sel], np.maximum(relative * power[sel] - floor**2, 0.0))
            q = var_fast * motion_time + q_slow
            density[inside, :2] = np.sqrt(np.maximum(q, 0.0))[:, None]
        return a, density

    def aligned_tilt(self, t: np.ndarray) -> np.ndarray:
        """rad: the tilt 1-sigma at the ends a span was aligned at (the solved intervals' own; 0 outside spans)."""
        t = np.asarray(t, dtype=float)
        out = np.zeros(len(t))
        for span in self.spans:
            sel = (t > span.a) & (t < span.b)
            end = span.end_sigma if span.end_sigma is not None else self.end_sigma
            out[sel] = min(float(np.hypot(end[0], end[1])), MAX_ANGLE_SIGMA)
        return out

    def _gap_power(self, t: np.ndarray, a: np.ndarray) -> np.ndarray:
        """(m/s^2)^2: the mean horizontal acceleration power inside the gap of the span each t lies in."""
        out = np.zeros(len(t))
        power = a[:, 0] ** 2 + a[:, 1] ** 2
        for span in self.spans:
            gap = (t > span.gap.t0) & (t < span.gap.t1)
            sel = (t > span.a) & (t < span.b)
            out[sel] = float(np.mean(power[gap])) if gap.any() else 0.0
        return out

    def _turn(self, t: np.ndarray) -> np.ndarray:
        """rad: how far the device's heading ranges over the span each t lies in (0 outside spans)."""
        out = np.zeros(len(t))
        for span in self.spans:
            sel = (t > span.a) & (t < span.b)
            if sel.sum() > 1:
                heading = np.unwrap(self.rotation(t[sel]).as_euler("ZYX")[:, 0])
                out[sel] = np.ptp(heading)
        return out


def _integrate(t: np.ndarray, gyro: np.ndarray, a: float, b: float) -> tuple[np.ndarray, np.ndarray, Rotation]:
    """The gyro's rotation from a to b (identity at a): step times, the rate held over each step, the rotations."""
    sel = np.flatnonzero((t > a) & (t < b))
    times = np.concatenate([[a], t[sel], [b]])
    rates = gyro[np.concatenate([[max(sel[0] - 1, 0)], sel])] if len(sel) else np.zeros((1, 3))
    if not len(sel):
        times = np.array([a, b])
    steps = Rotation.from_rotvec(rates * np.diff(times)[:, None])
    quats = np.empty((len(times), 4))
    r = Rotation.identity()
    quats[0] = r.as_quat()
    for k in range(len(steps)):
        r = r * steps[k]
        quats[k + 1] = r.as_quat()
    return times, rates, Rotation.from_quat(quats)


def _align(offsets: Rotation) -> tuple[Rotation, np.ndarray]:
    """Mean of ENU-frame offset rotations and the 1-sigma of that mean as (roll, pitch, yaw) spread / sqrt(n)."""
    mean = offsets.mean()
    spread = (offsets * mean.inv()).as_rotvec()
    n = len(spread)
    sigma = np.sqrt(np.mean(spread**2, axis=0) / max(n - 1, 1)) if n > 1 else np.full(3, np.inf)
    return mean, sigma


def _gyro_span(t: np.ndarray, gyro: np.ndarray, slerp: Callable[[np.ndarray], Rotation], align_t: np.ndarray,
               a: float, b: float) -> tuple[Callable[[np.ndarray], Rotation], np.ndarray, str]:
    """Sensor->ENU rotation on [a, b] from the gyro, the 1-sigma (roll, pitch, yaw, rad) of its alignment, and
    which ends it was aligned at.

    The gyro's integral G(t) is set against the solved orientations S of the intervals `align_t` within
    `ALIGN_WINDOW` before a and after b: the mean offset S G^-1 on each side (a single solved interval's angles are
    noisy, their mean over a few seconds is not), then Slerp from the one before to the one after across the span,
    so the gyro's drift over the span is taken out in proportion to the time elapsed. Where one side has no interval
    to align to (a stand: its yaw is held, not solved), the other side's offset holds across the whole span: the
    heading through a stand is the one the motion on the other side established, turned by the gyro."""
    lo, hi = a - ALIGN_WINDOW, b + ALIGN_WINDOW
    times, rates, integral = _integrate(t, gyro, lo, hi)

    def gyro_at(tt: np.ndarray) -> Rotation:
        k = np.clip(np.searchsorted(times, tt, side="right") - 1, 0, len(times) - 2)
        return integral[k] * Rotation.from_rotvec(rates[k] * (tt - times[k])[:, None])

    before = align_t[(align_t >= lo) & (align_t <= a + 1e-9)]
    after = align_t[(align_t >= b - 1e-9) & (align_t <= hi)]
    sides = []
    if len(before):
        left, s_left = _align(slerp(before) * gyro_at(before).inv())
        sides.append((left, s_left))
    if len(after):
        right, s_right = _align(slerp(after) * gyro_at(after).inv())
        sides.append((right, s_right))
    aligned = "both" if len(before) and len(after) else "before" if len(before) else "after"
    if aligned == "both":
        across = Slerp([a, b], Rotation.concatenate([left, right]))
    else:
        offset = sides[0][0]
        across = lambda tt: Rotation.concatenate([offset] * len(np.atleast_1d(tt)))  # noqa: E731

    def rotation(tt: np.ndarray) -> Rotation:
        return across(np.clip(tt, a, b)) * gyro_at(tt)

    return rotation, np.max([sigma for _, sigma in sides], axis=0), aligned


def estimate_gyro_bias(t: np.ndarray, gyro: np.ndarray, slerp: Callable[[np.ndarray], Rotation],
                       covered: list[tuple[float, float]]) -> Optional[np.ndarray]:
    """Constant gyro bias (rad/s, sensor frame): over windows of `GYRO_BIAS_WINDOW` inside stretches GPS covers, the
    rotation the gyro integrates against the one between the solved orientations at the window's ends."""
    misses, spans = [], []
    for c0, c1 in covered:
        for w0 in np.arange(c0, c1 - GYRO_BIAS_WINDOW, GYRO_BIAS_WINDOW):
            w1 = w0 + GYRO_BIAS_WINDOW
            sel = np.flatnonzero((t >= w0) & (t < w1))
            if len(sel) < 10:
                continue
            dt = np.diff(np.append(t[sel], w1))
            steps = Rotation.from_rotvec(gyro[sel] * dt[:, None])
            r = Rotation.identity()
            for k in range(len(steps)):
                r = r * steps[k]
            ends = slerp(np.array([t[sel[0]], w1]))
            solved = ends[0].inv() * ends[1]
            misses.append((solved.inv() * r).as_rotvec())  # body frame: turned too far by the bias * window
            spans.append(w1 - t[sel[0]])
    if len(misses) < 3:
        return None
    return np.median(np.array(misses) / np.array(spans)[:, None], axis=0)


def gap_model(slerp: Callable[[np.ndarray], Rotation], solved_t: np.ndarray, solved_euler: np.ndarray,
              solved_sigma: np.ndarray, gps_t: np.ndarray, imu_t: np.ndarray, gyro: Optional[np.ndarray],
              bias_sigma: float = 0.0, standing: Optional[np.ndarray] = None) -> GapModel:
    """The spans of the gaps in `gps_t` between the solved intervals (midpoints `solved_t`, Euler roll/pitch/yaw)
    around them; their orientation from the gyro where there is one; the rates their angle errors grow at.

    `standing` (bool per solved interval): the device stood, so the track had no direction and its yaw was held, or
    solved against a track direction held from before, not solved from motion. With a gyro, a span
    reaches over the stands next to its gap to the nearest interval whose yaw was solved (or to the end of the log),
    and is aligned only to such intervals: a held yaw is not a solved one, and a vehicle does not turn while it
    stands."""
    gaps = find_gaps(gps_t)
    yaw_rate, tilt_rate = _angle_rates(solved_t, solved_euler)
    end_sigma = np.zeros(3)
    for i in range(3):
        column = solved_sigma[:, i][np.isfinite(solved_sigma[:, i])]
        end_sigma[i] = float(np.median(column)) if len(column) else 0.0
    model = GapModel(slerp, [], yaw_rate, tilt_rate, end_sigma, bias_sigma)
    covered, last = [], gps_t[0]
    for gap in gaps:
        covered.append((last, gap.t0))
        last = gap.t1
    covered.append((last, gps_t[-1]))
    if gyro is not None and gaps:
        model.gyro_bias = estimate_gyro_bias(imu_t, gyro, slerp, covered)
        if model.gyro_bias is None:
            model.notes.append("gyro bias: too little GPS-covered time to estimate it; the gyro is used as logged")
    standing = np.zeros(len(solved_t), dtype=bool) if standing is None else np.asarray(standing, dtype=bool)
    solved_yaw_t = solved_t[~standing]
    for gap in gaps:
        before = solved_t[solved_t <= gap.t0 + 1e-9]
        after = solved_t[solved_t >= gap.t1 - 1e-9]
        a = float(before[-1]) if len(before) else gap.t0
        b = float(after[0]) if len(after) else gap.t1
        span = Span(gap, a, b, gyro=gyro is not None, bridged=b - a)
        if gyro is not None and len(before) and len(after):
            yaw_before = solved_yaw_t[solved_yaw_t <= gap.t0 + 1e-9]
            yaw_after = solved_yaw_t[solved_yaw_t >= gap.t1 - 1e-9]
            if len(yaw_before) or len(yaw_after):
                # over the stands next to the gap to the solved yaw beyond them (or the log's end)
                span.a = float(yaw_before[-1]) if len(yaw_before) else min(a, float(imu_t[0]))
                span.b = float(yaw_after[0]) if len(yaw_after) else max(b, float(imu_t[-1]))
                g = gyro - (model.gyro_bias if model.gyro_bias is not None else 0.0)
                span.rotation, span.end_sigma, span.aligned = _gyro_span(imu_t, g, slerp, solved_yaw_t, span.a,
                                                                         span.b)
            else:
                span.gyro = False
        else:
            span.gyro = False
        model.spans.append(span)
    return model


def _correlation_time(t: np.ndarray, a: np.ndarray) -> float:
    """s: the integral time scale of the horizontal accelerations (two-sided integral of their autocorrelation,
    up to its first zero), at the samples' median rate; what turns a variance into a white-noise density."""
    if len(t) < 16:
        return 1.0
    step = float(np.median(np.diff(t)))
    x = a - a.mean(axis=0)
    n = len(x)
    spectrum = np.fft.rfft(x, 2 * n, axis=0)
    acf = np.fft.irfft(np.abs(spectrum) ** 2, axis=0)[:n].sum(axis=1)
    if acf[0] <= 0:
        return step
    rho = acf / acf[0]
    first_zero = int(np.argmax(rho <= 0)) if (rho <= 0).any() else n
    return float(step * (2.0 * rho[:first_zero].sum() - 1.0))


def _angle_rates(t: np.ndarray, euler: np.ndarray) -> tuple[float, float]:
    """Random-walk rates (rad/sqrt(s)) of the yaw and of the tilt: sqrt(mean(change^2 / dt)) between consecutive
    solved intervals."""
    if len(t) < 3:
        return 0.0, 0.0
    dt = np.diff(t)
    typical = np.median(dt)
    near = dt < GAP_EPOCH_FACTOR * typical  # consecutive epochs, not across a gap
    if not near.any():
        return 0.0, 0.0
    d = np.diff(euler, axis=0)
    d = (d + np.pi) % (2 * np.pi) - np.pi
    var = d[near] ** 2 / dt[near, None]
    return float(np.sqrt(np.mean(var[:, 2]))), float(np.sqrt(np.mean(var[:, 0] + var[:, 1])))


@dataclass
class ImuMisfit:
    """How far the IMU's velocity change misses the GPS's where GPS covers the run, at the time scale of a gap and
    in proportion to the motion's acceleration.

    Per GPS interval the misfit is r = (v_gps[k+1] - v_gps[k]) - integral of the ENU accelerations; summed from an
    epoch on, it is the velocity the IMU alone would be off by. A gap is bridged with GPS at both ends, so what the
    ends tell (a constant acceleration error: the bias the smoother estimates) is taken out: over each window of a
    gap's length the summed misfit less the straight line between its two ends, e(s) at the fraction s of the window.
    A white acceleration error of density q leaves E[e^2] = q^2 W s (1 - s) (a Brownian bridge), plus the Doppler
    noise of the three epochs involved; a bounded oscillation (a hand's swing, a lever arm turning with the device)
    leaves an e that does not grow with W, so the white density that explains it falls as 1 / sqrt(W). Errors that
    turn or scale the accelerations (an angle, a lever arm, a scale factor) grow with the motion, and a device that
    stands has none: so the density is taken per unit of the window's horizontal acceleration power, and a gap gets
    it times its own power (a walker slowing to a stand gets less than the brisk walk before)."""

    t: np.ndarray  # (K+1,) s, the epochs of each stretch of consecutive usable intervals, stretch after stretch
    cum: np.ndarray  # (K+1,2) m/s, horizontal misfit summed from the stretch's first epoch
    doppler: np.ndarray  # (K+1,2) (m/s)^2, the GPS horizontal velocity variance at each of those epochs
    energy: np.ndarray  # (K+1,) m^2/s^3, the horizontal acceleration power integrated from the stretch's first epoch
    stretch: np.ndarray  # (K+1,) int, which stretch each epoch belongs to

    @classmethod
    def from_intervals(cls, t0: np.ndarray, t1: np.ndarray, residual: np.ndarray, power: np.ndarray,
                       sigma_vel0: np.ndarray, sigma_vel1: np.ndarray, usable: np.ndarray) -> "ImuMisfit":
        """`residual` (K,3) the misfit per interval [t0, t1], `power` (K,) its mean horizontal acceleration power
        ((m/s^2)^2), `sigma_vel0/1` (K,3) the GPS velocity 1-sigma at its ends."""
        ok = usable & np.isfinite(residual).all(axis=1) & np.isfinite(power)
        dt = t1 - t0
        typical = float(np.median(dt)) if len(dt) else 1.0
        ok &= dt < GAP_EPOCH_FACTOR * typical
        ts, cums, dops, energies, which = [], [], [], [], []
        k, n, label = 0, len(ok), 0
        while k < n:
            if not ok[k]:
                k += 1
                continue
            j = k
            while j + 1 < n and ok[j + 1] and abs(t0[j + 1] - t1[j]) < 1e-9:
                j += 1
            sel = slice(k, j + 1)
            ts.append(np.concatenate([[t0[k]], t1[sel]]))
            cums.append(np.concatenate([np.zeros((1, 2)), np.cumsum(residual[sel, :2], axis=0)]))
            dops.append(np.concatenate([sigma_vel0[k:k + 1, :2], sigma_vel1[sel, :2]]) ** 2)
            energies.append(np.concatenate([[0.0], np.cumsum(power[sel] * dt[sel])]))
            which.append(np.full(j - k + 2, label))
            label += 1
            k = j + 1
        if not ts:
            return cls(np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, dtype=int))
        return cls(np.concatenate(ts), np.concatenate(cums), np.concatenate(dops), np.concatenate(energies),
                   np.concatenate(which))

    def relative_power(self, window: float) -> float:
        """1/s: q^2 per unit of acceleration power, per horizontal axis: sum(e^2 - Doppler) / sum(W s (1 - s) P)
        over every window from an epoch to the first one at least `window` s on in its stretch (at least two
        intervals; the longest a stretch has where none is that long), at each epoch inside, with P the window's
        mean horizontal acceleration power. Zero where nothing is left above the Doppler noise."""
        if len(self.t) < 3:
            return 0.0
        stretches = [np.flatnonzero(self.stretch == s) for s in np.unique(self.stretch)]
        longest = max(float(np.ptp(self.t[idx])) for idx in stretches)
        window = min(max(window, 0.0), longest)
        excess, weight = 0.0, 0.0
        for idx in stretches:
            t, cum, dop, energy = self.t[idx], self.cum[idx], self.doppler[idx], self.energy[idx]
            ends = np.maximum(np.searchsorted(t, t + window - 1e-9), np.arange(len(t)) + 2)
            for i in np.flatnonzero(ends < len(t)):
                j = ends[i]
                w = t[j] - t[i]
                s = ((t[i + 1:j] - t[i]) / w)[:, None]
                e = cum[i + 1:j] - cum[i] - s * (cum[j] - cum[i])
                noise = dop[i + 1:j] + (1 - s) ** 2 * dop[i] + s**2 * dop[j]
                excess += 0.5 * float(np.sum(e**2 - noise))
                weight += float(np.sum(w * s * (1 - s))) * (energy[j] - energy[i]) / w
        if weight <= 0:
            return 0.0
        return max(excess / weight, 0.0)


@dataclass
class GyroTrack:
    """The gyro's integral over the whole log (bias removed) and the intervals whose yaw was solved: what a gyro
    span's orientation is built from, so the misfit a gyro span leaves can be measured where GPS covers the run.

    `relative_power(window)` is `ImuMisfit.relative_power` with one difference: each window from an epoch to the
    first one at least `window` s on is oriented as a gap there would be, the gyro's integral aligned to the solved
    intervals within `ALIGN_WINDOW` before its start and after its end and Slerped between the two (`_gyro_span`), and
    its velocity misfit against the GPS is taken with that orientation. The misfit left is what the gyro bridge's
    own errors leave over a gap's length: the body-fixed acceleration error (the accelerometer bias left, and the
    tilt the alignment took from the solved intervals) turned round with the device, the alignments' yaw, the
    gyro's drift, and whatever the IMU misses of the motion (a hand's swing, a lever arm)."""

    t: np.ndarray  # (N,) s, IMU sample times
    acc: np.ndarray  # (N,3) m/s^2, sensor frame, bias removed
    solved_t: np.ndarray  # s, midpoints of the intervals whose yaw was solved from motion
    slerp: Callable[[np.ndarray], Rotation]
    gps_t: np.ndarray
    gps_vel: np.ndarray  # (M,3) m/s
    gps_var: np.ndarray  # (M,2) (m/s)^2, horizontal Doppler variance
    times: np.ndarray  # the integral's step times
    rates: np.ndarray  # rad/s held over each step
    integral: Rotation  # at `times`
    _cache: dict = field(default_factory=dict)

    @classmethod
    def build(cls, t: np.ndarray, acc: np.ndarray, gyro: np.ndarray, solved_t: np.ndarray,
              slerp: Callable[[np.ndarray], Rotation], gps_t: np.ndarray, gps_vel: np.ndarray,
              gps_sigma_vel: np.ndarray) -> "GyroTrack":
        """`gyro` with its bias already removed, `acc` with the accelerometer's."""
        times, rates, integral = _integrate(t, gyro, float(t[0]) - 1e-6, float(t[-1]) + 1e-6)
        return cls(t, acc, np.asarray(solved_t, dtype=float), slerp, gps_t, gps_vel, gps_sigma_vel[:, :2] ** 2,
                   times, rates, integral)

    def _gyro_at(self, tt: np.ndarray) -> Rotation:
        k = np.clip(np.searchsorted(self.times, tt, side="right") - 1, 0, len(self.times) - 2)
        return self.integral[k] * Rotation.from_rotvec(self.rates[k] * (tt - self.times[k])[:, None])

    def _offset(self, at: np.ndarray) -> Rotation:
        return _align(self.slerp(at) * self._gyro_at(at).inv())[0]

    def _window(self, i: int, j: int) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """(velocity misfit at epochs i..j (j-i+1, 2), mean horizontal acceleration power) of the window from epoch
        i to epoch j, oriented as a gap there; None where it cannot be aligned at both ends."""
        a, b = self.gps_t[i], self.gps_t[j]
        before = self.solved_t[(self.solved_t >= a - ALIGN_WINDOW) & (self.solved_t <= a + 1e-9)]
        after = self.solved_t[(self.solved_t >= b - 1e-9) & (self.solved_t <= b + ALIGN_WINDOW)]
        if not len(before) or not len(after):
            return None
        across = Slerp([a, b], Rotation.concatenate([self._offset(before), self._offset(after)]))
        edges = np.searchsorted(self.t, [a, b])
        sel = slice(max(edges[0] - 2, 0), min(edges[1] + 2, len(self.t)))
        ts = self.t[sel]
        if len(ts) < 4:
            return None
        enu = (across(np.clip(ts, a, b)) * self._gyro_at(ts)).apply(self.acc[sel])
        enu[:, 2] -= STANDARD_GRAVITY
        enu[:, 2] = enu[:, 0] ** 2 + enu[:, 1] ** 2  # the third column carries the horizontal power
        nodes, cum = cumulative_integral(ts, enu)
        epochs = self.gps_t[i:j + 1]
        at = np.stack([np.interp(epochs, nodes, cum[:, c]) for c in range(3)], axis=1)
        misfit = (self.gps_vel[i:j + 1, :2] - self.gps_vel[i, :2]) - (at[:, :2] - at[0, :2])
        return misfit, (at[-1, 2] - at[0, 2]) / (b - a)

    def relative_power(self, window: float) -> Optional[float]:
        """1/s, per horizontal axis and unit of acceleration power, as ImuMisfit.relative_power; None where no window
        GPS covers can be aligned at both ends."""
        key = round(float(window), 6)
        if key not in self._cache:
            self._cache[key] = self._relative_power(window)
        return self._cache[key]

    def _relative_power(self, window: float) -> Optional[float]:
        gps_t = self.gps_t
        if len(gps_t) < 3:
            return None
        step = np.diff(gps_t)
        typical = float(np.median(step))
        breaks = np.flatnonzero(step > GAP_EPOCH_FACTOR * typical)
        starts = np.concatenate([[0], breaks + 1])
        stops = np.concatenate([breaks, [len(gps_t) - 1]])  # last epoch of each stretch
        inside = (gps_t >= self.t[0]) & (gps_t <= self.t[-1])
        longest = max(float(gps_t[e] - gps_t[s]) for s, e in zip(starts, stops))
        window = min(max(window, 0.0), longest)
        stride = max(1, int(round(0.25 * window / typical)))  # windows overlap by three quarters
        excess, weight = 0.0, 0.0
        for s0, s1 in zip(starts, stops):
            for i in range(s0, s1 + 1, stride):
                j = max(int(np.searchsorted(gps_t, gps_t[i] + window - 1e-9)), i + 2)
                if j > s1 or not (inside[i] and inside[j]):
                    continue
                found = self._window(i, j)
                if found is None:
                    continue
                misfit, power = found
                w = gps_t[j] - gps_t[i]
                s = ((gps_t[i + 1:j] - gps_t[i]) / w)[:, None]
                e = misfit[1:-1] - s * misfit[-1]
                dop = self.gps_var
                noise = dop[i + 1:j] + (1 - s) ** 2 * dop[i] + s**2 * dop[j]
                excess += 0.5 * float(np.sum(e**2 - noise))
                weight += float(np.sum(w * s * (1 - s))) * power
        if weight <= 0:
            return None
        return max(excess / weight, 0.0)
