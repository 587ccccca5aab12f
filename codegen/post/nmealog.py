"""NMEA 0183 logs of a GPS (speed) logger: RMC, GGA and VTG sentences, parsed by pynmeagps, checksums checked.

Sentences with one time of day make one epoch: RMC gives the fix's status, date, position, speed and course; GGA
the fix quality, position, HDOP and height; VTG (no time of its own) the speed and course of the epoch it follows.
An epoch is a fix when its RMC says A (and its mode is not N), or, without an RMC, when its GGA quality is above 0.
With an RMC date the time axis is UTC (Unix seconds); without one it is seconds after midnight UTC of the first
epoch's day (a day is added whenever the time of day goes back by more than 12 h). Sentences other than RMC/GGA/VTG
are skipped; so are damaged ones (bad checksum, too few fields: a serial log loses characters), counted in a note.
"""

from __future__ import annotations

import calendar
import datetime
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from pynmeagps import VALCKSUM, NMEAReader

from codegen.errors import Location, UserError
from codegen.post.fixes import Fixes

KNOT = 0.514444  # m/s
SECONDS_PER_DAY = 86400.0
WANTED = ("RMC", "GGA", "VTG")


def looks_like_nmea(text: str) -> bool:
    for line in text.splitlines()[:50]:
        line = line.strip()
        if line:
            return line.startswith("$") and len(line) > 6 and line[3:6].isalpha()
    return False


@dataclass
class _Epoch:
    time: float  # s of day
    line: int
    date: Optional[datetime.date] = None
    lat: float = float("nan")
    lon: float = float("nan")
    alt: float = float("nan")
    sog: float = float("nan")
    cog: float = float("nan")
    hdop: float = float("nan")
    rmc_valid: Optional[bool] = None
    gga_valid: Optional[bool] = None
    sentences: list[str] = field(default_factory=list)

    @property
    def valid(self) -> bool:
        if self.rmc_valid is not None:
            return self.rmc_valid
        return bool(self.gga_valid)


def _number(value) -> float:
    try:
        return float(value) if value not in ("", None) else float("nan")
    except (TypeError, ValueError):
        return float("nan")


def _seconds(time: datetime.time) -> float:
    return time.hour * 3600.0 + time.minute * 60.0 + time.second + time.microsecond * 1e-6


def read_nmea(path: Path, text: str) -> Fixes:
    epochs: list[_Epoch] = []
    by_time: dict[float, _Epoch] = {}
    damaged, first_damaged, other, current = 0, None, 0, None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        start = line.find("$")
        if start < 0:
            damaged += 1
            first_damaged = first_damaged or number
            continue
        line = line[start:]
        try:
            msg = NMEAReader.parse(line, validate=VALCKSUM)
        except Exception:  # pynmeagps raises its own errors and, on some damaged fields, plain ones
            msg = None
        if msg is None or not hasattr(msg, "msgID"):
            damaged += 1
            first_damaged = first_damaged or number
            continue
        kind = msg.msgID
        if kind not in WANTED:
            other += 1
            continue
        if kind == "VTG":
            if current is not None:
                if not np.isfinite(current.sog):
                    knots = _number(getattr(msg, "sogn", None))
                    kmh = _number(getattr(msg, "sogk", None))
                    current.sog = knots * KNOT if np.isfinite(knots) else kmh / 3.6
                if not np.isfinite(current.cog):
                    current.cog = _number(getattr(msg, "cogt", None))
                if getattr(msg, "posMode", "") == "N":
                    current.rmc_valid = False if current.rmc_valid is None else current.rmc_valid
                current.sentences.append(kind)
            continue
        time = getattr(msg, "time", None)
        if not isinstance(time, datetime.time):
            damaged += 1
            first_damaged = first_damaged or number
            continue
        key = _seconds(time)
        epoch = by_time.get(key)
        if epoch is None or (epochs and epochs[-1] is not epoch):
            epoch = _Epoch(key, number)
            by_time[key] = epoch
            epochs.append(epoch)
        current = epoch
        epoch.sentences.append(kind)
        lat, lon = _number(getattr(msg, "lat", None)), _number(getattr(msg, "lon", None))
        if kind == "RMC":
            epoch.rmc_valid = getattr(msg, "status", "") == "A" and getattr(msg, "posMode", "A") != "N"
            date = getattr(msg, "date", None)
            epoch.date = date if isinstance(date, datetime.date) else epoch.date
            epoch.sog = _number(getattr(msg, "spd", None)) * KNOT
            epoch.cog = _number(getattr(msg, "cog", None))
        else:
            epoch.gga_valid = int(_number(getattr(msg, "quality", 0)) or 0) > 0
            epoch.hdop = _number(getattr(msg, "HDOP", None))
            epoch.alt = _number(getattr(msg, "alt", None))
        if np.isfinite(lat) and np.isfinite(lon):
            epoch.lat, epoch.lon = lat, lon
    name = str(path)
    notes = []
    if damaged:
        notes.append(f"{name}: skipped {damaged} damaged line(s) (bad checksum or fields; first at line "
                     f"{first_damaged})")
    if not epochs:
        raise UserError(f"{name}: no RMC or GGA sentence with a time in the file ({other} other sentence(s), "
                        f"{damaged} damaged line(s))", location=Location(name, 1, 1),
                        hint="the GPS logger must log RMC (or GGA) sentences: they carry the fix, its time and place")
    fixes = [e for e in epochs if e.valid and np.isfinite(e.lat) and np.isfinite(e.lon)]
    if not fixes:
        raise UserError(f"{name}: none of the {len(epochs)} epochs has a valid fix (RMC status V or GGA quality 0 "
                        "throughout)", location=Location(name, epochs[0].line, 1),
                        hint="the receiver never had a fix while logging: log outdoors, with a view of the sky")
    for e in fixes:
        if abs(e.lat) > 90.0 or abs(e.lon) > 180.0:
            raise UserError(f"{name}: position {e.lat:g}, {e.lon:g} is outside the Earth's latitudes/longitudes",
                            location=Location(name, e.line, 1), hint="the sentence is damaged here")
    if len(fixes) < len(epochs):
        notes.append(f"{name}: {len(epochs) - len(fixes)} of {len(epochs)} epochs without a valid fix left out")
    t = _time_axis(fixes, notes, name)
    order = np.argsort(t, kind="stable")
    if np.any(np.diff(t) < 0):
        notes.append(f"{name}: epochs out of time order were sorted")
    f = [fixes[i] for i in order]
    col = lambda attr: np.array([getattr(e, attr) for e in f], dtype=float)  # noqa: E731
    return Fixes(t[order], col("lat"), col("lon"), col("alt"), col("sog"), col("cog"), np.full(len(f), np.nan),
                 col("hdop"), notes)


def _time_axis(fixes: list[_Epoch], notes: list[str], name: str) -> np.ndarray:
    dates = [e.date for e in fixes]
    if any(d is not None for d in dates):
        # an epoch without an RMC takes the date of the nearest one before it (after it, at the start)
        known = next(d for d in dates if d is not None)
        for i, d in enumerate(dates):
            known = d if d is not None else known
            dates[i] = known
        return np.array([calendar.timegm(d.timetuple()) + e.time for d, e in zip(dates, fixes)])
    notes.append(f"{name}: no date in the sentences (no RMC): time is seconds after midnight UTC of the first day")
    t = np.array([e.time for e in fixes])
    day = 0.0
    out = np.empty(len(t))
    for i in range(len(t)):
        if i and t[i] + day < out[i - 1] - SECONDS_PER_DAY / 2:
            day += SECONDS_PER_DAY
        out[i] = t[i] + day
    return out
