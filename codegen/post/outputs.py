"""What `deadreckon post` writes: trajectory CSV, GPX, per-interval angles, the report (text + JSON), plots.

Every file is made in memory and handed to `outdir.write_files`, which only replaces what post itself wrote.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from codegen.post.bridge import hermite_bridge
from codegen.post.geodesy import enu_to_geodetic
from codegen.post.orientation import (
    FLAG_GIMBAL,
    FLAG_GPS_GAP,
    FLAG_LM_WAHBA,
    FLAG_NO_IMU,
    FLAG_POOR_FIT,
    FLAG_STATIONARY,
    FLAG_YAW_HELD,
)
from codegen.post.mappage import MapLayers, map_page
from codegen.post.outdir import write_files
from codegen.post.pipeline import PostResult

GPS_UTC_LEAP_SECONDS = 18  # s, GPST - UTC since 2017-01-01
SIGMA_SHADE = "#fbd9b5"  # pale orange: the 1-sigma region of what was dead-reckoned
REPORT_LIST_MAX = 40  # rows of a list in report.txt (report.json has them all)


@dataclass
class TimeZero:
    """The one zero every plot and report counts time from: the first GPS epoch, and what it is in UTC."""

    t: float  # s, on the log's time axis
    utc: datetime | None  # None when the log's times carry no date (seconds since some start)

    @property
    def label(self) -> str:
        """'s after ...' wording for axis labels and report lines."""
        if self.utc is None:
            return "the first GPS epoch (the log's times carry no date)"
        return f"the first GPS epoch, {self.utc.strftime('%Y-%m-%d %H:%M:%S.%f')[:-5]} UTC"


def time_zero(result: PostResult) -> TimeZero:
    t0 = float(result.log.gps.t[0])
    scale = result.log.time_scale
    if scale not in ("gpst", "utc"):
        return TimeZero(t0, None)
    leap = GPS_UTC_LEAP_SECONDS if scale == "gpst" else 0
    return TimeZero(t0, datetime.fromtimestamp(t0 - leap, tz=timezone.utc))


def strict_json(value, reasons: dict[str, str], unknown: dict[str, str], key: str = ""):
    """`value` with every NaN or infinity replaced by null, and for each top-level key that held one, why it is unknown
    (from `reasons`, else a general wording) in `unknown`: JSON parsers reject NaN and Infinity."""
    if isinstance(value, dict):
        return {k: strict_json(v, reasons, unknown, key or k) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v, reasons, unknown, key) for v in value]
    if isinstance(value, (float, np.floating)):
        if np.isfinite(value):
            return float(value)
        unknown.setdefault(key, reasons.get(key, "not determined from this log"))
        return None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def _finite_max(values: np.ndarray) -> float:
    finite = np.asarray(values, dtype=float)[np.isfinite(values)]
    return float(finite.max()) if finite.size else float("nan")


HALF_TURN_DEG = 180.0  # an angle's 1-sigma above this says nothing about the angle


def _column_medians(values: np.ndarray) -> list[float]:
    """Median of each column's finite values (NaN for a column without any), without numpy's all-NaN warning."""
    return [float(np.median(c[np.isfinite(c)])) if np.isfinite(c).any() else float("nan") for c in values.T]


def trajectory_rows(result: PostResult) -> dict[str, np.ndarray]:
    tr = result.track
    lat, lon, h = enu_to_geodetic(tr.pos, result.origin)
    rot = result.gaps.rotation(tr.t)
    zyx = np.degrees(rot.as_euler("ZYX"))
    no_height = not np.isfinite(result.log.gps.h).any()
    return {
        "t": tr.t, "lat": lat, "lon": lon, "h": np.full(len(h), np.nan) if no_height else h,
        "east": tr.pos[:, 0], "north": tr.pos[:, 1], "up": tr.pos[:, 2],
        "v_east": tr.vel[:, 0], "v_north": tr.vel[:, 1], "v_up": tr.vel[:, 2],
        "speed": np.hypot(tr.vel[:, 0], tr.vel[:, 1]),
        "sigma_east": tr.sigma_pos[:, 0], "sigma_north": tr.sigma_pos[:, 1],
        "sigma_v_east": tr.sigma_vel[:, 0], "sigma_v_north": tr.sigma_vel[:, 1],
        "roll_deg": zyx[:, 2], "pitch_deg": zyx[:, 1], "yaw_deg": zyx[:, 0],
    }


def _csv_text(columns: dict[str, np.ndarray], formats: dict[str, str]) -> str:
    names = list(columns)
    lines = [",".join(names)]
    for i in range(len(columns[names[0]])):
        lines.append(",".join(_fmt(columns[n][i], formats.get(n, "{:.4f}")) for n in names))
    return "\n".join(lines) + "\n"


def _fmt(value, fmt: str) -> str:
    if isinstance(value, str):
        return value
    return "" if not np.isfinite(value) else fmt.format(value)


def trajectory_csv(result: PostResult) -> str:
    return _csv_text(trajectory_rows(result), {"t": "{:.3f}", "lat": "{:.8f}", "lon": "{:.8f}", "h": "{:.3f}"})


def gpx_text(result: PostResult) -> str:
    rows = trajectory_rows(result)
    stamp = result.log.time_scale in ("gpst", "utc")
    leap = GPS_UTC_LEAP_SECONDS if result.log.time_scale == "gpst" else 0
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           '<gpx version="1.1" creator="deadreckon post" xmlns="http://www.topografix.com/GPX/1/1">',
           f"<trk><name>{escape(result.log.name)}</name><trkseg>"]
    for i in range(len(rows["t"])):
        point = f'<trkpt lat="{rows["lat"][i]:.8f}" lon="{rows["lon"][i]:.8f}">'
        if np.isfinite(rows["h"][i]):
            point += f"<ele>{rows['h'][i]:.3f}</ele>"
        if stamp:
            utc = datetime.fromtimestamp(rows["t"][i] - leap, tz=timezone.utc)
            point += f"<time>{utc.strftime('%Y-%m-%dT%H:%M:%S.%f')[:-3]}Z</time>"
        out.append(point + "</trkpt>")
    out.append("</trkseg></trk></gpx>")
    return "\n".join(out) + "\n"


def angles_csv(result: PostResult) -> str:
    o = result.orientation
    e, s = np.degrees(o.euler), np.degrees(o.sigma)
    return _csv_text({
        "t": o.t, "roll_deg": e[:, 0], "pitch_deg": e[:, 1], "yaw_deg": e[:, 2],
        "sigma_roll_deg": s[:, 0], "sigma_pitch_deg": s[:, 1], "sigma_yaw_deg": s[:, 2],
        "horizontal_accel": o.horizontal_accel, "window_horizontal_accel": o.window_horizontal_accel,
        "chi2": o.chi2, "lm_vs_wahba_deg": o.lm_vs_wahba_deg,
        "flags": np.array([" ".join(f) for f in o.flags], dtype=object),
    }, {"t": "{:.3f}", "lm_vs_wahba_deg": "{:.2e}"})


@dataclass
class Stretch:
    """A stretch of the run the report lists: a GPS gap, or consecutive intervals with the same flags."""

    t0: float  # s, on the log's time axis
    t1: float
    what: str
    count: int = 1  # epochs missing (gap) or intervals (flags)
    worst_sigma: float = float("nan")  # m, largest horizontal 1-sigma (east or north) inside
    hermite_difference: float = float("nan")  # m, largest distance from the GPS-only cubic Hermite bridge
    bridged_by: str = ""


def gap_stretches(result: PostResult) -> list[Stretch]:
    """The GPS gaps, each with its length, worst 1-sigma, how its orientation was had, and how far the bridge goes
    from the cubic Hermite bridge of the GPS positions and velocities at its two ends."""
    tr, gps = result.track, result.log.gps
    out = []
    for span in result.gaps.spans:
        gap = span.gap
        inside = (tr.t > gap.t0) & (tr.t < gap.t1)
        worst = float(np.max(tr.sigma_pos[inside, :2])) if inside.any() else float("nan")
        difference = float("nan")
        a = gap.index
        if inside.any() and np.isfinite(result.gps_enu[[a, a + 1], :2]).all():
            h, _ = hermite_bridge(tr.t[inside], gap.t0, result.gps_enu[a, :2], gps.vel[a, :2], gap.t1,
                                  result.gps_enu[a + 1, :2], gps.vel[a + 1, :2])
            difference = float(np.max(np.hypot(*(tr.pos[inside, :2] - h).T)))
        out.append(Stretch(gap.t0, gap.t1, "gps-gap", gap.missing, worst, difference,
                           "gyro" if span.gyro else "accelerometer, orientation interpolated"))
    return out


def flag_stretches(result: PostResult) -> list[Stretch]:
    """Consecutive GPS intervals with the same flags, merged (a standing start is one row, not forty)."""
    o, iv = result.orientation, result.intervals
    out: list[Stretch] = []
    for k, flags in enumerate(o.flags):
        if not flags:
            continue
        what = " ".join(flags)
        if out and out[-1].what == what and out[-1].t1 == iv.t0[k]:
            out[-1].t1 = float(iv.t1[k])
            out[-1].count += 1
        else:
            out.append(Stretch(float(iv.t0[k]), float(iv.t1[k]), what))
    return out


def options_summary(result: PostResult) -> dict:
    o = result.options
    return {
        "velocity_only": not o.smoother.use_positions,
        "delay_given_s": o.delay,
        "max_lag_s": o.max_lag,
        "window_intervals": o.orientation.half_window,
        "min_horizontal_accel_mps2": o.orientation.min_horizontal_accel,
        "estimate_bias": o.orientation.estimate_bias,
        "calibration": o.calibration is not None,
        "rate_hz": o.smoother.rate,
        "gyro_used_in_gaps": result.log.imu.gyro is not None,
    }


def _stretch_json(s: Stretch, t0: float, gap: bool = False) -> dict:
    out = {"start_s": round(s.t0 - t0, 3), "end_s": round(s.t1 - t0, 3), "length_s": round(s.t1 - s.t0, 3),
           "what": s.what, "count": s.count}
    if gap:
        out.update(worst_sigma_m=None if not np.isfinite(s.worst_sigma) else round(s.worst_sigma, 3),
                   hermite_difference_m=None if not np.isfinite(s.hermite_difference) else round(s.hermite_difference, 3),
                   bridged_by=s.bridged_by)
    return out


def summary(result: PostResult) -> dict:
    o, est, tr = result.orientation, result.delay_estimate, result.track
    valid = o.valid
    e = np.degrees(o.euler[valid])
    sig = np.degrees(o.sigma[valid])
    sig[sig > HALF_TURN_DEG] = np.nan  # a 1-sigma beyond half a turn leaves the angle undetermined: no figure
    flags = {name: int(sum(name in f for f in o.flags)) for name in
             (FLAG_YAW_HELD, FLAG_STATIONARY, FLAG_POOR_FIT, FLAG_LM_WAHBA, FLAG_NO_IMU, FLAG_GPS_GAP, FLAG_GIMBAL)}
    res = result.velocity_residual
    ok = np.isfinite(res).all(axis=1)
    m = o.mounting
    distance = float(np.sum(np.hypot(*np.diff(tr.pos[:, :2], axis=0).T)))
    zero = time_zero(result)
    t0 = zero.t
    gaps = gap_stretches(result)
    velocity_only = not result.options.smoother.use_positions
    reasons = _unknown_reasons(result)
    unknown: dict[str, str] = {}
    report = {
        "log": result.log.name,
        "options": options_summary(result),
        "imu_samples": len(result.log.imu), "imu_rate_hz": round(result.log.imu.rate_hz, 3),
        "gps_epochs": len(result.log.gps), "duration_s": round(float(tr.t[-1] - tr.t[0]), 3),
        "first_gps_epoch_s": t0,
        "time_zero_utc": None if zero.utc is None else zero.utc.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z",
        "time_scale": result.log.time_scale,
        "delay_s": result.delay,
        # at the search's edge the delay may lie beyond it: the misfit's curvature there bounds nothing
        "delay_sigma_s": None if est is None else float("nan") if est.at_edge else est.sigma,  # NaN: null + reason
        "delay_correlation": None if est is None else est.correlation,
        "delay_estimated": est is not None,
        "delay_search_at_edge": None if est is None else bool(est.at_edge),
        "accel_bias_sensor_mps2": o.bias.tolist(),
        "mounting_relative_to_track_deg": None if m is None else np.degrees(m.euler).tolist(),
        "mounting_sigma_deg": None if m is None else np.degrees(m.sigma_euler).tolist(),
        "mounting_fit_chi2": None if m is None else m.chi2,
        "bias_rejected": None if m is None else m.bias_rejected,
        "angles_median_deg": np.median(e, axis=0).tolist() if len(e) else None,
        "angles_min_deg": e.min(axis=0).tolist() if len(e) else None,
        "angles_max_deg": e.max(axis=0).tolist() if len(e) else None,
        "angle_sigma_median_deg": _column_medians(sig) if len(e) else None,
        "intervals": len(o.t), "intervals_solved": int(valid.sum()),
        "flags": flags,
        "flagged_stretches": [_stretch_json(s, t0) for s in flag_stretches(result)],
        "gps_gaps": [_stretch_json(s, t0, gap=True) for s in gaps],
        "dead_reckoned_s": round(float(tr.t[-1] - tr.t[0]), 3) if velocity_only else round(sum(s.t1 - s.t0 for s in gaps), 3),
        "position_sigma_max_m": float(np.max(tr.sigma_pos[:, :2])),
        "lm_vs_wahba_max_deg": _finite_max(o.lm_vs_wahba_deg),
        "velocity_residual_rms_mps": result.velocity_residual_rms,
        "velocity_residual_rms_enu_mps": np.sqrt(np.mean(res[ok] ** 2, axis=0)).tolist() if ok.any() else [np.nan] * 3,
        "velocity_residual_max_mps": _finite_max(np.abs(res[ok])),
        "imu_interval_velocity_residual_rms_mps": result.imu_velocity_residual_rms,
        "distance_m": distance,
        "notes": result.notes,
    }
    if zero.utc is None:
        unknown["time_zero_utc"] = "the log's times are seconds since its start, without a date"
    if est is None:
        for key in ("delay_sigma_s", "delay_correlation", "delay_search_at_edge"):
            unknown[key] = "the delay was given (--delay), not searched"
    if m is None:
        for key in ("mounting_relative_to_track_deg", "mounting_sigma_deg", "mounting_fit_chi2", "bias_rejected"):
            unknown[key] = "fewer than 6 moving GPS intervals with IMU samples: no whole-run mounting fit"
    report = strict_json(report, reasons, unknown)
    report["unknown"] = unknown
    return report


def _unknown_reasons(result: PostResult) -> dict[str, str]:
    """Why a report value can come out unknown, in this run's terms (strict_json uses the ones that apply)."""
    est, o = result.delay_estimate, result.orientation
    reasons = {}
    if est is not None:
        reasons["delay_sigma_s"] = ("the delay search hit its edge: the delay lies at or beyond the searched range"
                                    if est.at_edge else
                                    "the misfit has no curvature at the delay: the data do not fix it")
        reasons["delay_correlation"] = "the IMU's velocity changes do not vary over the run"
    held = np.array([FLAG_YAW_HELD in f for f in o.flags])
    reasons["angle_sigma_median_deg"] = (
        f"the yaw was held (too little horizontal acceleration: carried over, not solved) on {int(held.sum())} of "
        f"{int(o.valid.sum())} solved intervals, and no fit of the others determined it (a 1-sigma beyond "
        f"{HALF_TURN_DEG:g} deg counts as undetermined): it has no 1-sigma")
    reasons["mounting_sigma_deg"] = "the whole-run mounting fit does not determine this angle (too little motion)"
    reasons["mounting_fit_chi2"] = "the whole-run mounting fit has no residual degrees of freedom"
    reasons["lm_vs_wahba_max_deg"] = "no interval was solved by both methods"
    for name in ("velocity_residual_rms_mps", "velocity_residual_rms_enu_mps", "velocity_residual_max_mps",
                 "imu_interval_velocity_residual_rms_mps"):
        reasons[name] = "no GPS epoch inside the IMU's span to compare with"
    reasons["gps_gaps"] = "the smoother has no row inside the gap, or a gap end has no GPS position"
    return reasons


