"""The device's own run log (docs/log-format.md: blocks of H/I/G/W/E records), read into a `PostLog`.

Kept apart from the other readers so a new log version only touches this module. Version 2 (today's app): a run's
clock is the device's microseconds since the run began, through all the part files the run rotated across (their
headers name the run and the part), and each IMU record is the mean of `log_every` samples, stamped with the last
one's time. Version 1 (older apps): each file has its own clock from its opening, and IMU records are single
samples. GPS records also carry the fix's UTC time. When they do, both streams go
onto UTC: GPS epochs at their fix times, IMU samples through the device clock at its own rate (unless the fixes
prove it off), offset to the earliest fix receipts (the fixed part of the NMEA latency is left to the delay
estimate). Without UTC the device clock is used.
"""

from __future__ import annotations

import calendar
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codegen.board.model import STANDARD_GRAVITY
from codegen.errors import Location, UserError
from codegen.post.csvlog import average_duplicate_epochs
from codegen.post.model import GpsSeries, ImuSeries, PostLog
from codegen.post.table import check_input_file, read_bytes

DEVICE_LOG_SUFFIXES = (".bin",)
REC_PAD, REC_HEADER, REC_IMU, REC_GPS, REC_WINDOW, REC_EVENT = 0x00, 0x48, 0x49, 0x47, 0x57, 0x45
RECORDS = {REC_IMU: ("<BI6h", 17), REC_GPS: ("<BIIHBBiiiiHiBBBH", 40), REC_WINDOW: ("<BIBiiffffffiiI", 50)}
DEFAULT_BLOCK = 4096  # bytes, logging.block_bytes default
UNKNOWN_I32 = -(2**31)
UNKNOWN_U16 = 0xFFFF
UNKNOWN_U32 = 0xFFFFFFFF
DOPPLER_SIGMA = 0.1  # m/s, NEO-6M velocity accuracy
CLIMB_SIGMA = 0.5  # m/s: the climb rate is no Doppler, but GGA altitude differences 1 s apart (metres of noise)
UERE = 2.5  # m, horizontal 1-sigma per unit HDOP
CLIMB_UNKNOWN_SIGMA = 1.0  # m/s, vertical velocity when the log has no climb rate
BLOCK_BYTES_RANGE = (256, 65536)  # logging.block_bytes' range in the board schema
LSB_RANGE = (1.0, 1.0e6)  # counts per g or per degree/s a header may give (the MPU-6050's: 2048..16384, 16.4..131)
CLOCK_RATE_TOLERANCE = 0.002  # a clock this far off its nominal rate is believed from the fixes (MPU-6050's is +-1 %)
CLOCK_RATE_SIGMAS = 4.0  # ... when the fixes also show it by this many of their 1-sigma
VERSIONS = (1, 2)  # device log versions this reader knows
YEARS = (1980, 2200)  # a GPS fix's year (the receiver's week rollover aside, nothing else is a date it gives)


def is_device_log(path: Path) -> bool:
    if path.is_dir():
        return any(p.suffix in DEVICE_LOG_SUFFIXES for p in path.iterdir()) and not any(path.glob("*.pos"))
    if path.suffix in DEVICE_LOG_SUFFIXES:
        return True
    check_input_file(path, "log")
    try:
        with path.open("rb") as f:
            return f.read(1) == bytes([REC_HEADER])
    except OSError:
        return False


@dataclass
class RawDeviceLog:
    path: Path
    header: dict[str, str] = field(default_factory=dict)
    imu: list[tuple] = field(default_factory=list)  # (t_us unwrapped, ax, ay, az, gx, gy, gz)
    gps: list[tuple] = field(default_factory=list)  # (t_us unwrapped, *fields of the G record after t_us)
    events: list[tuple[int, str]] = field(default_factory=list)
    truncated: bool = False
    version: int = 1
    parts: list[Path] = field(default_factory=list)  # the files read, in order (one, or a run's parts)


def _first_header(data: bytes, path: Path) -> tuple[int, dict[str, str]]:
    """(version, keys) of the header record a device log begins with; UserError when it does not."""
    if len(data) < 4 or data[0] != REC_HEADER:
        raise UserError(f"{path}: not a deadreckon device log (no header record)", location=Location(str(path), 1, 1),
                        hint="device logs are the dr00001.bin files from the board's /logs folder")
    _, version, n = struct.unpack_from("<BBH", data, 0)
    if version not in VERSIONS:
        raise UserError(f"{path}: device log version {version}; this reader knows versions "
                        f"{', '.join(map(str, VERSIONS))}", location=Location(str(path), 1, 1),
                        hint="a newer app wrote it: update deadreckon")
    text = data[4:4 + n].decode("ascii", "replace")
    return version, dict(kv.split("=", 1) for kv in text.split(";") if "=" in kv)


