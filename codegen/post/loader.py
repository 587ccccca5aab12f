"""Which reader a `deadreckon post LOG [--gps GPS]` argument needs (GPS: CSV, NMEA or GPX, by content)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from codegen.errors import Location, UserError
from codegen.post import csvlog, devicelog, gpxlog, nmealog, rtklib
from codegen.post.fixes import to_gps_series
from codegen.post.model import GpsSeries, PostLog
from codegen.post.table import read_text

UNIX_TIME_2000 = 946684800.0  # s: GPS times beyond this are absolute (UTC), not seconds since a start


def read_gps_file(path: Path) -> tuple[GpsSeries, list[str], str]:
    """A GPS log for --gps: the CSV (t,lat,lon,sog,cog,climb), an NMEA log, a GPX track or an RTKLIB solution
    (.pos with velocities), told apart by content. Returns the series, notes and its time scale (PostLog's)."""
    text = read_text(path, "GPS log")
    if rtklib.looks_like_pos(text):
        series = rtklib.read_pos(path, text)
        return series, [f"GPS: {path.name}, {len(series)} epochs (RTKLIB solution)"], "gpst"
    if nmealog.looks_like_nmea(text):
        series, notes = to_gps_series(nmealog.read_nmea(path, text), str(path))
    elif gpxlog.looks_like_gpx(text):
        series, notes = to_gps_series(gpxlog.read_gpx(path, text), str(path))
    else:
        series, notes = csvlog.read_gps_csv(path)
    absolute = len(series) > 0 and series.t[0] > UNIX_TIME_2000
    return series, notes, "utc" if absolute else "relative"


def load_log(log: Path, gps: Optional[Path] = None) -> PostLog:
    log = Path(log)
    if not log.exists():
        raise UserError(f"{log} does not exist", hint="pass a device log, an IMU CSV with --gps, or a recording folder")
    if gps is not None:
        if log.is_dir():
            raise UserError(f"{log} is a folder; --gps goes with an IMU CSV file")
        series, gps_notes, time_scale = read_gps_file(Path(gps))
        if time_scale == "gpst" and log.with_name(log.name + ".tag").exists():
            # a logger's raw IMU CSV with its RTKLIB time tags, as in a recording folder
            imu, imu_notes = rtklib.read_tagged_or_stamped_imu(log)
        else:
            imu, imu_notes = csvlog.read_imu_csv(log)
        return PostLog(log.stem, imu, series, notes=imu_notes + gps_notes, time_scale=time_scale)
    if log.is_dir():
        if any(log.glob("*.pos")):
            return rtklib.read_recording_folder(log)
        if devicelog.is_device_log(log):
            return devicelog.read_device_log(log)
        raise UserError(f"{log}: no RTKLIB .pos or device log in the folder")
    if log.suffix == ".pos":
        return rtklib.read_recording_folder(log.parent)
    if devicelog.is_device_log(log):
        return devicelog.read_device_log(log)
    text = read_text(log, "log")
    kind = "NMEA" if nmealog.looks_like_nmea(text) else "GPX" if gpxlog.looks_like_gpx(text) else None
    if kind:
        raise UserError(f"{log} is a GPS log ({kind}) without IMU data", location=Location(str(log), 1, 1),
                        hint="post-processing turns accelerations into a path with GPS as the reference; it needs the "
                             f"IMU log as well: deadreckon post IMU.csv --gps {log.name}")
    header = text.lstrip().split("\n", 1)[0].replace(" ", "").lower()
    columns = set(header.split(","))
    if set(csvlog.GPS_COLUMNS) <= columns:
        raise UserError(f"{log} is a GPS log without IMU data", location=Location(str(log), 1, 1),
                        hint="post-processing needs the accelerations: deadreckon post IMU.csv --gps GPS.csv")
    if set(csvlog.IMU_COLUMNS) <= columns:
        raise UserError(f"{log} is an IMU log; the GPS log is missing", location=Location(str(log), 1, 1),
                        hint="pass it with --gps GPS.csv (columns t,lat,lon,sog,cog,climb)")
    raise UserError(f"{log}: not a log this command knows", location=Location(str(log), 1, 1),
                    hint="expected an IMU CSV (t,ax,ay,az) with --gps, a device log, or a recording folder")