def _f(value, spec: str, missing: str = "unknown") -> str:
    """A report number, or `missing` where strict_json made it null."""
    return missing if value is None else format(value, spec)


def report_text(result: PostResult) -> str:
    s = summary(result)
    opt = s["options"]
    lines = [f"deadreckon post: {s['log']}", ""]
    used = ["positions: " + ("NOT used (--velocity-only: the whole path is IMU + Doppler dead reckoning)"
                             if opt["velocity_only"] else "GPS positions and Doppler velocities")]
    used.append("delay " + ("given" if opt["delay_given_s"] is not None else f"searched within +-{opt['max_lag_s']:g} s"))
    used.append(f"window +-{opt['window_intervals']} intervals, yaw held below {opt['min_horizontal_accel_mps2']:g} m/s^2")
    used.append("bias " + ("sought (see acc bias)" if opt["estimate_bias"] else "not estimated (--no-bias)"))
    if opt["calibration"]:
        used.append("calibration given")
    used.append(f"{opt['rate_hz']:g} rows/s")
    used.append("gyro " + ("used across GPS gaps" if opt["gyro_used_in_gaps"] else "not in the log"))
    lines.append("options    " + "; ".join(used))
    lines.append(f"input      {s['imu_samples']} IMU samples at {s['imu_rate_hz']:.1f} Hz, {s['gps_epochs']} GPS epochs, "
                 f"{s['duration_s']:.1f} s, {s['distance_m']:.1f} m travelled")
    for note in s["notes"]:
        lines.append(f"           {note}")
    if s["delay_estimated"]:
        sigma = "unbounded" if s["delay_sigma_s"] is None else f"{s['delay_sigma_s'] * 1e3:.1f} ms"
        lines.append(f"delay      {s['delay_s'] * 1e3:+.1f} ms +- {sigma} (IMU stamps late by this; "
                     f"correlation {_f(s['delay_correlation'], '.3f')})" + ("; SEARCH HIT ITS EDGE, see the note above"
                                                                            if s["delay_search_at_edge"] else ""))
    else:
        lines.append(f"delay      {s['delay_s'] * 1e3:+.1f} ms (given)")
    b = np.array(s["accel_bias_sensor_mps2"]) / 9.80665e-3
    if result.orientation.mounting is not None and result.orientation.mounting.bias_rejected:
        lines.append("acc bias   not estimated: the device does not sit rigidly relative to the track (mounting fit "
                     "chi2 too high), so a bias cannot be told from a tilt; give --accel-offset from a calibration")
    else:
        lines.append(f"acc bias   x {b[0]:+.1f} mg, y {b[1]:+.1f} mg, z {b[2]:+.1f} mg (sensor frame, removed)")
    if s["mounting_relative_to_track_deg"] is not None:
        m, ms = s["mounting_relative_to_track_deg"], s["mounting_sigma_deg"]
        lines.append(f"mounting   roll {m[0]:+.2f}+-{_f(ms[0], '.2f')}, pitch {m[1]:+.2f}+-{_f(ms[1], '.2f')}, "
                     f"yaw vs track {m[2]:+.2f}+-{_f(ms[2], '.2f')} deg (fit chi2 "
                     f"{_f(s['mounting_fit_chi2'], '.2f')}; >>1: the device turns on its own)")
    if s["angles_median_deg"] is not None:
        med, lo, hi, sd = s["angles_median_deg"], s["angles_min_deg"], s["angles_max_deg"], s["angle_sigma_median_deg"]
        for i, name in enumerate(("roll", "pitch", "yaw")):
            typical = (f"typical 1-sigma {sd[i]:.2f} deg" if sd[i] is not None else
                       "no 1-sigma (" + s["unknown"].get("angle_sigma_median_deg", "not determined") + ")")
            lines.append(f"{name:<10s} median {med[i]:+8.2f} deg, range {lo[i]:+8.2f}..{hi[i]:+8.2f}, {typical}")
    lines.append(f"intervals  {s['intervals_solved']} of {s['intervals']} solved; flagged: "
                 + ", ".join(f"{k} {v}" for k, v in s["flags"].items()))
    lines.append(f"LM vs closed form (Wahba): max {_f(s['lm_vs_wahba_max_deg'], '.2e')} deg")
    r = s["velocity_residual_rms_enu_mps"]
    lines.append(f"velocity   GPS - smoothed RMS {_f(s['velocity_residual_rms_mps'], '.3f')} m/s (E {_f(r[0], '.3f')}, "
                 f"N {_f(r[1], '.3f')}, U {_f(r[2], '.3f')}), max {_f(s['velocity_residual_max_mps'], '.3f')}")
    lines.append("           GPS - IMU velocity change per interval RMS "
                 f"{_f(s['imu_interval_velocity_residual_rms_mps'], '.3f')} m/s")
    zero = time_zero(result)
    lines.append("")
    if opt["velocity_only"]:
        lines.append(f"dead reckoned: all {s['dead_reckoned_s']:.1f} s (--velocity-only: positions from the IMU and "
                     f"Doppler alone); worst horizontal 1-sigma {s['position_sigma_max_m']:.2f} m")
    gaps = s["gps_gaps"]
    if gaps:
        lines.append(f"GPS gaps (epochs missing; bridged by the IMU between the epochs around them): {len(gaps)}, "
                     f"{sum(g['length_s'] for g in gaps):.1f} s in all"
                     + (f"; the {REPORT_LIST_MAX} longest, in time order" if len(gaps) > REPORT_LIST_MAX else ""))
        lines.append(f"  (s after {zero.label})")
        lines.append("  from [s]    to [s]   length  missing  worst 1-sigma  from GPS-only bridge  orientation by")
        shown = sorted(sorted(gaps, key=lambda g: -g["length_s"])[:REPORT_LIST_MAX], key=lambda g: g["start_s"])
        for g in shown:
            sigma = "-" if g["worst_sigma_m"] is None else f"{g['worst_sigma_m']:.2f} m"
            diff = "-" if g["hermite_difference_m"] is None else f"{g['hermite_difference_m']:.2f} m"
            lines.append(f"  {g['start_s']:8.2f}  {g['end_s']:8.2f}  {g['length_s']:6.2f} s  {g['count']:7d}  "
                         f"{sigma:>13s}  {diff:>20s}  {g['bridged_by']}")
        lines.append("  (1-sigma: per axis, east or north; 'from GPS-only bridge': largest distance from the cubic "
                     "through the GPS positions and velocities at the two ends)")
    else:
        lines.append("GPS gaps: none (no epoch missing)")
    flagged = s["flagged_stretches"]
    if flagged:
        lines.append("")
        lines.append(f"flagged stretches of GPS intervals (s after {zero.label}): {len(flagged)}"
                     + (f", the first {REPORT_LIST_MAX}" if len(flagged) > REPORT_LIST_MAX else ""))
        lines.append("  yaw-held: too little horizontal acceleration, yaw carried over; stationary: no track direction;")
        lines.append("  poor-fit: the window's vectors disagree with one rotation; lm-wahba: LM and closed form differ")
        lines.append("  (on a yaw-held interval: the tilt differs, i.e. the held yaw does not suit the window);")
        lines.append("  gimbal: pitch near +-90 deg, the rotation is sound but roll and yaw are not separable;")
        lines.append("  gps-gap: epochs missing, the interval is not solved (see GPS gaps)")
        for f in flagged[:REPORT_LIST_MAX]:
            lines.append(f"  {f['start_s']:8.2f} .. {f['end_s']:8.2f} ({f['count']:3d} interval{'s' if f['count'] > 1 else ' '}): "
                         f"{f['what']}")
    return "\n".join(lines) + "\n"


