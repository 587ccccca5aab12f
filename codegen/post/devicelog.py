"""The device's own run log (written by the generated app's logger), read into a `PostLog`.

Kept apart from the other readers so the format the app documents can be wired here without touching the method.
Until then a device log is recognised and refused with a clear message.
"""

from __future__ import annotations

from pathlib import Path

from codegen.errors import Location, UserError
from codegen.post.model import PostLog

DEVICE_LOG_SUFFIXES = (".bin",)
REC_HEADER = 0x48  # first byte of a device log file ('H' record)


def is_device_log(path: Path) -> bool:
    if path.is_dir():
        return any(p.suffix in DEVICE_LOG_SUFFIXES for p in path.iterdir()) and not any(path.glob("*.pos"))
    if path.suffix in DEVICE_LOG_SUFFIXES:
        return True
    try:
        with path.open("rb") as f:
            return f.read(1) == bytes([REC_HEADER])
    except OSError:
        return False


def read_device_log(path: Path) -> PostLog:
    raise UserError(
        f"{path}: device logs are not readable by this version of `deadreckon post` yet",
        location=Location(str(path), 1, 1),
        hint="export the run as the CSV pair (imu.csv: t,ax,ay,az; gps.csv: t,lat,lon,sog,cog,climb) and pass --gps",
    )
