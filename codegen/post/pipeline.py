"""`deadreckon post`: the whole method on one `PostLog`, as a library call the CLI and the tests share."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from codegen.board.model import STANDARD_GRAVITY
from codegen.errors import UserError
from codegen.post.bridge import GapModel, GyroTrack, ImuMisfit, gap_model
from codegen.post.delay import DelayEstimate, estimate_delay
from codegen.post.geodesy import geodetic_to_enu
from codegen.post.gyroframe import GyroFrame, fit_gyro_frame
from codegen.post.model import Calibration, PostLog
from codegen.post.orientation import (
    GPS_GAP_FACTOR,
    Intervals,
    Mounting,
    OrientationOptions,
    OrientationResult,
    Track,
    build_intervals,
    cumulative_integral,
    euler_matrix,
    fit_mounting,
    interval_means,
    solve_orientations,
    turn_compensated_means,
)
from codegen.post.smoother import SmootherOptions, SmootherResult, smooth
from codegen.post.stands import STILL_GPS_SPEED, learn_stillness

Progress = Optional[Callable[[str, float], None]]
MIN_IMU_SAMPLES = 10
MIN_GPS_INTERVALS = 3


@dataclass
class PostOptions:
    orientation: OrientationOptions = field(default_factory=OrientationOptions)
    smoother: SmootherOptions = field(default_factory=SmootherOptions)
    delay: Optional[float] = None  # s: use this delay instead of estimating it
    max_lag: float = 1.0  # s, delay search range
    calibration: Optional[Calibration] = None
    output_rate: float = 10.0  # Hz, trajectory CSV/GPX rows
    plots: bool = True


@dataclass
class PostResult:
    log: PostLog
    delay: float  # s, total; IMU timestamps were late by this much
    delay_estimate: Optional[DelayEstimate]
    orientation: OrientationResult
    intervals: Intervals
    imu_t: np.ndarray  # corrected IMU times (GPS time axis)
    acc_enu: np.ndarray  # (N,3) rotated, bias- and gravity-free accelerations
    track: SmootherResult
    origin: tuple[float, float, float]
    gps_enu: np.ndarray  # (M,3), U NaN when the log has no height
    velocity_residual: np.ndarray  # (M,3) GPS - smoothed at GPS epochs (NaN outside)
    imu_velocity_residual: np.ndarray  # (K,3) GPS - IMU velocity change per interval, m/s
    gaps: GapModel  # GPS gaps, the orientation across them and its uncertainty
    notes: list[str] = field(default_factory=list)
    options: PostOptions = field(default_factory=PostOptions)
    gyro_frame: Optional[GyroFrame] = None  # where the mounting and bias came from the gyro (codegen.post.gyroframe)

    @property
    def velocity_residual_rms(self) -> float:
        r = self.velocity_residual[np.isfinite(self.velocity_residual).all(axis=1)]
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")

    @property
    def imu_velocity_residual_rms(self) -> float:
        r = self.imu_velocity_residual[np.isfinite(self.imu_velocity_residual).all(axis=1)]
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def check_log(log: PostLog, where: str | None = None) -> None:
    """A log the method cannot work on is a user error with the reason, never a traceback later; `where` names
    the log's file(s) in the message (default: the run's name)."""
    imu, gps = log.imu, log.gps
    where = where or log.name
    if len(imu) < MIN_IMU_SAMPLES:
        raise UserError(f"{where}: only {len(imu)} IMU sample(s); the method needs accelerations over the GPS epochs",
                        hint="is the IMU log empty or cut off?")
    if len(gps) < MIN_GPS_INTERVALS + 1:
        raise UserError(f"{where}: only {len(gps)} GPS epoch(s) with a fix; need at least {MIN_GPS_INTERVALS + 1}",
                        hint="the receiver had no fix during the log, or the GPS log is cut off")
    covered = np.sum((gps.t[:-1] >= imu.t[0]) & (gps.t[1:] <= imu.t[-1]))
    if covered < MIN_GPS_INTERVALS:
        raise UserError(
            f"{where}: IMU ({imu.t[0]:.3f}..{imu.t[-1]:.3f} s) and GPS ({gps.t[0]:.3f}..{gps.t[-1]:.3f} s) "
            f"share {covered} GPS interval(s); need at least {MIN_GPS_INTERVALS}",
            hint="both logs must use the same time axis (device seconds or GPS time)",
        )
    if not np.all(np.isfinite(gps.vel)):
        raise UserError(f"{where}: GPS velocities contain gaps (NaN)")
    if np.all(gps.vel == gps.vel[0]):
        still = not np.any(gps.vel[0])
        raise UserError(
            f"{where}: the GPS velocity is {'zero' if still else np.round(gps.vel[0], 3).tolist()} m/s at all "
            f"{len(gps)} epochs: {'the device stood still' if still else 'it never changes'}, so there is no velocity "
            "change to align the accelerometer to (nor to find the delay by)",
            hint="post-processing needs a run with speed changes or turns; a GPS log that repeats one velocity may "
                 "also come from a logger that writes its last value again when it has no new fix")


def _segments(gps_t: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) epoch index ranges between GPS gaps."""
    step = np.diff(gps_t)
    breaks = list(np.flatnonzero(step > GPS_GAP_FACTOR * np.median(step)) + 1)
    edges = [0] + breaks + [len(gps_t)]
    return list(zip(edges[:-1], edges[1:]))