def _shade(ax, stretches: list[Stretch], t0: float, color: str, label: str | None) -> None:
    for i, s in enumerate(stretches):
        ax.axvspan(s.t0 - t0, s.t1 - t0, color=color, alpha=0.25, lw=0, label=label if i == 0 else None)


def _break_wraps(x: np.ndarray, y: np.ndarray, *along: np.ndarray,
                 limit: float = 180.0) -> tuple[np.ndarray, ...]:
    """NaN between consecutive points of y that jump by more than half a turn (a wrap, not a motion); the arrays
    `along` (a band around y) are broken at y's wraps, so every array returned has x's new length."""
    jump = np.flatnonzero(np.abs(np.diff(y)) > limit)
    return tuple(np.insert(a.astype(float), jump + 1, np.nan) for a in (x, y, *along))


def plots(result: PostResult) -> dict[str, bytes]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    zero = time_zero(result)
    gaps, flagged = gap_stretches(result), flag_stretches(result)
    flagged = [f for f in flagged if "gps-gap" not in f.what]
    out = {"angles.png": _angles_png(plt, result, zero, gaps, flagged),
           "velocity.png": _velocity_png(plt, result, zero, gaps),
           "trajectory.png": _trajectory_png(plt, result, gaps, flagged)}
    est = result.delay_estimate
    if est is not None and len(est.lags) > 1:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        ax.plot(est.lags * 1e3, est.cost, color="tab:blue", label="misfit of the first search")
        ax.axvline(result.delay * 1e3, color="tab:red", lw=1.2, label=f"chosen delay {result.delay * 1e3:+.1f} ms")
        if est.at_edge:
            ax.axvspan(est.lags[0] * 1e3, est.lags[-1] * 1e3, color="tab:red", alpha=0.08,
                       label="searched range (its edge was hit)")
        ax.set_title(f"{result.log.name}: delay search")
        ax.set_xlabel("trial lag [ms] (IMU stamps late by this)")
        ax.set_ylabel("normalised misfit")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=3, frameon=False)
        out["delay.png"] = _png(fig)
    return out


