"""Which reader a `deadreckon post LOG [--gps GPS]` argument needs."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from codegen.errors import Location, UserError
from codegen.post import csvlog, devicelog, rtklib
from codegen.post.model import PostLog
from codegen.post.table import read_text


def load_log(log: Path, gps: Optional[Path] = None) -> PostLog:
    log = Path(log)
    if not log.exists():
        raise UserError(f"{log} does not exist", hint="pass a device log, an IMU CSV with --gps, or a recording folder")
    if gps is not None:
        if log.is_dir():
            raise UserError(f"{log} is a folder; --gps goes with an IMU CSV file")
        return csvlog.read_csv_pair(log, Path(gps))
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
    header = read_text(log, "log").lstrip().split("\n", 1)[0].replace(" ", "").lower()
    columns = set(header.split(","))
    if set(csvlog.GPS_COLUMNS) <= columns:
        raise UserError(f"{log} is a GPS log without IMU data", location=Location(str(log), 1, 1),
                        hint="post-processing needs the accelerations: deadreckon post IMU.csv --gps GPS.csv")
    if set(csvlog.IMU_COLUMNS) <= columns:
        raise UserError(f"{log} is an IMU log; the GPS log is missing", location=Location(str(log), 1, 1),
                        hint="pass it with --gps GPS.csv (columns t,lat,lon,sog,cog,climb)")
    raise UserError(f"{log}: not a log this command knows", location=Location(str(log), 1, 1),
                    hint="expected an IMU CSV (t,ax,ay,az) with --gps, a device log, or a recording folder")
