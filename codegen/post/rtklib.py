"""RTKLIB files: the .pos solution (with Doppler velocities) and the binary .tag time-tag file of a logged stream,
plus the recording folder that combines them with a raw IMU CSV (../shared/data/gnss-imu-walk).

The .tag layout (RTKLIB src/stream.c, openfile_/writefile; the rtklibexplorer "EX" fork writes the same):

    offset  size  field
    0       60    ASCII "TIMETAG RTKLIB <version>", NUL padded
    60      4     uint32 tick_f: the logger's millisecond tick when the file was opened
    64      4     uint32 time: GPST start time as a time_t (seconds, calendar as if UTC)
    68      8     float64 sec: fraction of a second of that start time
    76      ...   records: uint32 tick (ms since tick_f), uint32 fpos (bytes of the data file written by then)
                  (8-byte fpos in builds without 4-byte tags: 12-byte records)

All little-endian. Record k says: the first fpos_k bytes of the data file had been received at start + tick_k ms.
"""

from __future__ import annotations

import calendar
import re
import struct
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from codegen.board.model import STANDARD_GRAVITY
from codegen.errors import Location, UserError
from codegen.post.model import GpsSeries, ImuSeries, PostLog
from codegen.post.table import read_bytes, read_text

TAG_MAGIC = b"TIMETAG RTKLIB"
TAG_HEADER_LEN = 64  # bytes, including tick_f
TAG_TIME_LEN = 12  # bytes: uint32 time + float64 sec


@dataclass
class TimeTag:
    start: float  # s, GPST time_t + fraction
    tick_f: int  # ms, logger tick at open
    tick: np.ndarray  # (K,) ms since start
    fpos: np.ndarray  # (K,) bytes received by then
    version: str

    def receive_time(self, byte_end: np.ndarray) -> np.ndarray:
        """GPST time (s) at which the byte just before offset `byte_end` had been received."""
        k = np.searchsorted(self.fpos, byte_end, side="left")
        k = np.clip(k, 0, len(self.tick) - 1)
        return self.start + self.tick[k] / 1000.0


def read_tag(path: Path) -> TimeTag:
    if not path.exists():
        raise UserError(f"time-tag file {path} does not exist", hint="RTKLIB writes it beside the log with -t / ::T")
    data = read_bytes(path, "time-tag file")
    if len(data) < TAG_HEADER_LEN + TAG_TIME_LEN or not data.startswith(TAG_MAGIC):
        raise UserError(f"{path} is not an RTKLIB time-tag file (no 'TIMETAG RTKLIB' header)",
                        location=Location(str(path), 1, 1))
    version = data[:60].rstrip(b"\0").decode("ascii", "replace")
    (tick_f,) = struct.unpack_from("<I", data, 60)
    time_t, sec = struct.unpack_from("<Id", data, 64)
    body = data[TAG_HEADER_LEN + TAG_TIME_LEN:]
    for size_fpos in (4, 8):
        record = 4 + size_fpos
        if len(body) % record:
            continue
        dtype = np.dtype([("tick", "<u4"), ("fpos", "<u4" if size_fpos == 4 else "<u8")])
        rec = np.frombuffer(body, dtype=dtype)
        if len(rec) and np.all(np.diff(rec["tick"].astype(np.int64)) >= 0) and np.all(np.diff(rec["fpos"].astype(np.int64)) >= 0):
            return TimeTag(time_t + sec, tick_f, rec["tick"].astype(float), rec["fpos"].astype(np.int64), version)
    raise UserError(f"{path}: time-tag records are truncated or out of order", location=Location(str(path), 1, 1))


# ----------------------------------------------------------------------------------------------- .pos solutions

def _pos_time(date: str, clock: str) -> float:
    stamp = datetime.strptime(f"{date} {clock}", "%Y/%m/%d %H:%M:%S.%f")
    return calendar.timegm(stamp.timetuple()) + stamp.microsecond * 1e-6


def looks_like_pos(text: str) -> bool:
    """An RTKLIB solution file: a '%' comment header naming the GPST time and latitude columns."""
    for line in text.splitlines()[:200]:
        if line.startswith("%") and "GPST" in line and "latitude" in line:
            return True
        if line.strip() and not line.startswith("%"):
            return False
    return False


