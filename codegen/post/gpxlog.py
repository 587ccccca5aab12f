"""GPX tracks (1.0 and 1.1), parsed by gpxpy: every track point with a time, in time order, all tracks and segments.

Speed and course are taken where the file has them: GPX 1.0's <speed> (m/s) and <course> (deg), or a 1.1 extension
element named speed or course (Garmin's TrackPointExtension and the like, any namespace); HDOP from <hdop>; height
from <ele>. What is missing is derived from the positions (codegen.post.fixes). Times are UTC, as Unix seconds.
"""

from __future__ import annotations

import re
from pathlib import Path

import gpxpy
import gpxpy.gpx
import numpy as np

from codegen.errors import Location, UserError
from codegen.post.fixes import Fixes


def looks_like_gpx(text: str) -> bool:
    head = text.lstrip()[:2000].lower()
    return head.startswith("<?xml") and "<gpx" in head or head.startswith("<gpx")


def _extension(point: gpxpy.gpx.GPXTrackPoint, name: str) -> float:
    for element in point.extensions:
        for node in element.iter():
            tag = node.tag.rsplit("}", 1)[-1].lower()
            if tag == name and node.text:
                try:
                    return float(node.text)
                except ValueError:
                    return float("nan")
    return float("nan")


def _value(value) -> float:
    return float(value) if value is not None else float("nan")


def read_gpx(path: Path, text: str) -> Fixes:
    name = str(path)
    try:
        gpx = gpxpy.parse(text)
    except gpxpy.gpx.GPXXMLSyntaxException as error:
        original = getattr(error, "original_exception", None)
        place = re.search(r"line (\d+), column (\d+)", str(original or error))
        line, col = (int(place.group(1)), int(place.group(2)) + 1) if place else (1, 1)
        raise UserError(f"{name}: not readable as GPX ({original or error})", location=Location(name, line, col),
                        hint="the file is damaged or not XML") from None
    except gpxpy.gpx.GPXException as error:
        raise UserError(f"{name}: not a GPX file this command can read ({error})",
                        location=Location(name, 1, 1)) from None
    rows, untimed = [], 0
    for track in gpx.tracks:
        for segment in track.segments:
            for p in segment.points:
                if p.time is None:
                    untimed += 1
                    continue
                speed = _value(p.speed)
                if not np.isfinite(speed):
                    speed = _extension(p, "speed")
                course = _value(getattr(p, "course", None))
                if not np.isfinite(course):
                    course = _extension(p, "course")
                rows.append((p.time.timestamp(), p.latitude, p.longitude, _value(p.elevation), speed, course,
                             _value(p.horizontal_dilution)))
    notes = []
    if untimed:
        notes.append(f"{name}: {untimed} track point(s) without a time left out")
    if not rows:
        what = (f"{len(gpx.routes)} route(s), {len(gpx.waypoints)} waypoint(s)" if gpx.routes or gpx.waypoints
                else "nothing")
        raise UserError(f"{name}: no track point with a time (the file holds {what})", location=Location(name, 1, 1),
                        hint="post-processing needs a recorded track (<trk><trkseg><trkpt> with <time>), not a route")
    data = np.array(rows, dtype=float)
    bad = np.flatnonzero(~(np.abs(data[:, 1]) <= 90.0) | ~(np.abs(data[:, 2]) <= 180.0))  # nan is outside too
    if bad.size:
        raise UserError(f"{name}: track point {bad[0] + 1} at {data[bad[0], 1]:g}, {data[bad[0], 2]:g} is outside the "
                        "Earth's latitudes/longitudes", location=Location(name, 1, 1), hint="the file is damaged")
    order = np.argsort(data[:, 0], kind="stable")
    if np.any(np.diff(data[:, 0]) < 0):
        notes.append(f"{name}: track points out of time order were sorted")
    d = data[order]
    return Fixes(d[:, 0], d[:, 1], d[:, 2], d[:, 3], d[:, 4], d[:, 5], np.full(len(d), np.nan), d[:, 6], notes)