def _time_label(zero: TimeZero) -> str:
    return f"time [s] after {zero.label}"


def _angles_png(plt, result: PostResult, zero: TimeZero, gaps: list[Stretch], flagged: list[Stretch]) -> bytes:
    """Roll, pitch, yaw per GPS interval with their 1-sigma bands, the angles across gaps, and a panel of the
    1-sigma itself (a yaw band of a degree cannot be seen on a 360-degree axis)."""
    o, tr = result.orientation, result.track
    t0 = zero.t
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(11, 9.5), gridspec_kw={"height_ratios": [1, 1, 1.3, 1]})
    bridged = result.gaps.inside(tr.t)
    tb = np.where(bridged, tr.t, np.nan)  # NaN outside the gaps breaks the line there
    zyx = np.degrees(result.gaps.rotation(tr.t).as_euler("ZYX"))
    across = {"roll": zyx[:, 2], "pitch": zyx[:, 1], "yaw": zyx[:, 0]}
    held = np.array([FLAG_YAW_HELD in f for f in o.flags])
    for i, name in enumerate(("roll", "pitch", "yaw")):
        ax = axes[i]
        e, s = np.degrees(o.euler[:, i]), np.minimum(np.degrees(o.sigma[:, i]), 30.0)
        _shade(ax, flagged, t0, "0.6", "flagged intervals")
        _shade(ax, gaps, t0, "tab:orange", "GPS gap (bridged)")
        if name == "yaw":
            # the band is drawn per stretch between wraps so it never spans the +-180 jump
            x, y, lo, hi = _break_wraps(o.t - t0, e, e - s, e + s)
            band = np.isfinite(lo) & np.isfinite(hi)
            ax.fill_between(x, np.where(band, lo, np.nan), np.where(band, hi, np.nan), color="tab:blue", alpha=0.35,
                            lw=0, label="1 sigma")
        else:
            x, y = o.t - t0, e
            ax.fill_between(x, e - s, e + s, alpha=0.35, color="tab:blue", lw=0, label="1 sigma")
        ax.plot(x, y, "-", lw=0.9, color="tab:blue", label="per GPS interval")
        if bridged.any():
            xb, yb = _break_wraps(tb - t0, across[name])
            ax.plot(xb, yb, "--", lw=0.9, color="tab:red", label="across gaps (gyro or interpolated)")
        ax.set_ylabel(f"{name} [deg]")
    axes[2].set_ylim(-185.0, 185.0)
    axes[2].set_yticks([-180, -90, 0, 90, 180])
    sig = axes[3]
    yaw_gap, tilt_gap = result.gaps.angle_sigma(tr.t)
    for i, (name, colour) in enumerate((("roll", "tab:green"), ("pitch", "tab:purple"), ("yaw", "tab:blue"))):
        sig.plot(o.t - t0, np.degrees(o.sigma[:, i]), ".", ms=3, color=colour, label=f"{name} 1-sigma")
    if bridged.any():
        sig.plot(tb - t0, np.degrees(np.where(bridged, yaw_gap, np.nan)), "--", lw=1.0, color="tab:red",
                 label="yaw 1-sigma across gaps")
    if held.any():
        sig.plot(o.t[held] - t0, np.full(held.sum(), 0.0), "|", ms=8, color="0.3",
                 label="yaw held (not solved: no 1-sigma)")
    sig.set_yscale("symlog", linthresh=0.1)
    sig.set_ylabel("1-sigma [deg]")
    _shade(sig, gaps, t0, "tab:orange", None)
    axes[-1].set_xlabel(_time_label(zero))
    handles, labels = [], []
    for ax in (axes[0], axes[3]):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="upper center", ncol=5, frameon=False, bbox_to_anchor=(0.5, 0.995), fontsize=8)
    fig.suptitle(f"{result.log.name}: orientation (yaw from East, wraps at +-180 deg)", y=0.945, fontsize=10)
    return _png(fig, top=0.91)