def read_pos(path: Path, text: str | None = None) -> GpsSeries:
    """RTKLIB .pos with lat/lon/height and velocity columns (rnx2rtkp/rtkpost with velocity output)."""
    text = read_text(path, "RTKLIB solution") if text is None else text
    header = None
    rows, numbers = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        if line.startswith("%"):
            if "latitude" in line and "GPST" in line:
                header = line[1:].split()
            continue
        if not line.strip():
            continue
        if header is None:
            raise UserError(f"{path}: no column header ('%  GPST  latitude(deg) ...') before the data",
                            location=Location(str(path), number, 1),
                            hint="write the solution in lat/lon/height format with time as yyyy/mm/dd hh:mm:ss")
        fields = line.split()
        if len(fields) != len(header) + 1:
            raise UserError(f"{path}: solution line has {len(fields)} fields, expected {len(header) + 1}",
                            location=Location(str(path), number, 1), hint="the file is truncated or damaged here")
        rows.append(fields)
        numbers.append(number)
    if header is None or not rows:
        raise UserError(f"{path}: no solutions in the file", location=Location(str(path), 1, 1))
    names = [re.sub(r"\(.*\)", "", h) for h in header]
    need = ["latitude", "longitude", "height", "Q", "vn", "ve", "vu"]
    missing = [n for n in need if n not in names]
    if missing:
        raise UserError(f"{path}: solution lacks column(s) {', '.join(missing)}", location=Location(str(path), 1, 1),
                        hint="enable velocity output (out-outvel=on) so the Doppler velocities are written")
    col = {n: i + 1 for i, n in enumerate(names)}  # the time takes two fields
    try:
        t = np.array([_pos_time(r[0], r[1]) for r in rows])
        num = lambda n: np.array([float(r[col[n]]) for r in rows])  # noqa: E731
        lat, lon, h, q = num("latitude"), num("longitude"), num("height"), num("Q").astype(int)
        vel = np.stack([num("ve"), num("vn"), num("vu")], axis=1)
        sv = np.stack([num(n) if n in col else np.full(len(rows), 0.05) for n in ("sdve", "sdvn", "sdvu")], axis=1)
        sp = np.stack([num(n) if n in col else np.full(len(rows), 1.0) for n in ("sde", "sdn", "sdu")], axis=1)
    except ValueError as error:
        raise UserError(f"{path}: unreadable value ({error})", hint="the file is damaged") from None
    step = np.diff(t)
    if np.any(step < 0):
        i = int(np.flatnonzero(step < 0)[0]) + 1
        raise UserError(f"{path}: solution time goes back", location=Location(str(path), numbers[i], 1))
    for name, values, limit in (("latitude", lat, 90.0), ("longitude", lon, 180.0)):
        bad = np.flatnonzero(np.abs(values) > limit)
        if bad.size:
            raise UserError(f"{path}: {name} {values[bad[0]]:g} deg is outside -{limit:g}..{limit:g}",
                            location=Location(str(path), numbers[bad[0]], 1), hint="the file is damaged here")
    sv = np.where(sv > 0, sv, 0.05)
    sp = np.where(sp > 0, sp, 0.01)
    return GpsSeries(t, lat, lon, h, vel, sv, sp, q)


# ---------------------------------------------------------------------------------- raw IMU CSV + its time tags

RAW_IMU_FIELDS = 7  # ax, ay, az [g], gx, gy, gz [deg/s], t [ms ticks]