def smooth_segments(t, a_enu, gps, gps_enu, options: SmootherOptions) -> list[SmootherResult]:
    """KF + RTS on each stretch of GPS without gaps, alone (dead reckoning across a gap would bend the track
    direction the orientation is solved against)."""
    parts = []
    for a, b in _segments(gps.t):
        margin = 2.0 * float(np.median(np.diff(t)))  # a sample either side: the stretch starts at its first epoch
        inside = (t >= gps.t[a] - margin) & (t <= gps.t[b - 1] + margin)
        if b - a < 2 or inside.sum() < MIN_IMU_SAMPLES:
            continue
        sel = slice(a, b)
        parts.append(smooth(t[inside], a_enu[inside], gps.t[sel], gps.vel[sel], gps.sigma_vel[sel], gps_enu[sel],
                            gps.sigma_pos[sel], options))
    if not parts:
        raise UserError("no stretch of the log has both GPS epochs and IMU samples")
    return parts


def _rotate_mounted(mounting, iv: Intervals, t: np.ndarray, acc: np.ndarray) -> np.ndarray:
    chi, _ = iv.track.yaw(t)
    grade = np.interp(t, iv.mid, iv.grade) if iv.grade is not None else np.zeros(len(t))
    m = mounting.euler
    rot = (Rotation.from_euler("z", chi[:, None]) * Rotation.from_euler("y", -grade[:, None])
           * Rotation.from_euler("ZYX", [m[2], m[1], m[0]]))
    return rot.apply(acc - mounting.bias) - np.array([0.0, 0.0, STANDARD_GRAVITY])


def _rotate(orientation: OrientationResult, t: np.ndarray, acc: np.ndarray) -> np.ndarray:
    rot = orientation.slerp()(t)
    return rot.apply(acc - orientation.bias) - np.array([0.0, 0.0, STANDARD_GRAVITY])


def _whole_run_mounting(t: np.ndarray, acc: np.ndarray, log: PostLog, iv: Intervals, options: OrientationOptions,
                        strict: bool = True) -> tuple[Optional[Mounting], Optional[GyroFrame]]:
    """The rigid mounting fit; where it fits poorly (chi2 above `poor_fit_chi2`: the device does not sit rigidly, a
    hand) and the log has a gyro, the gyro frame's mean mounting and bias instead, if that model passes the bias's
    chi2 test (`strict`), or (not strict: while the delay is still being searched, and a wrong delay spoils every
    fit) fits better than the rigid one.

    Between `bias_max_chi2` and `poor_fit_chi2` the rigid fit stands with its bias rejected, as before the gyro frame:
    on the real hand-held walk (rigid chi2 4.4) the gyro frame halves the error in 10-60 s gaps, but the gap model's
    1-sigma, whose IMU misfit it then measures with the gyro frame, covers only a third of the error in 5-10 s gaps
    (docs/post.md, "The app's own device log")."""
    mounting = fit_mounting(iv, options.estimate_bias, options.bias_prior, options.bias_max_chi2)
    gyro = log.imu.gyro
    if gyro is None or not options.estimate_bias or (mounting is not None and mounting.chi2 <= options.poor_fit_chi2):
        return mounting, None
    frame = fit_gyro_frame(t, acc, gyro, iv, log.gps.t, log.gps.vel, log.gps.sigma_vel)
    limit = options.bias_max_chi2 if strict else (mounting.chi2 if mounting is not None else np.inf)
    if frame is None or not frame.chi2 <= limit:
        return mounting, None
    carried = frame.mounting(iv, options.min_speed)
    return (carried, frame) if carried is not None else (mounting, None)