def _block_size(data: bytes, path: Path) -> int:
    _, header = _first_header(data, path)
    written = header.get("block_bytes", str(DEFAULT_BLOCK))
    low, high = BLOCK_BYTES_RANGE
    if not (written.strip().isdigit() and low <= int(written) <= high):
        raise UserError(f"{path}: the header's block_bytes={written[:40]} is not a block size ({low}..{high} bytes)",
                        location=Location(str(path), 1, 1),
                        hint="the header is damaged; a log written by the app says the board's logging.block_bytes")
    return int(written)


def parse_device_log(path: Path, block: int | None = None) -> RawDeviceLog:
    """One file on its own (a version 1 file, or one part of a version 2 run read alone)."""
    return parse_device_parts([path], block)


def parse_device_parts(paths: list[Path], block: int | None = None) -> RawDeviceLog:
    """Files read in order as one log, the clock unwrapped across them (the parts of one version 2 run)."""
    log = RawDeviceLog(paths[0], parts=list(paths))
    state = [0, 0]  # the clock's wraps so far (in us), the last time read
    for index, path in enumerate(paths):
        data = read_bytes(path, "device log")
        _not_empty(data, path)
        if index == 0:
            log.version = _first_header(data, path)[0]
        _parse_blocks(data, path, block or _block_size(data, path), log, state, last_file=index == len(paths) - 1)
    return log


def _not_empty(data: bytes, path: Path) -> None:
    if not data:
        raise UserError(f"device log {path} is empty", location=Location(str(path), 1, 1),
                        hint="the device wrote no complete block: the run was shorter than one block or logging was off")


def _parse_blocks(data: bytes, path: Path, block: int, log: RawDeviceLog, state: list[int], last_file: bool) -> None:
    if len(data) % block:
        log.truncated = True
    t_hi, last = state
    for start in range(0, len(data), block):
        blk = data[start:start + block]
        i = 0
        while i < len(blk) and blk[i] != REC_PAD:
            kind = blk[i]
            where = f"byte {start + i}"
            try:
                if kind == REC_HEADER:
                    _, _, n = struct.unpack_from("<BBH", blk, i)
                    log.header.update(dict(kv.split("=", 1) for kv in blk[i + 4:i + 4 + n].decode("ascii", "replace")
                                           .split(";") if "=" in kv))
                    i += 4 + n
                    continue
                if kind == REC_EVENT:
                    _, t, n = struct.unpack_from("<BIB", blk, i)
                    fields = (blk[i + 6:i + 6 + n].decode("ascii", "replace"),)
                    i += 6 + n
                elif kind in RECORDS:
                    fmt, size = RECORDS[kind]
                    _, t, *fields = struct.unpack_from(fmt, blk, i)
                    i += size
                else:
                    raise UserError(f"{path}: unknown record type 0x{kind:02x} at {where}",
                                    location=Location(str(path), 1, 1), hint="the log is damaged here")
            except struct.error:
                if start + block >= len(data):  # the last, partial block of a cut-off file
                    log.truncated = True
                    break
                raise UserError(f"{path}: record cut short at {where}", location=Location(str(path), 1, 1)) from None
            if t < last and last - t < (1 << 31):  # the clock wraps from near 2^32 to near 0; this went back
                raise UserError(f"{path}: the record at {where} is {(last - t) / 1e6:.6f} s older than the one "
                                "before it (the device's clock only goes forward)",
                                location=Location(str(path), 1, 1), hint="the log is damaged there")
            t_hi += (1 << 32) if t < last else 0
            last = t
            stamp = t + t_hi
            if kind == REC_IMU:
                log.imu.append((stamp, *fields))
            elif kind == REC_GPS:
                log.gps.append((stamp, *fields))
            elif kind == REC_EVENT:
                log.events.append((stamp, fields[0]))
    state[:] = [t_hi, last]
    if log.truncated and not last_file:
        raise UserError(f"{path}: a part of the run that is cut short, with later parts after it",
                        location=Location(str(path), 1, 1), hint="the file is damaged; pass a single part to read it "
                        "alone")


