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


def read_gps_file(path: Path) -> tuple[GpsSeries, list[str]]:
    """A GPS log for --gps: the CSV (t,lat,lon,sog,cog,climb), an NMEA log or a GPX track, told apart by content."""
    text = read_text(path, "GPS log")
    if nmealog.looks_like_nmea(text):
        return to_gps_series(nmealog.read_nmea(path, text), str(path))
    if gpxlog.looks_like_gpx(text):
        return to_gps_series(gpxlog.read_gpx(path, text), str(path))
    return csvlog.read_gps_csv(path)


def load_log(log: Path, gps: Optional[Path] = None) -> PostLog:
    log = Path(log)
    if not log.exists():
        raise UserError(f"{log} does not exist", hint="pass a device log, an IMU CSV with --gps, or a recording folder")
    if gps is not None:
        if log.is_dir():
            raise UserError(f"{log} is a folder; --gps goes with an IMU CSV file")
        imu, imu_notes = csvlog.read_imu_csv(log)
        series, gps_notes = read_gps_file(Path(gps))
        absolute = len(series) > 0 and series.t[0] > UNIX_TIME_2000
        return PostLog(log.stem, imu, series, notes=imu_notes + gps_notes, time_scale="utc" if absolute else "relative")
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