def _orient(t, acc, log: PostLog, options: OrientationOptions, track: Optional[Track], progress: Progress):
    """Mounting + bias over the run, per-interval LM, then again on turn-compensated interval means."""
    gps = log.gps
    iv = build_intervals(t, acc, gps.t, gps.vel, gps.sigma_vel, options.min_speed)
    if track is not None:
        iv.track = track
        iv.track_yaw, iv.moving = track.yaw(iv.mid)
    mounting, frame = _whole_run_mounting(t, acc, log, iv, options)
    bias1 = mounting.bias if mounting is not None else np.zeros(3)
    first = solve_orientations(iv, options, bias1, mounting)
    if not first.valid.any():
        raise UserError(f"{log.name}: no GPS interval has IMU samples; cannot find the orientation")
    up = np.array([euler_matrix(*e).T[:, 2] if np.isfinite(e).all() else [0.0, 0.0, 1.0] for e in first.euler])
    iv.acc_mean = turn_compensated_means(iv, t, acc - bias1, up)
    if frame is None:
        mounting2 = fit_mounting(iv, options.estimate_bias, options.bias_prior, options.bias_max_chi2)
    else:  # the gyro frame's bias is already removed, its mounting does not depend on the interval means
        mounting2 = replace(mounting, bias=np.zeros(3))
    bias2 = mounting2.bias if mounting2 is not None else np.zeros(3)
    result = solve_orientations(iv, options, bias2, mounting2, progress=progress)
    if frame is not None:  # the gyro follows the device between the GPS epochs; windows of solved intervals do not
        ok = result.valid
        zyx = frame.rotation_at(result.t[ok]).as_euler("ZYX")
        result.euler[ok] = zyx[:, ::-1]
    result.bias = bias1 + bias2
    if mounting2 is not None:
        mounting2.bias = result.bias
    return result, iv, frame


def _imu_misfit(t: np.ndarray, a_enu: np.ndarray, iv: Intervals, gps) -> ImuMisfit:
    """Where GPS covers the run, how far the IMU's velocity change per interval misses the GPS's."""
    nodes, cum = cumulative_integral(t, a_enu)
    dt = iv.t1 - iv.t0
    residual = np.diff(gps.vel, axis=0) - interval_means(nodes, cum, iv.t0, iv.t1) * dt[:, None]
    power_nodes, power_cum = cumulative_integral(t, np.column_stack([a_enu[:, 0] ** 2 + a_enu[:, 1] ** 2,
                                                                     np.zeros((len(t), 2))]))
    power = interval_means(power_nodes, power_cum, iv.t0, iv.t1)[:, 0]
    return ImuMisfit.from_intervals(iv.t0, iv.t1, residual, power, gps.sigma_vel[:-1], gps.sigma_vel[1:], iv.usable)


def _bias_sigma(orientation: OrientationResult, options: OrientationOptions, parts: list[SmootherResult],
                rigid: bool = True) -> float:
    """m/s^2 per axis: the accelerometer bias left after the removal: the rigid mounting fit's 1-sigma where the bias
    was fitted by it, else what the smoother found the horizontal ENU accelerations off by where GPS covers the run
    (RMS). Not the gyro frame's least-squares 1-sigma (`rigid` False): that takes the intervals' errors as
    independent, and a hand's motion is not (on the real walk it put the 1-sigma of 5-10 s gaps at a third of the
    error)."""
    m = orientation.mounting
    if m is not None and not m.bias_rejected and options.estimate_bias and rigid:
        return float(np.sqrt(np.mean(m.sigma_bias**2)))
    found = np.concatenate([p.bias[:, :2] for p in parts])
    return float(min(options.bias_prior, np.sqrt(np.mean(found**2))))


