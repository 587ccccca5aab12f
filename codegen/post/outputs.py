"""What `deadreckon post` writes: trajectory CSV, GPX, per-interval angles, the report (text + JSON), plots."""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from codegen.post.geodesy import enu_to_geodetic
from codegen.post.orientation import (
    FLAG_GIMBAL, FLAG_GPS_GAP, FLAG_LM_WAHBA, FLAG_NO_IMU, FLAG_POOR_FIT, FLAG_STATIONARY, FLAG_YAW_HELD,
)
from codegen.post.pipeline import PostResult

GPS_UTC_LEAP_SECONDS = 18  # s, GPST - UTC since 2017-01-01


def trajectory_rows(result: PostResult) -> dict[str, np.ndarray]:
    tr = result.track
    lat, lon, h = enu_to_geodetic(tr.pos, result.origin)
    rot = result.orientation.slerp()(tr.t)
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


def _write_csv(path: Path, columns: dict[str, np.ndarray], formats: dict[str, str]) -> None:
    names = list(columns)
    with path.open("w") as f:
        f.write(",".join(names) + "\n")
        for i in range(len(columns[names[0]])):
            f.write(",".join(_fmt(columns[n][i], formats.get(n, "{:.4f}")) for n in names) + "\n")


def _fmt(value, fmt: str) -> str:
    if isinstance(value, str):
        return value
    return "" if not np.isfinite(value) else fmt.format(value)


def write_trajectory_csv(result: PostResult, path: Path) -> None:
    _write_csv(path, trajectory_rows(result), {"t": "{:.3f}", "lat": "{:.8f}", "lon": "{:.8f}", "h": "{:.3f}"})


def write_gpx(result: PostResult, path: Path) -> None:
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
    path.write_text("\n".join(out) + "\n")


def write_angles_csv(result: PostResult, path: Path) -> None:
    o = result.orientation
    e, s = np.degrees(o.euler), np.degrees(o.sigma)
    _write_csv(path, {
        "t": o.t, "roll_deg": e[:, 0], "pitch_deg": e[:, 1], "yaw_deg": e[:, 2],
        "sigma_roll_deg": s[:, 0], "sigma_pitch_deg": s[:, 1], "sigma_yaw_deg": s[:, 2],
        "horizontal_accel": o.horizontal_accel, "window_horizontal_accel": o.window_horizontal_accel,
        "chi2": o.chi2, "lm_vs_wahba_deg": o.lm_vs_wahba_deg,
        "flags": np.array([" ".join(f) for f in o.flags], dtype=object),
    }, {"t": "{:.3f}", "lm_vs_wahba_deg": "{:.2e}"})


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
    return {
        "log": result.log.name,
        "imu_samples": len(result.log.imu), "imu_rate_hz": round(result.log.imu.rate_hz, 3),
        "gps_epochs": len(result.log.gps), "duration_s": round(float(tr.t[-1] - tr.t[0]), 3),
        "delay_s": result.delay,
        "delay_sigma_s": None if est is None else est.sigma,
        "delay_correlation": None if est is None else est.correlation,
        "delay_estimated": est is not None,
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
    o = result.orientation
    lines = [f"deadreckon post: {s['log']}", ""]
    lines.append(f"input      {s['imu_samples']} IMU samples at {s['imu_rate_hz']:.1f} Hz, {s['gps_epochs']} GPS epochs, "
                 f"{s['duration_s']:.1f} s, {s['distance_m']:.1f} m travelled")
    for note in s["notes"]:
        lines.append(f"           {note}")
    if s["delay_estimated"]:
        lines.append(f"delay      {s['delay_s'] * 1e3:+.1f} ms +- {s['delay_sigma_s'] * 1e3:.1f} ms (IMU stamps late by this; "
                     f"correlation {s['delay_correlation']:.3f})")
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
    flagged = [(o.t[k], o.flags[k]) for k in range(len(o.t)) if o.flags[k]]
    if flagged:
        t0 = result.log.gps.t[0]
        lines.append("")
        lines.append(f"flagged intervals (midpoint, s after the first GPS epoch at {t0:.3f} s), first 40:")
        lines.append("  yaw-held: too little horizontal acceleration, yaw carried over; stationary: no track direction;")
        lines.append("  poor-fit: the window's vectors disagree with one rotation; lm-wahba: LM and closed form differ")
        lines.append("  (on a yaw-held interval: the tilt differs, i.e. the held yaw does not suit the window);")
        lines.append("  gimbal: pitch near +-90 deg, the rotation is sound but roll and yaw are not separable")
        for t, f in flagged[:40]:
            lines.append(f"  {t - t0:8.3f}: {' '.join(f)}")
    return "\n".join(lines) + "\n"


def write_plots(result: PostResult, folder: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    o, tr, gps = result.orientation, result.track, result.log.gps
    t0 = tr.t[0]
    paths = []
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(10, 7))
    for i, name in enumerate(("roll", "pitch", "yaw")):
        e, s = np.degrees(o.euler[:, i]), np.minimum(np.degrees(o.sigma[:, i]), 30.0)
        axes[i].plot(o.t - t0, e, ".-", ms=2, lw=0.8)
        axes[i].fill_between(o.t - t0, e - s, e + s, alpha=0.3)
        held = np.array([bool(f) for f in o.flags])
        axes[i].plot((o.t - t0)[held], e[held], "x", color="tab:red", ms=3, label="flagged")
        axes[i].set_ylabel(f"{name} [deg]")
    axes[2].set_ylim(-185.0, 185.0)
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("orientation per GPS interval (band: 1 sigma)")
    paths.append(_save(fig, folder / "angles.png"))
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(10, 7))
    for i, name in enumerate(("east", "north", "up")):
        axes[i].plot(gps.t - t0, gps.vel[:, i], ".", ms=3, label="GPS Doppler")
        axes[i].plot(tr.t - t0, tr.vel[:, i], lw=0.8, label="IMU + GPS smoothed")
        imu_only = gps.vel[1:, i] - result.imu_velocity_residual[:, i]  # previous epoch + IMU velocity change
        axes[i].plot(gps.t[1:] - t0, imu_only, "+", ms=3, label="previous GPS + IMU over the interval")
        axes[i].set_ylabel(f"v {name} [m/s]")
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time [s]")
    paths.append(_save(fig, folder / "velocity.png"))
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(result.gps_enu[:, 0], result.gps_enu[:, 1], ".", ms=3, label="GPS")
    ax.plot(tr.pos[:, 0], tr.pos[:, 1], lw=1.0, label="reconstructed")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    paths.append(_save(fig, folder / "trajectory.png"))
    if result.delay_estimate is not None and len(result.delay_estimate.lags) > 1:
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot(result.delay_estimate.lags * 1e3, result.delay_estimate.cost)
        ax.set_xlabel("trial lag [ms] (first search)")
        ax.set_ylabel("normalised misfit")
        paths.append(_save(fig, folder / "delay.png"))
    return paths


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def write_outputs(result: PostResult, folder: Path, plots: bool = True) -> dict[str, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    files = {"trajectory": folder / "trajectory.csv", "gpx": folder / "trajectory.gpx",
             "angles": folder / "angles.csv", "report": folder / "report.txt", "summary": folder / "report.json"}
    write_trajectory_csv(result, files["trajectory"])
    write_gpx(result, files["gpx"])
    write_angles_csv(result, files["angles"])
    files["report"].write_text(report_text(result))
    files["summary"].write_text(json.dumps(summary(result), indent=2) + "\n")
    if plots:
        for p in write_plots(result, folder):
            files[f"plot_{p.stem}"] = p
    return files