def read_raw_imu(path: Path, tag: TimeTag) -> tuple[ImuSeries, list[str]]:
    """Parse the raw IMU CSV and put each sample on GPS time through the tag file.

    Each complete line's receive time comes from the tag (the first record whose fpos covers the line's end). The
    IMU's own millisecond clock is smooth, the receive times are not (USB/serial buffering only ever delays), so the
    map is the line t_gps = a + b * tick fitted to the lower envelope of the receive times.
    """
    raw = read_bytes(path, "IMU log")
    if not raw.strip():
        raise UserError(f"IMU log {path} is empty", location=Location(str(path), 1, 1))
    crlf_in_file = b"\r\n" in raw[:4096]
    lines = raw.split(b"\n")
    ends = np.cumsum([len(x) + 1 for x in lines])  # byte offset after each line's newline, as stored
    # The tag counts bytes as logged. A copy that lost its CRs (CRLF -> LF) is shorter by one byte per line.
    notes = []
    if not crlf_in_file and tag.fpos[-1] > len(raw):
        excess = tag.fpos[-1] - len(raw)
        if abs(excess - len(lines)) <= 2:
            ends = ends + np.arange(1, len(lines) + 1)
            notes.append(f"{path.name}: the tag counts CRLF line ends but the file has LF; offsets corrected")
    rows, row_ends, numbers, dropped = [], [], [], 0
    for number, line in enumerate(lines):
        fields = line.strip().split(b",")
        if len(fields) != RAW_IMU_FIELDS:
            if line.strip():
                if 0 < number < len(lines) - 2:
                    raise UserError(f"IMU log line has {len(fields)} fields, expected {RAW_IMU_FIELDS}",
                                    location=Location(str(path), number + 1, 1), hint="the log is damaged here")
                dropped += 1
            continue
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            if 0 < number < len(lines) - 2:
                raise UserError("IMU log has a value that is not a number", location=Location(str(path), number + 1, 1)) from None
            dropped += 1
            continue
        row_ends.append(ends[number])
        numbers.append(number + 1)
    if dropped:
        notes.append(f"{path.name}: dropped {dropped} partial first/last line(s)")
    if len(rows) < 2:
        raise UserError(f"IMU log {path} has fewer than two complete samples", location=Location(str(path), 1, 1))
    data = np.array(rows)
    ticks = data[:, 6]
    bad = np.flatnonzero(np.diff(ticks) <= 0)
    if bad.size:
        raise UserError(f"IMU clock does not increase ({ticks[bad[0]]:.0f} -> {ticks[bad[0] + 1]:.0f} ms)",
                        location=Location(str(path), numbers[bad[0] + 1], 1))
    received = tag.receive_time(np.array(row_ends))
    # lower-envelope fit: least squares, then keep the earliest-received half, refit, shift onto the envelope
    x = (ticks - ticks[0]) / 1000.0
    coef = np.polyfit(x, received, 1)
    for _ in range(3):
        resid = received - np.polyval(coef, x)
        keep = resid <= np.percentile(resid, 20)
        coef = np.polyfit(x[keep], received[keep], 1)
    resid = received - np.polyval(coef, x)
    coef[1] += np.percentile(resid, 1)
    t = np.polyval(coef, x)
    latency = received - t
    notes.append(
        f"{path.name}: IMU clock mapped to GPST by the tag file: rate {coef[0]:.6f} s/s, "
        f"receive latency median {np.median(latency) * 1e3:.1f} ms (95% {np.percentile(latency, 95) * 1e3:.1f} ms)"
    )
    acc = data[:, 0:3] * STANDARD_GRAVITY
    gyro = np.radians(data[:, 3:6])
    return ImuSeries(t, acc, gyro), notes


def read_sf_imu(path: Path) -> ImuSeries:
    """The already GPS-stamped IMU CSV (t [s], acc [g] x3, gyro [rad/s] x3, ...) used as a cross-check."""
    data = np.loadtxt(path, delimiter=",", ndmin=2)
    return ImuSeries(data[:, 0], data[:, 1:4] * STANDARD_GRAVITY, data[:, 4:7])


def read_tagged_or_stamped_imu(path: Path) -> tuple[ImuSeries, list[str]]:
    """An IMU CSV beside an RTKLIB solution: the raw logger CSV with its `.tag` (put on GPST through the tag), or
    the GPS-stamped `*_sf.csv`."""
    tag_path = path.with_name(path.name + ".tag")
    if tag_path.exists():
        tag = read_tag(tag_path)
        imu, notes = read_raw_imu(path, tag)
        return imu, [f"IMU: {path.name} via {tag.version} time tags"] + notes
    return read_sf_imu(path), [f"IMU: {path.name} (already on GPS time)"]


def read_recording_folder(folder: Path) -> PostLog:
    """A folder with an RTKLIB .pos (with velocities) and an IMU CSV with its .tag (or a GPS-stamped *_sf.csv)."""
    pos = sorted(folder.glob("*.pos"))
    if not pos:
        raise UserError(f"{folder}: no RTKLIB .pos solution in the folder",
                        hint="expected <name>.pos with velocities, and an IMU CSV with its .tag")
    imu_tagged = sorted(p for p in folder.glob("*.csv") if p.with_name(p.name + ".tag").exists())
    imu_sf = sorted(folder.glob("*_sf.csv"))
    if not imu_tagged and not imu_sf:
        raise UserError(f"{folder}: GPS solution but no IMU log (an IMU .csv with its .csv.tag)",
                        hint="post-processing needs accelerometer samples; copy the IMU log next to the .pos")
    gps = read_pos(pos[0])
    notes = [f"GPS: {pos[0].name}, {len(gps)} epochs"]
    imu, imu_notes = read_tagged_or_stamped_imu(imu_tagged[0] if imu_tagged else imu_sf[0])
    return PostLog(folder.name, imu, gps, notes=notes + imu_notes, time_scale="gpst")