def _axes(spec: str) -> list[tuple[int, int]]:
    """'+0+1+2' -> [(+1, 0), (+1, 1), (+1, 2)]: body axis k = sign * sensor axis index; ValueError for anything
    but three signed axis indices using each of 0, 1, 2 once."""
    if len(spec) != 6 or any(spec[i] not in "+-" or spec[i + 1] not in "012" for i in range(0, 6, 2)):
        raise ValueError(spec)
    out = [(-1 if spec[i] == "-" else 1, int(spec[i + 1])) for i in range(0, 6, 2)]
    if sorted(a for _, a in out) != [0, 1, 2]:
        raise ValueError(spec)
    return out


def _sensitivity(header: dict[str, str], key: str, default: float) -> float:
    """A header's counts per unit, finite and within LSB_RANGE; ValueError otherwise."""
    value = float(header.get(key, default))
    if not LSB_RANGE[0] <= value <= LSB_RANGE[1]:  # also false for nan
        raise ValueError(key)
    return value


def _box_centre(header: dict[str, str], path: Path) -> float:
    """Seconds from a version 2 IMU record's time back to the middle of the samples it averages."""
    try:
        every, rate = int(header.get("log_every", "1")), float(header.get("imu_rate_hz", "0"))
    except ValueError:
        every, rate = 0, 0.0
    if not (1 <= every <= 1000 and 1.0 <= rate <= 10000.0):
        raise UserError(f"{path}: the header's log_every={header.get('log_every', '(none)')[:20]};"
                        f"imu_rate_hz={header.get('imu_rate_hz', '(none)')[:20]} is not a decimation (1..1000) and "
                        "an IMU rate (1..10000 Hz)", location=Location(str(path), 1, 1), hint="the header is damaged")
    return 0.5 * (every - 1) / rate


def _check_fixes(path: Path, year, month, day, utc_ms, lat, lon, known) -> None:
    """Every GPS record with a UTC time holds a calendar date and a time of day, and every position is on Earth;
    the first that is not is a UserError naming it (its place among the file's GPS records)."""
    for index in range(len(year)):
        if known[index] and not (YEARS[0] <= year[index] <= YEARS[1] and 1 <= month[index] <= 12
                                 and 1 <= day[index] <= calendar.monthrange(int(year[index]), int(month[index]))[1]
                                 and 0 <= utc_ms[index] < 86_401_000):
            raise UserError(
                f"{path}: GPS record {index + 1} of the log says {int(year[index])}-{int(month[index]):02d}-"
                f"{int(day[index]):02d} {utc_ms[index] / 1000:.3f} s, which is no date and time of a fix",
                location=Location(str(path), 1, 1), hint="the log is damaged there; a receiver's fix has a "
                f"calendar date from {YEARS[0]} on and a time of day")
        if not (abs(lat[index]) <= 90e7 and abs(lon[index]) <= 180e7):
            raise UserError(
                f"{path}: GPS record {index + 1} of the log is at latitude {lat[index] * 1e-7:.7f}, longitude "
                f"{lon[index] * 1e-7:.7f}, which is not on Earth (latitude -90..90, longitude -180..180)",
                location=Location(str(path), 1, 1), hint="the log is damaged there")


def _clock_rate(g_dev: np.ndarray, utc: np.ndarray) -> tuple[float, float, float]:
    """UTC seconds per device second, with the rate the fixes alone give and its 1-sigma.

    The device clock counts IMU sample periods at the header's imu_rate_hz (FIFO) or the ESP32's crystal ticks, so
    its rate is 1 to the chip's tolerance. The fixes' receipt times jitter by tens of milliseconds, which on a short
    file puts a fitted rate 1e-3 off (a drift of a millisecond per second); they override the device only when they
    prove it off by more than CLOCK_RATE_TOLERANCE and CLOCK_RATE_SIGMAS of their own uncertainty.
    """
    if len(utc) < 3 or np.ptp(g_dev) <= 0:
        return 1.0, 1.0, float("inf")
    fitted, intercept = np.polyfit(g_dev, utc, 1)
    resid = utc - (fitted * g_dev + intercept)
    spread = float(np.sqrt(np.sum(resid ** 2) / (len(utc) - 2)))
    sigma = spread / float(np.sqrt(np.sum((g_dev - g_dev.mean()) ** 2)))
    off = abs(fitted - 1.0)
    rate = float(fitted) if off > CLOCK_RATE_TOLERANCE and off > CLOCK_RATE_SIGMAS * sigma else 1.0
    return rate, float(fitted), sigma