def _velocity_png(plt, result: PostResult, zero: TimeZero, gaps: list[Stretch]) -> bytes:
    """Left: the velocities (GPS Doppler and smoothed); right, on their own scale: the residuals at the GPS epochs
    (GPS - smoothed) and per interval (GPS velocity change - the IMU's)."""
    tr, gps = result.track, result.log.gps
    t0 = zero.t
    fig, axes = plt.subplots(3, 2, sharex=True, figsize=(13, 7.5), gridspec_kw={"width_ratios": [1.4, 1]})
    for i, name in enumerate(("east", "north", "up")):
        left, right = axes[i]
        for ax in (left, right):
            _shade(ax, gaps, t0, "tab:orange", "GPS gap (bridged)")
        left.plot(tr.t - t0, tr.vel[:, i], lw=0.9, color="tab:blue", label="IMU + GPS smoothed")
        left.plot(gps.t - t0, gps.vel[:, i], ".", ms=2.5, color="black", label="GPS Doppler")
        left.set_ylabel(f"v {name} [m/s]")
        right.axhline(0.0, color="0.5", lw=0.6)
        right.plot(gps.t[1:] - t0, result.imu_velocity_residual[:, i], "+", ms=3, color="tab:purple",
                   label="GPS - IMU velocity change per interval")
        right.plot(gps.t - t0, result.velocity_residual[:, i], ".", ms=3, color="tab:red",
                   label="GPS - smoothed at each epoch")
        right.set_ylabel(f"residual {name} [m/s]")
    axes[-1, 0].set_xlabel(_time_label(zero))
    axes[-1, 1].set_xlabel("time [s], same zero")
    handles, labels = [], []
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="upper center", ncol=5, frameon=False, bbox_to_anchor=(0.5, 0.995), fontsize=8)
    fig.suptitle(f"{result.log.name}: velocity and residuals", y=0.95, fontsize=10)
    return _png(fig, top=0.91)