STAND_BRIDGE_SPEED = 0.5  # m/s: a node is a stand only where the bridge without stands is surely slower than this


def _stands_in_gaps(t: np.ndarray, acc: np.ndarray, gyro: Optional[np.ndarray], gps, gaps: GapModel,
                    bridge: SmootherResult):
    """(zero_velocity(nodes) -> 1-sigma or NaN, seconds stood) for the smoother, or (None, 0) where the device did
    not stand inside any gap. A node stands when the IMU's window there is as quiet as the run's own stands
    (codegen.post.stands), and either the bridge without stands is slower than `STAND_BRIDGE_SPEED` there by more
    than its 1-sigma (a smooth cruise can be as quiet as a stand; it is not as slow), or the whole gap is a stand:
    GPS stood at both ends and the IMU is quiet all through it (without a gyro the bridge's speed says little)."""
    if not gaps.spans:
        return None, 0.0
    stillness = learn_stillness(t, acc, gyro, gps.t, gps.vel)
    nodes = bridge.t
    speed = np.hypot(bridge.vel[:, 0], bridge.vel[:, 1])
    speed_sigma = np.hypot(bridge.sigma_vel[:, 0], bridge.sigma_vel[:, 1])
    gps_speed = np.hypot(gps.vel[:, 0], gps.vel[:, 1])
    stands = np.zeros(len(nodes), dtype=bool)
    for span in gaps.spans:
        inside = np.flatnonzero((nodes > span.gap.t0) & (nodes < span.gap.t1))
        if not len(inside):
            continue
        quiet = stillness.still(t, acc, gyro, nodes[inside])
        ends_still = gps_speed[span.gap.index] < STILL_GPS_SPEED and gps_speed[span.gap.index + 1] < STILL_GPS_SPEED
        if ends_still and quiet.all():
            stands[inside] = True
        else:
            stands[inside] = quiet & (speed[inside] + speed_sigma[inside] < STAND_BRIDGE_SPEED)
    if not stands.any():
        return None, 0.0
    stand_t = nodes[stands]
    sigma = stillness.velocity_sigma

    def zero_velocity(at: np.ndarray) -> np.ndarray:
        hit = np.isin(np.round(at, 9), np.round(stand_t, 9))
        return np.where(hit, sigma, np.nan)

    step = np.median(np.diff(nodes)) if len(nodes) > 1 else 0.0
    return zero_velocity, float(stands.sum() * step)


