"""The app's own numbers in the boards' single precision (the 32-bit unix MicroPython, tests/conftest.py).

Each case here is one the double-precision PyPI interpreter computes right and a board did not: the values are
chosen from those where float32 rounding lands on the other side of an integer than float64's.
"""

from __future__ import annotations

import struct

import pytest

from codegen.sim.harness import generate_app, run_script, sentence
from conftest import board_micropython

LOG_ONE_FIX = r"""
import struct
import sys
import logger
from nmea import Nmea

got = []
p = Nmea(on_fix=got.append)
for line in sys.argv[1:]:
    p.feed(line.encode() + b"\r\n")
log = logger.Logger("test", 1)  # one sample per record; the unix port cannot make the log folder: logging off
log.enabled = True  # ... and on again, for the record's encoding alone
log.used = 0
log.gps(got[-1])
print(bytes(log.block[:struct.calcsize(logger.GPS_FMT)]).hex())
"""


@pytest.fixture(scope="module")
def app_dir(tmp_path_factory):
    return generate_app("ttgo-tbeam-v1.1", tmp_path_factory.mktemp("gen") / "out") / "app"


@pytest.mark.parametrize("alt, hdop", [("-128.4", "0.53"), ("-261.8", "1.17"), ("183.8", "1.05")])
def test_log_keeps_the_receivers_decimals(app_dir, tmp_path, alt, hdop):
    """float32("-128.4") * 1000 is -128399.99...: the logger truncated it to -128399 mm (and 0.53 to an HDOP of
    0.52); the log holds the receiver's decimals exactly."""
    script = tmp_path / "log_fix.py"
    script.write_text(LOG_ONE_FIX)
    epoch = [sentence("GPRMC,120000.00,A,4002.10513,N,07531.20562,W,1.000,90.00,241013,,,A"),
             sentence(f"GPGGA,120000.00,4002.10513,N,07531.20562,W,1,07,{hdop},{alt},M,-34.4,M,,"),
             sentence("GPGSA,A,3,28,17,01,08,09,11,32,,,,,,2.94,1.72,2.39"),
             sentence("GPRMC,120001.00,A,4002.10513,N,07531.20562,W,1.000,90.00,241013,,,A")]
    done = run_script(board_micropython(), app_dir, str(script), epoch, timeout=60)
    assert done.returncode == 0, done.stderr + done.stdout
    record = bytes.fromhex(done.stdout.split()[-1])
    fields = struct.unpack("<BHHiHBBiiiiHiBBBH", record)
    alt_mm, sog_mm, cog, hdop_100 = fields[9], fields[10], fields[11], fields[16]
    assert alt_mm == round(float(alt) * 1000) and hdop_100 == round(float(hdop) * 100), (alt_mm, hdop_100)
    assert sog_mm == 514 and cog == 9000  # 1 kn, 90 degrees


CLIMB = r"""
import struct
import sys
from nmea import Nmea

got = []
p = Nmea(on_fix=got.append)
for line in sys.argv[1:]:
    p.feed(line.encode() + b"\r\n")
print(" ".join("%d:%s" % (round(f.alt_m * 1000), struct.pack("<f", f.climb_ms or 0.0).hex()) for f in got))
"""


def _epoch(second: int, alt: str) -> list[str]:
    utc = f"1200{second:02d}.00"
    return [sentence(f"GPRMC,{utc},A,4005.80138,N,10508.83204,W,0.000,,241013,,,A"),
            sentence(f"GPGGA,{utc},4005.80138,N,10508.83204,W,1,07,1.1,{alt},M,-21.0,M,,"),
            sentence("GPGSA,A,3,28,17,01,08,09,11,32,,,,,,2.94,1.72,2.39")]


def test_climb_rate_from_the_receivers_altitudes_not_their_floats(app_dir, tmp_path):
    """Boulder, 1600 m up: a float32 altitude there is a multiple of 0.12 mm (30-bit floats: 0.5 mm), so two of them
    0.2 m apart gave a climb of 0.19995 m/s (CircuitPython: 0.19983). The parser keeps altitudes in integer
    millimetres, as it keeps positions in 1e-7 degree: the climb is one rounding from the truth."""
    script = tmp_path / "climb.py"
    script.write_text(CLIMB)
    lines = _epoch(0, "1600.2") + _epoch(1, "1600.4") + _epoch(2, "1599.9") + _epoch(3, "-0.0005") + \
        [sentence("GPRMC,120004.00,A,4005.80138,N,10508.83204,W,0.000,,241013,,,A")]
    done = run_script(board_micropython(), app_dir, str(script), lines, timeout=60)
    assert done.returncode == 0, done.stderr + done.stdout
    fixes = [(int(a), struct.unpack("<f", bytes.fromhex(c))[0]) for a, c in
             (item.split(":") for item in done.stdout.split())]
    assert [a for a, _ in fixes] == [1600200, 1600400, 1599900, -1]
    for (_, climb), want in zip(fixes[1:], (0.2, -0.5, -1599.901)):
        assert abs(climb - want) <= 2.0**-23 * abs(want), (climb, want)