def to_post_log(raw: RawDeviceLog) -> PostLog:
    path = raw.path
    notes = [f"{path.name}: device log version {raw.version}, board {raw.header.get('board', '?')}, kernel "
             f"{raw.header.get('kernel', '?')}"]
    if len(raw.parts) > 1:
        notes.append(f"{path.name}: run {raw.header.get('run', '?')} read from its {len(raw.parts)} parts "
                     f"({', '.join(p.name for p in raw.parts)})")
    if raw.truncated:
        notes.append(f"{path.name}: the last block is incomplete (power cut?); its records were kept as far as whole")
    if len(raw.imu) < 2:
        raise UserError(f"{path}: {len(raw.imu)} IMU record(s)", location=Location(str(path), 1, 1),
                        hint="logging.imu must be on to post-process a run")
    try:
        lsb = _sensitivity(raw.header, "accel_lsb_per_g", 16384)
        gyro_lsb = _sensitivity(raw.header, "gyro_lsb_per_dps", 131)
        axes = _axes(raw.header.get("axes", "+0+1+2"))
    except ValueError:
        shown = ";".join(f"{key}={raw.header.get(key, '(none)')[:20]}" for key in
                         ("accel_lsb_per_g", "gyro_lsb_per_dps", "axes"))
        raise UserError(f"{path}: the header's {shown} is not a sensitivity of {LSB_RANGE[0]:g}..{LSB_RANGE[1]:g} "
                        "counts per unit and a signed permutation of the axes 0, 1, 2 (e.g. +0+1+2)",
                        location=Location(str(path), 1, 1), hint="the header is damaged") from None
    imu = np.array(raw.imu, dtype=float)
    t_dev = imu[:, 0] * 1e-6
    if raw.version >= 2:  # a record is the mean of log_every samples up to its time: it stands for their middle
        t_dev = t_dev - _box_centre(raw.header, path)
    counts = imu[:, 1:4]
    body = np.stack([sign * counts[:, index] for sign, index in axes], axis=1)
    acc = body / lsb * STANDARD_GRAVITY
    rate_counts = imu[:, 4:7]
    gyro = None
    if np.any(rate_counts != 0):  # a log written without the gyro holds zeros there
        gyro = np.radians(np.stack([sign * rate_counts[:, index] for sign, index in axes], axis=1) / gyro_lsb)
    keep = np.concatenate([[True], np.diff(t_dev) > 0])
    if not keep.all():
        notes.append(f"{path.name}: dropped {np.sum(~keep)} IMU record(s) with a repeated time stamp")
    t_dev, acc = t_dev[keep], acc[keep]
    gyro = gyro[keep] if gyro is not None else None
    if not raw.gps:
        raise UserError(f"{path}: no GPS fix in the log", location=Location(str(path), 1, 1),
                        hint="the receiver never had a fix during this run; post-processing needs GPS velocities")
    g = np.array(raw.gps, dtype=float)
    (t_g, utc_ms, year, month, day, lat, lon, alt, sog, cog, climb, mode, quality, sats, hdop) = g.T
    valid = (mode >= 2) & (sog != UNKNOWN_I32) & ((cog != UNKNOWN_U16) | (sog < 100))
    if valid.sum() < 2:
        raise UserError(f"{path}: {int(valid.sum())} GPS record(s) with a fix and a speed", location=Location(str(path), 1, 1))
    g_dev = t_g[valid] * 1e-6
    has_utc = (utc_ms[valid] != UNKNOWN_U32) & (year[valid] > 0)
    _check_fixes(path, year[valid], month[valid], day[valid], utc_ms[valid], lat[valid], lon[valid], has_utc)
    time_scale = "relative"
    t_gps, t_imu = g_dev, t_dev
    if has_utc.all():
        utc = np.array([calendar.timegm((int(y), int(m), int(d), 0, 0, 0)) for y, m, d in
                        zip(year[valid], month[valid], day[valid])], dtype=float) + utc_ms[valid] / 1000.0
        if len(np.unique(utc)) >= 2:
            rate, fitted, sigma = _clock_rate(g_dev, utc)
            # fixes are received after they happen, late by a varying amount: the earliest receipts (the top
            # percentile of UTC minus the mapped device time) are the ones nearest the fix
            offset = float(np.percentile(utc - rate * g_dev, 99))
            t_gps, t_imu = utc, rate * t_dev + offset
            time_scale = "utc"
            if rate == 1.0:
                notes.append(f"{path.name}: device clock mapped to UTC through {len(utc)} fixes (the device's rate; "
                             f"the fixes alone say {fitted:.6f} +- {sigma:.6f} s/s)")
            else:
                notes.append(f"{path.name}: device clock mapped to UTC through {len(utc)} fixes at their rate "
                             f"{rate:.6f} +- {sigma:.6f} s/s: the device's clock runs off its nominal rate")
    sog_ms, cog_deg = sog[valid] / 1000.0, np.where(cog[valid] == UNKNOWN_U16, 0.0, cog[valid] / 100.0)
    climb_known = climb[valid] != UNKNOWN_I32
    v_up = np.where(climb_known, climb[valid] / 1000.0, 0.0)
    cog_rad = np.radians(cog_deg)
    vel = np.stack([sog_ms * np.sin(cog_rad), sog_ms * np.cos(cog_rad), v_up], axis=1)
    m = len(t_gps)
    sigma_vel = np.full((m, 3), DOPPLER_SIGMA)
    sigma_vel[:, 2] = np.where(climb_known, CLIMB_SIGMA, CLIMB_UNKNOWN_SIGMA)
    h_dop = np.where(hdop[valid] == UNKNOWN_U16, 200.0, hdop[valid]) / 100.0
    sigma_h = UERE * np.maximum(h_dop, 1.0)
    alt_m = np.where(alt[valid] == UNKNOWN_I32, np.nan, alt[valid] / 1000.0)
    sigma_pos = np.stack([sigma_h, sigma_h, 2 * sigma_h], axis=1)
    order = np.argsort(t_gps, kind="stable")
    n_epochs = len(order)
    t_gps, (lat_deg, lon_deg, alt_m, vel, sigma_vel, sigma_pos, q) = average_duplicate_epochs(
        t_gps[order], lat[valid][order] * 1e-7, lon[valid][order] * 1e-7, alt_m[order], vel[order],
        sigma_vel[order], sigma_pos[order], quality[valid][order].astype(float))
    if len(t_gps) < n_epochs:
        notes.append(f"{path.name}: averaged {n_epochs - len(t_gps)} duplicate GPS epoch(s)")
    gps = GpsSeries(t_gps, lat_deg, lon_deg, alt_m, vel, sigma_vel, sigma_pos, np.round(q).astype(int))
    return PostLog(path.stem, ImuSeries(t_imu, acc, gyro), gps, notes=notes, time_scale=time_scale)