def process(log: PostLog, options: PostOptions = PostOptions(), progress: Progress = None) -> PostResult:
    check_log(log)
    notes = list(log.notes)
    gps = log.gps
    calibration = options.calibration or log.calibration
    acc = calibration.apply(log.imu.acc) if calibration is not None else log.imu.acc
    if calibration is not None:
        notes.append(f"calibration applied: offset {np.round(calibration.offset, 4).tolist()} m/s^2, "
                     f"scale {np.round(calibration.scale, 5).tolist()}")
    origin_h = float(gps.h[0]) if np.isfinite(gps.h[0]) else 0.0
    origin = (float(gps.lat[0]), float(gps.lon[0]), origin_h)
    gps_enu = geodetic_to_enu(gps.lat, gps.lon, np.nan_to_num(gps.h, nan=origin_h), origin)
    gps_enu[~np.isfinite(gps.h), 2] = np.nan
    step = float(np.median(np.diff(log.imu.t)))

    # 1. delay and orientation, alternately (the delay search needs ENU accelerations, the orientation the delay)
    delay, estimate, curve = (options.delay or 0.0), None, None
    for attempt in range(4):
        t = log.imu.t - delay
        iv = build_intervals(t, acc, gps.t, gps.vel, gps.sigma_vel, options.orientation.min_speed)
        mounting, frame = _whole_run_mounting(t, acc, log, iv, options.orientation, strict=options.delay is not None)
        if options.delay is not None:
            break
        # the delay search only needs rough ENU accelerations: the gyro frame where the device does not sit
        # rigidly, else the whole-run mounting turned with the track (cheap), or the per-interval solution where
        # there is too little motion to fit a mounting
        if frame is not None:
            a_rough = frame.enu(acc)
        elif mounting is not None:
            a_rough = _rotate_mounted(mounting, iv, t, acc)
        else:
            orientation = solve_orientations(iv, options.orientation, np.zeros(3), None)
            if not orientation.valid.any():
                raise UserError(f"{log.name}: no GPS interval has IMU samples; cannot find the orientation")
            a_rough = _rotate(orientation, t, acc)
        estimate = estimate_delay(t, a_rough, gps.t, gps.vel, options.max_lag if attempt == 0 else 4 * step,
                                  gps.sigma_vel)
        curve = estimate if attempt == 0 else curve  # the full-range search, for the report's plot
        delay += estimate.delay
        if progress:
            progress("delay", (attempt + 1) / 4)
        if abs(estimate.delay) < 0.25 * step:
            break
    coarse_delay = curve.delay if curve is not None else delay  # the first, full-range search
    # then per-interval orientation, and the delay refined with it (a device that does not sit rigidly is only
    # roughly described by the mounting)
    for attempt in range(3):
        t = log.imu.t - delay
        iv = build_intervals(t, acc, gps.t, gps.vel, gps.sigma_vel, options.orientation.min_speed)
        mounting, frame = _whole_run_mounting(t, acc, log, iv, options.orientation, strict=options.delay is not None)
        orientation = solve_orientations(iv, options.orientation, mounting.bias if mounting else np.zeros(3), mounting)
        if not orientation.valid.any():
            raise UserError(f"{log.name}: no GPS interval has IMU samples; cannot find the orientation")
        if options.delay is not None:
            break
        # the gyro frame follows a hand's wander, the per-interval solution (windows of seconds) does not
        enu = frame.enu(acc) if frame is not None else _rotate(orientation, t, acc)
        refined = estimate_delay(t, enu, gps.t, gps.vel, min(options.max_lag, 0.25), gps.sigma_vel)
        delay += refined.delay
        spread = max(refined.sigma, curve.sigma) if curve is not None else refined.sigma  # the full search's too
        estimate = replace(curve if curve is not None else refined, delay=delay, sigma=spread,
                           correlation=refined.correlation)
        if abs(refined.delay) < 0.25 * step:
            break
    if curve is not None and (curve.at_edge or abs(delay) > options.max_lag):
        # the first search's best lag at its edge, or the refinement walked out of its range: the range was too small
        estimate = replace(estimate, at_edge=True)
        notes.append(f"the delay search ended at its edge (first search {curve.delay * 1e3:+.0f} ms, range "
                     f"+-{options.max_lag * 1e3:.0f} ms): the streams are shifted by about --max-lag or more; the "
                     f"refinement went on to {delay * 1e3:+.0f} ms, but lags beyond the range were never searched: run "
                     f"again with --max-lag {2 * max(options.max_lag, abs(delay)):.3g}")
    elif estimate is not None and abs(delay - coarse_delay) > max(3.0 * estimate.sigma, step):
        notes.append(f"the delay moved from {coarse_delay * 1e3:+.0f} ms (first search) to {delay * 1e3:+.0f} ms as "
                     f"the orientation was refitted: the data do not pin it down; treat it as uncertain by "
                     f"{abs(delay - coarse_delay) * 1e3:.0f} ms")
    t = log.imu.t - delay
    # 2. the smoothed velocity gives a quieter track direction than raw Doppler: orient again with it, and with the
    #    interval means turned back for the device's own turning
    #    (per stretch without GPS gaps: dead reckoning across a gap would bend the track)
    parts = smooth_segments(t, _rotate(orientation, t, acc), gps, gps_enu, options.smoother)
    track = Track(np.concatenate([p.t for p in parts]), np.concatenate([p.vel for p in parts]),
                  options.orientation.min_speed)
    orientation, iv, frame = _orient(t, acc, log, options.orientation, track, progress)
    if frame is not None:
        rigid = fit_mounting(iv, False)
        fitted = f"the rigid mounting fit's chi2 {rigid.chi2:.1f}" if rigid is not None else "no rigid mounting fit"
        notes.append(f"the device does not sit rigidly ({fitted}): its mounting "
                     f"is its mean orientation along the track and the accelerometer bias is solved with the gyro's "
                     f"integral (chi2 {frame.chi2:.2f}; the gyro's bias "
                     f"{np.round(np.degrees(frame.gyro_bias), 2).tolist()} deg/s from {frame.quiet_epochs} quiet "
                     f"stand epochs)")
    # 3. across GPS gaps: the orientation from the gyro (where logged) or Slerp, and how uncertain it is there
    ok = orientation.valid
    # a stand: the track had no direction, so the yaw was held, or solved against a track direction held from the
    # motion before (wrong by however far the device turned in a gap since): neither is a solved yaw
    standing = ~iv.moving
    # where the gyro frame oriented the run it turns every sample (a hand moves within a GPS interval), else Slerp
    # between the solved intervals
    orient_at = frame.rotation_at if frame is not None else orientation.slerp()
    gaps = gap_model(orient_at, orientation.t[ok], orientation.euler[ok], orientation.sigma[ok], gps.t, t,
                     log.imu.gyro, _bias_sigma(orientation, options.orientation, parts, rigid=frame is None),
                     standing=standing[ok])
    notes += gaps.notes
    # where GPS covers the run, how far the IMU's velocity change misses the GPS's at each gap's time scale: beyond
    # what the smoother assumes, that is noise the IMU carries into the gap too (a hand's swing, a lever arm)
    misfit = _imu_misfit(t, gaps.enu(t, acc, orientation.bias), iv, gps)
    # with a gyro, the same misfit with the orientation a gyro span has, over windows where GPS covers the run
    gyro_misfit = None
    if log.imu.gyro is not None and any(span.gyro for span in gaps.spans):
        gyro = log.imu.gyro - (gaps.gyro_bias if gaps.gyro_bias is not None else 0.0)
        moving_t = orientation.t[ok][~standing[ok]]
        gyro_misfit = GyroTrack.build(t, acc - orientation.bias, gyro, moving_t, orient_at, gps.t, gps.vel,
                                      gps.sigma_vel).relative_power
    a_enu, a_noise = gaps.rotate(t, acc, orientation.bias, misfit, options.smoother.accel_noise, gyro_misfit)

    def gap_noise(nodes):
        return a_noise[np.clip(np.searchsorted(t, nodes), 0, len(t) - 1)]

    # 4. final smoothing: one pass over the whole log, so position and velocity carry across every GPS gap
    result = smooth(t, a_enu, gps.t, gps.vel, gps.sigma_vel, gps_enu, gps.sigma_pos, options.smoother,
                    progress=progress, extra_accel_noise=gap_noise)
    # 5. where the device stood inside a gap (the IMU as quiet as the run's stands, and the bridge slow there):
    #    again, with zero-velocity measurements at those nodes
    zero_velocity, stood = _stands_in_gaps(t, acc, log.imu.gyro, gps, gaps, result)
    if zero_velocity is not None:
        notes.append(f"stood still inside GPS gaps for {stood:.1f} s (the IMU as quiet as the run's stands): "
                     "zero-velocity measurements there")
        result = smooth(t, a_enu, gps.t, gps.vel, gps.sigma_vel, gps_enu, gps.sigma_pos, options.smoother,
                        progress=progress, extra_accel_noise=gap_noise, zero_velocity=zero_velocity)
    residual = np.full((len(gps), 3), np.nan)
    ok = result.gps_index >= 0
    residual[ok] = gps.vel[ok] - result.vel[result.gps_index[ok]]
    # IMU-only check: the velocity change the IMU integrates over each interval against the GPS's
    bias_at = np.stack([np.interp(t, result.t, result.bias[:, i]) for i in range(3)], axis=1)
    nodes, cum = cumulative_integral(t, a_enu - bias_at)
    dv_imu = (interval_means(nodes, cum, iv.t0, iv.t1) * (iv.t1 - iv.t0)[:, None])
    imu_residual = np.diff(gps.vel, axis=0) - dv_imu
    imu_residual[~iv.usable] = np.nan
    return PostResult(log, delay, estimate, orientation, iv, t, a_enu, result, origin, gps_enu, residual,
                      imu_residual, gaps, notes, options, frame)