def _trajectory_png(plt, result: PostResult, gaps: list[Stretch], flagged: list[Stretch]) -> bytes:
    """The path in the plane: GPS fixes, the reconstruction, what was dead-reckoned (gaps, or all of it with
    --velocity-only) with its 1-sigma shaded, flagged stretches, start and end."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Ellipse

    tr = result.track
    velocity_only = not result.options.smoother.use_positions
    fig, ax = plt.subplots(figsize=(9, 9))
    ax.plot(result.gps_enu[:, 0], result.gps_enu[:, 1], ".", ms=3, color="0.25", alpha=0.7, zorder=2,
            label="GPS fixes")
    path_label = "dead-reckoned (IMU + Doppler, --velocity-only)" if velocity_only else "reconstructed (IMU + GPS)"
    ax.plot(tr.pos[:, 0], tr.pos[:, 1], lw=1.2, color="tab:blue", zorder=3, label=path_label)
    for i, f in enumerate(flagged):
        inside = (tr.t >= f.t0) & (tr.t <= f.t1)
        ax.plot(tr.pos[inside, 0], tr.pos[inside, 1], lw=2.5, color="tab:purple", alpha=0.5, zorder=3,
                label="flagged intervals" if i == 0 else None)
    shaded = []
    for i, g in enumerate(gaps):
        inside = (tr.t >= g.t0) & (tr.t <= g.t1)
        ax.plot(tr.pos[inside, 0], tr.pos[inside, 1], lw=2.2, color="tab:orange", zorder=4,
                label="GPS gap, dead-reckoned" if i == 0 else None)
        shaded += [Ellipse((p[0], p[1]), 2 * s[0], 2 * s[1]) for p, s in zip(tr.pos[inside], tr.sigma_pos[inside])]
    if velocity_only:
        step = max(1, len(tr.t) // 400)
        shaded += [Ellipse((p[0], p[1]), 2 * s[0], 2 * s[1]) for p, s in zip(tr.pos[::step], tr.sigma_pos[::step])]
    if shaded:  # opaque and pale, under everything: overlapping ellipses do not darken into a blot
        ax.add_collection(PatchCollection(shaded, facecolor=SIGMA_SHADE, edgecolor="none", zorder=1))
        ax.fill([], [], color=SIGMA_SHADE, label="1-sigma where dead-reckoned")
    ax.plot(*tr.pos[0, :2], "^", ms=11, color="tab:green", mec="black", zorder=5, label="start")
    ax.plot(*tr.pos[-1, :2], "s", ms=10, color="tab:red", mec="black", zorder=5, label="end")
    ax.set_xlabel("east [m] from the first GPS fix")
    ax.set_ylabel("north [m] from the first GPS fix")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    distance = float(np.sum(np.hypot(*np.diff(tr.pos[:, :2], axis=0).T)))
    what = "dead-reckoned path (no GPS positions used)" if velocity_only else "reconstructed path"
    ax.set_title(f"{result.log.name}: {what}, {distance:.0f} m, {tr.t[-1] - tr.t[0]:.0f} s"
                 + (f", {len(gaps)} GPS gap(s) dead-reckoned" if gaps else ""), fontsize=11)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3, frameon=False, fontsize=9)
    return _png(fig)


def _png(fig, top: float | None = None) -> bytes:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    if top is not None:
        fig.subplots_adjust(top=top)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def map_layers(result: PostResult) -> MapLayers:
    tr = result.track
    lat, lon, _ = enu_to_geodetic(tr.pos, result.origin)
    gps = result.log.gps
    velocity_only = not result.options.smoother.use_positions

    def rows(t0: float, t1: float) -> np.ndarray:
        return np.flatnonzero((tr.t >= t0) & (tr.t <= t1))

    gaps = [rows(g.t0, g.t1) for g in gap_stretches(result)]
    flagged = [(rows(f.t0, f.t1), f.what) for f in flag_stretches(result) if "gps-gap" not in f.what]
    zero = time_zero(result)
    what = "dead-reckoned path (no GPS positions used)" if velocity_only else "reconstructed path"
    title = f"{result.log.name}: {what}, from {zero.label}"
    return MapLayers(title, tr.pos[:, :2], np.stack([lat, lon], axis=1), np.max(tr.sigma_pos[:, :2], axis=1),
                     result.gps_enu[:, :2], np.stack([gps.lat, gps.lon], axis=1), [g for g in gaps if len(g)],
                     [(i, w) for i, w in flagged if len(i) > 1], velocity_only)


def write_outputs(result: PostResult, folder: Path, plots_too: bool = True) -> dict[str, Path]:
    """All outputs into `folder` (see outdir: only files post wrote are ever replaced)."""
    contents = {
        "trajectory.csv": trajectory_csv(result).encode(),
        "trajectory.gpx": gpx_text(result).encode(),
        "trajectory.html": map_page(map_layers(result)).encode(),
        "angles.csv": angles_csv(result).encode(),
        "report.txt": report_text(result).encode(),
        "report.json": (json.dumps(summary(result), indent=2, allow_nan=False) + "\n").encode(),
    }
    if plots_too:
        contents.update(plots(result))
    written = write_files(folder, contents)
    names = {"trajectory.csv": "trajectory", "trajectory.gpx": "gpx", "trajectory.html": "map", "angles.csv": "angles",
             "report.txt": "report",
             "report.json": "summary"}
    return {names.get(n, f"plot_{Path(n).stem}"): p for n, p in written.items()}