def _run_of(path: Path) -> tuple[str, int] | None:
    """(run, part) a version 2 file's header names, None for a version 1 file."""
    check_input_file(path, "device log")
    with path.open("rb") as f:
        data = f.read(1024)
    _not_empty(data, path)
    version, header = _first_header(data, path)
    if version < 2:
        return None
    part = header.get("part", "")
    if "run" not in header or not part.isdigit():
        raise UserError(f"{path}: a version {version} header without its run and part",
                        location=Location(str(path), 1, 1), hint="the header is damaged")
    return header["run"], int(part)


def run_parts(path: Path) -> list[Path]:
    """The files of the run `path` belongs to, in part order: a version 2 file with the other parts of its run
    beside it (the oldest may have been deleted to make room), or a folder holding one run; a version 1 file alone."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix in DEVICE_LOG_SUFFIXES)
        runs = {p: _run_of(p) for p in files}
        names = sorted({r[0] for r in runs.values() if r is not None})
        if len(files) > 1 and (None in runs.values() or len(names) > 1):
            raise UserError(f"{path}: {len(files)} device logs of {len(names) or len(files)} runs in the folder; "
                            "pass one file (a file of a run brings the run's other parts)",
                            hint="each boot starts a run with its own clock")
        path = files[0]
    own = _run_of(path)
    if own is None:
        return [path]
    parts = {}
    for p in sorted(path.parent.iterdir()):
        if p.suffix in DEVICE_LOG_SUFFIXES and p.is_file():
            try:
                r = _run_of(p)
            except (UserError, OSError):
                continue  # another file: not a part of this run
            if r is not None and r[0] == own[0]:
                if r[1] in parts:
                    raise UserError(f"{path.parent}: {parts[r[1]].name} and {p.name} both say they are part {r[1]} "
                                    f"of run {own[0]}", hint="pass one file")
                parts[r[1]] = p
    numbers = sorted(parts)
    missing = sorted(set(range(numbers[0], numbers[-1] + 1)) - set(numbers))
    if missing:
        raise UserError(f"{path.parent}: run {own[0]} lacks part(s) {', '.join(map(str, missing))} between its "
                        f"parts {numbers[0]} and {numbers[-1]}", hint="copy every dr*.bin file of the run from the "
                        "board's /logs folder")
    return [parts[n] for n in numbers]


def read_device_log(path: Path) -> PostLog:
    """One run: a dr*.bin file with the other parts of its run beside it, or a folder of one run's files."""
    return to_post_log(parse_device_parts(run_parts(path)))
