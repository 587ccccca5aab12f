"""Inputs for the hostile and fuzz suites (tests/test_post_hostile_devicelog.py, tests/test_hostile_fuzz.py,
benchmarks/hostile_fuzz.py): a device log (docs/log-format.md v1) written from a synthetic run, with any header
value or GPS record field replaced, and the same run as the CSV pair, NMEA and GPX a user may post instead.
"""

from __future__ import annotations

import calendar
import struct
import time
from functools import lru_cache

import numpy as np

from codegen.board.model import STANDARD_GRAVITY
from codegen.post.synthetic import Scenario, make_run

BLOCK = 4096
START_UTC = calendar.timegm((2026, 11, 21, 12, 0, 0))
HEADER = {"deadreckon": "1", "board": "synthetic", "imu_rate_hz": "50", "log_every": "1",
          "accel_lsb_per_g": "16384", "gyro_lsb_per_dps": "131", "axes": "+0+1+2", "kernel": "python",
          "block_bytes": str(BLOCK)}
GPS_FIELDS = ("utc_ms", "year", "month", "day", "lat", "lon", "alt", "sog", "cog", "climb", "mode", "quality",
              "sats", "hdop")


@lru_cache(maxsize=1)
def synthetic_run(duration: float = 40.0, seed: int = 3):
    return make_run(Scenario(duration=duration, seed=seed))[0]


def device_log(header: dict[str, str] | None = None, gps: dict[int, dict[str, int]] | None = None,
               block: int = BLOCK, run=None) -> bytes:
    """The run (default: synthetic_run()) as a device log; `header` values replace HEADER's (None removes one),
    `gps` {record index: {field: value}} replaces fields of single GPS records (the rest as the receiver gave
    them)."""
    log = run if run is not None else synthetic_run()
    values = {**HEADER, **(header or {})}
    text = ";".join(f"{key}={value}" for key, value in values.items() if value is not None).encode()
    records = [struct.pack("<BBH", 0x48, 1, len(text)) + text]
    counts = np.round(log.imu.acc / STANDARD_GRAVITY * 16384).astype(int)
    t0 = log.imu.t[0]
    events = [(t, 0, i) for i, t in enumerate(log.imu.t)] + [(t + 0.3, 1, i) for i, t in enumerate(log.gps.t)]
    v = log.gps.vel
    for number, (t, kind, i) in enumerate(sorted(events)):
        t_us = int(round((t - t0 + 5.0) * 1e6)) & 0xFFFFFFFF
        if kind == 0:
            records.append(struct.pack("<BI6h", 0x49, t_us, *counts[i], 0, 0, 0))
            continue
        utc = START_UTC + log.gps.t[i]
        y, mo, d = time.gmtime(utc - utc % 86400)[:3]
        fix = dict(zip(GPS_FIELDS, (int(round((utc % 86400) * 1000)), y, mo, d, int(round(log.gps.lat[i] * 1e7)),
                                    int(round(log.gps.lon[i] * 1e7)), 400000, int(np.hypot(v[i, 0], v[i, 1]) * 1000),
                                    int(np.degrees(np.arctan2(v[i, 0], v[i, 1])) % 360.0 * 100) % 36000,
                                    int(round(v[i, 2] * 1000)), 3, 1, 8, 120)))
        fix.update((gps or {}).get(i, {}))
        records.append(struct.pack("<BIIHBBiiiiHiBBBH", 0x47, t_us, *(fix[name] for name in GPS_FIELDS)))
    out, current = bytearray(), bytearray()
    for record in records:
        if len(current) + len(record) > block:
            out += current + bytes(block - len(current))
            current = bytearray()
        current += record
    out += current + bytes(block - len(current))
    return bytes(out)
