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
from codegen.post.outdir import write_files
from codegen.post.pipeline import PostResult

GPS_UTC_LEAP_SECONDS = 18  # s, GPST - UTC since 2017-01-01
REPORT_LIST_MAX = 40  # rows of a list in report.txt (report.json has them all)


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


def _stretch_json(s: Stretch, t0: float) -> dict:
    out = {"start_s": round(s.t0 - t0, 3), "end_s": round(s.t1 - t0, 3), "length_s": round(s.t1 - s.t0, 3),
           "what": s.what, "count": s.count}
    if s.what == "gps-gap":
        out.update(worst_sigma_m=None if not np.isfinite(s.worst_sigma) else round(s.worst_sigma, 3),
                   hermite_difference_m=None if not np.isfinite(s.hermite_difference) else round(s.hermite_difference, 3),
                   bridged_by=s.bridged_by)
    return out


def summary(result: PostResult) -> dict:
    o, est, tr = result.orientation, result.delay_estimate, result.track
    valid = o.valid
    e = np.degrees(o.euler[valid])
    sig = np.degrees(o.sigma[valid])
    flags = {name: int(sum(name in f for f in o.flags)) for name in
             (FLAG_YAW_HELD, FLAG_STATIONARY, FLAG_POOR_FIT, FLAG_LM_WAHBA, FLAG_NO_IMU, FLAG_GPS_GAP, FLAG_GIMBAL)}
    res = result.velocity_residual
    ok = np.isfinite(res).all(axis=1)
    m = o.mounting
    distance = float(np.sum(np.hypot(*np.diff(tr.pos[:, :2], axis=0).T)))
    t0 = float(result.log.gps.t[0])
    gaps = gap_stretches(result)
    velocity_only = not result.options.smoother.use_positions
    return {
        "log": result.log.name,
        "options": options_summary(result),
        "imu_samples": len(result.log.imu), "imu_rate_hz": round(result.log.imu.rate_hz, 3),
        "gps_epochs": len(result.log.gps), "duration_s": round(float(tr.t[-1] - tr.t[0]), 3),
        "first_gps_epoch_s": t0,
        "delay_s": result.delay,
        "delay_sigma_s": None if est is None else est.sigma,
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
        "angle_sigma_median_deg": np.nanmedian(sig, axis=0).tolist() if len(e) else None,
        "intervals": len(o.t), "intervals_solved": int(valid.sum()),
        "flags": flags,
        "flagged_stretches": [_stretch_json(s, t0) for s in flag_stretches(result)],
        "gps_gaps": [_stretch_json(s, t0) for s in gaps],
        "dead_reckoned_s": round(float(tr.t[-1] - tr.t[0]), 3) if velocity_only else round(sum(s.t1 - s.t0 for s in gaps), 3),
        "position_sigma_max_m": float(np.max(tr.sigma_pos[:, :2])),
        "lm_vs_wahba_max_deg": float(np.nanmax(o.lm_vs_wahba_deg)),
        "velocity_residual_rms_mps": result.velocity_residual_rms,
        "velocity_residual_rms_enu_mps": np.sqrt(np.mean(res[ok] ** 2, axis=0)).tolist(),
        "velocity_residual_max_mps": float(np.abs(res[ok]).max()),
        "imu_interval_velocity_residual_rms_mps": result.imu_velocity_residual_rms,
        "distance_m": distance,
        "notes": result.notes,
    }


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
        lines.append(f"delay      {s['delay_s'] * 1e3:+.1f} ms +- {s['delay_sigma_s'] * 1e3:.1f} ms (IMU stamps late by this; "
                     f"correlation {s['delay_correlation']:.3f})" + ("; SEARCH HIT ITS EDGE, see the note above"
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
        lines.append(f"mounting   roll {m[0]:+.2f}+-{ms[0]:.2f}, pitch {m[1]:+.2f}+-{ms[1]:.2f}, yaw vs track {m[2]:+.2f}+-{ms[2]:.2f} deg "
                     f"(fit chi2 {s['mounting_fit_chi2']:.2f}; >>1: the device turns on its own)")
    if s["angles_median_deg"] is not None:
        med, lo, hi, sd = s["angles_median_deg"], s["angles_min_deg"], s["angles_max_deg"], s["angle_sigma_median_deg"]
        for i, name in enumerate(("roll", "pitch", "yaw")):
            lines.append(f"{name:<10s} median {med[i]:+8.2f} deg, range {lo[i]:+8.2f}..{hi[i]:+8.2f}, typical 1-sigma {sd[i]:.2f} deg")
    lines.append(f"intervals  {s['intervals_solved']} of {s['intervals']} solved; flagged: "
                 + ", ".join(f"{k} {v}" for k, v in s["flags"].items()))
    lines.append(f"LM vs closed form (Wahba): max {s['lm_vs_wahba_max_deg']:.2e} deg")
    r = s["velocity_residual_rms_enu_mps"]
    lines.append(f"velocity   GPS - smoothed RMS {s['velocity_residual_rms_mps']:.3f} m/s (E {r[0]:.3f}, N {r[1]:.3f}, U {r[2]:.3f}), "
                 f"max {s['velocity_residual_max_mps']:.3f}")
    lines.append(f"           GPS - IMU velocity change per interval RMS {s['imu_interval_velocity_residual_rms_mps']:.3f} m/s")
    t0 = s["first_gps_epoch_s"]
    lines.append("")
    if opt["velocity_only"]:
        lines.append(f"dead reckoned: all {s['dead_reckoned_s']:.1f} s (--velocity-only: positions from the IMU and "
                     f"Doppler alone); worst horizontal 1-sigma {s['position_sigma_max_m']:.2f} m")
    gaps = s["gps_gaps"]
    if gaps:
        lines.append(f"GPS gaps (epochs missing; bridged by the IMU between the epochs around them): {len(gaps)}, "
                     f"{sum(g['length_s'] for g in gaps):.1f} s in all"
                     + (f"; the {REPORT_LIST_MAX} longest, in time order" if len(gaps) > REPORT_LIST_MAX else ""))
        lines.append(f"  (s after the first GPS epoch at {t0:.3f} s)")
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
        lines.append(f"flagged stretches of GPS intervals (s after the first GPS epoch at {t0:.3f} s): {len(flagged)}"
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


def _shade(ax, stretches: list[Stretch], t0: float, color: str, label: str) -> None:
    for i, s in enumerate(stretches):
        ax.axvspan(s.t0 - t0, s.t1 - t0, color=color, alpha=0.25, lw=0, label=label if i == 0 else None)


def _break_wraps(x: np.ndarray, y: np.ndarray, limit: float = 180.0) -> tuple[np.ndarray, np.ndarray]:
    """NaN between consecutive points that jump by more than half a turn (a wrap, not a motion)."""
    jump = np.flatnonzero(np.abs(np.diff(y)) > limit)
    return np.insert(x.astype(float), jump + 1, np.nan), np.insert(y.astype(float), jump + 1, np.nan)


def plots(result: PostResult) -> dict[str, bytes]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    o, tr, gps = result.orientation, result.track, result.log.gps
    t0 = tr.t[0]
    gaps = gap_stretches(result)
    flagged = flag_stretches(result)
    out = {}
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(11, 7.5))
    bridged = result.gaps.inside(tr.t)
    tb = np.where(bridged, tr.t, np.nan)  # NaN outside the gaps breaks the line there
    zyx = np.degrees(result.gaps.rotation(tr.t).as_euler("ZYX"))
    across = {"roll": zyx[:, 2], "pitch": zyx[:, 1], "yaw": zyx[:, 0]}
    for i, name in enumerate(("roll", "pitch", "yaw")):
        e, s = np.degrees(o.euler[:, i]), np.minimum(np.degrees(o.sigma[:, i]), 30.0)
        x, y = _break_wraps(o.t - t0, e) if name == "yaw" else (o.t - t0, e)
        _shade(axes[i], [f for f in flagged if "gps-gap" not in f.what], t0, "0.6", "flagged intervals")
        _shade(axes[i], gaps, t0, "tab:orange", "GPS gap (bridged)")
        axes[i].plot(x, y, "-", lw=0.9, color="tab:blue", label="per GPS interval")
        if bridged.any():
            xb, yb = _break_wraps(tb - t0, across[name])
            axes[i].plot(xb, yb, "--", lw=0.9, color="tab:red", label="across gaps (gyro or interpolated)")
        if name != "yaw":
            axes[i].fill_between(o.t - t0, e - s, e + s, alpha=0.3, color="tab:blue", lw=0, label="1 sigma")
        axes[i].set_ylabel(f"{name} [deg]")
    axes[2].set_ylim(-185.0, 185.0)
    axes[2].set_yticks([-180, -90, 0, 90, 180])
    axes[-1].set_xlabel(f"time [s] after {t0:.1f} s")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), frameon=False, bbox_to_anchor=(0.5, 0.995))
    fig.suptitle("orientation (yaw wraps at +-180 deg)", y=0.955, fontsize=10)
    out["angles.png"] = _png(fig, top=0.92)
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(11, 7.5))
    for i, name in enumerate(("east", "north", "up")):
        _shade(axes[i], gaps, t0, "tab:orange", "GPS gap (bridged)")
        axes[i].plot(gps.t - t0, gps.vel[:, i], ".", ms=3, label="GPS Doppler")
        axes[i].plot(tr.t - t0, tr.vel[:, i], lw=0.8, label="IMU + GPS smoothed")
        imu_only = gps.vel[1:, i] - result.imu_velocity_residual[:, i]  # previous epoch + IMU velocity change
        axes[i].plot(gps.t[1:] - t0, imu_only, "+", ms=3, label="previous GPS + IMU over the interval")
        axes[i].set_ylabel(f"v {name} [m/s]")
    axes[-1].set_xlabel(f"time [s] after {t0:.1f} s")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), frameon=False, bbox_to_anchor=(0.5, 0.995))
    out["velocity.png"] = _png(fig, top=0.94)
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(result.gps_enu[:, 0], result.gps_enu[:, 1], ".", ms=3, color="tab:blue", label="GPS")
    ax.plot(tr.pos[:, 0], tr.pos[:, 1], lw=1.0, color="tab:green", label="reconstructed")
    for i, g in enumerate(gaps):
        inside = (tr.t >= g.t0) & (tr.t <= g.t1)
        ax.plot(tr.pos[inside, 0], tr.pos[inside, 1], lw=2.0, color="tab:orange",
                label="bridged across a GPS gap" if i == 0 else None)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3, frameon=False)
    out["trajectory.png"] = _png(fig)
    est = result.delay_estimate
    if est is not None and len(est.lags) > 1:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        ax.plot(est.lags * 1e3, est.cost, color="tab:blue", label="misfit of the first search")
        ax.axvline(result.delay * 1e3, color="tab:red", lw=1.2, label=f"chosen delay {result.delay * 1e3:+.1f} ms")
        if est.at_edge:
            ax.axvspan(est.lags[0] * 1e3, est.lags[-1] * 1e3, color="tab:red", alpha=0.08,
                       label="searched range (its edge was hit)")
        ax.set_xlabel("trial lag [ms] (IMU stamps late by this)")
        ax.set_ylabel("normalised misfit")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=3, frameon=False)
        out["delay.png"] = _png(fig)
    return out


def _png(fig, top: float | None = None) -> bytes:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    if top is not None:
        fig.subplots_adjust(top=top)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def write_outputs(result: PostResult, folder: Path, plots_too: bool = True) -> dict[str, Path]:
    """All outputs into `folder` (see outdir: only files post wrote are ever replaced)."""
    contents = {
        "trajectory.csv": trajectory_csv(result).encode(),
        "trajectory.gpx": gpx_text(result).encode(),
        "angles.csv": angles_csv(result).encode(),
        "report.txt": report_text(result).encode(),
        "report.json": (json.dumps(summary(result), indent=2) + "\n").encode(),
    }
    if plots_too:
        contents.update(plots(result))
    written = write_files(folder, contents)
    names = {"trajectory.csv": "trajectory", "trajectory.gpx": "gpx", "angles.csv": "angles", "report.txt": "report",
             "report.json": "summary"}
    return {names.get(n, f"plot_{Path(n).stem}"): p for n, p in written.items()}
