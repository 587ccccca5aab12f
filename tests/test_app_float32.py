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
log = logger.Logger("test")  # the unix port cannot make the board's log folder: logging off
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
