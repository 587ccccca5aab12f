"""The NMEA parser on MicroPython: edge cases by hand, and a short fuzz run (benchmarks/nmea_fuzz.py runs >= 1e5)."""

from __future__ import annotations

import json
import sys

import pytest

from codegen.sim.harness import generate_app, run_script, sentence
from conftest import ROOT, require_tool

sys.path.insert(0, str(ROOT / "benchmarks"))
from nmea_fuzz import run_fuzz  # noqa: E402


@pytest.fixture(scope="module")
def app_dir(tmp_path_factory):
    return generate_app("ttgo-tbeam-v1.1", tmp_path_factory.mktemp("gen") / "out") / "app"


def test_fuzz_short(app_dir, tmp_path):
    micropython = require_tool("micropython")
    stats = run_fuzz(micropython, app_dir, 3000, 7, tmp_path)
    assert stats["exceptions"] == 0 and stats["failures"] == [], stats["failures"]
    assert stats["bad_checksum_seen"] > 500 and stats["bad_checksum_rejected"] == stats["bad_checksum_seen"]
    assert stats["accepted"] > 300  # the mutations still reach the field parsers


EDGE = r"""
import json
from nmea import Nmea
out = {}
def state(p):
    return [p.lat_e7, p.lon_e7, p.speed_ms, p.course_deg, p.valid, p.mode, p.fixes, p.utc_ms, p.date, p.alt_m,
            p.sentences, p.bad_checksum, p.bad_lines]
CASES = json.loads(open(__import__("sys").argv[1]).read())
for name, chunks in CASES:
    p = Nmea()
    for c in chunks:
        p.feed(c.encode("latin-1") if isinstance(c, str) else bytes(c))
    out[name] = state(p)
print(json.dumps(out))
"""


def test_edge_cases(app_dir, tmp_path):
    micropython = require_tool("micropython")
    rmc = sentence("GPRMC,143252.00,A,4002.10513,N,07531.20562,W,1.944,271.5,241013,,,A")
    gga = sentence("GPGGA,143252.00,4002.10513,N,07531.20562,W,1,07,1.72,183.8,M,-34.4,M,,")
    bad = rmc[:-2] + ("00" if rmc[-2:] != "00" else "01")
    cases = [
        ("valid", [rmc + "\r\n", gga + "\r\n"]),
        ("split_bytes", [ch for ch in rmc + "\r\n" + gga + "\r\n"]),
        ("bad_checksum", [bad + "\r\n"]),
        ("no_checksum", [rmc[: rmc.index("*")] + "\r\n"]),
        ("lowercase_checksum", [rmc[:-2] + rmc[-2:].lower() + "\r\n"]),
        ("garbage_then_valid", ["\x00\xff\x13garbage" + rmc[:20] + rmc + "\r\n"]),
        ("overlong", ["$GPRMC," + "9" * 300 + "\r\n", rmc + "\r\n"]),
        ("empty_fields", [sentence("GPRMC,,V,,,,,,,,,,N") + "\r\n", sentence("GPGGA,,,,,,0,00,99.99,,,,,,") + "\r\n"]),
        ("no_fix_after_fix", [rmc + "\r\n", gga + "\r\n",
                              sentence("GPRMC,143253.00,V,,,,,,,241013,,,N") + "\r\n"]),
        ("bad_minutes", [sentence("GPRMC,143252.00,A,4062.10513,N,07531.20562,W,0.0,,241013,,,A") + "\r\n"]),
        ("partial_line_then_new", [rmc[:30], "\r\n", gga + "\r\n"]),
    ]
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    script = tmp_path / "edge.py"
    script.write_text(EDGE)
    proc = run_script(micropython, app_dir, str(script), [str(tmp_path / "cases.json")])
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout)
    lat, lon = 400350855, -755200937
    v = got["valid"]
    assert v[:2] == [lat, lon] and v[2] == pytest.approx(1.944 * 0.514444) and v[3] == 271.5
    assert v[4:8] == [True, 3, 1, 52372000] and v[8] == [2013, 10, 24] and v[9] == 183.8
    assert got["split_bytes"][:7] == v[:7]
    assert got["bad_checksum"][10:12] == [0, 1] and got["bad_checksum"][0] is None
    assert got["no_checksum"][10] == 0 and got["no_checksum"][12] == 1
    assert got["lowercase_checksum"][10] == 1
    assert got["garbage_then_valid"][:2] == [lat, lon]
    assert got["overlong"][:2] == [lat, lon] and got["overlong"][12] == 1
    assert got["empty_fields"][4] is False and got["empty_fields"][0] is None and got["empty_fields"][6] == 0
    assert got["no_fix_after_fix"][4] is False and got["no_fix_after_fix"][5] == 1
    assert got["bad_minutes"][0] is None and got["bad_minutes"][4] is False
    assert got["partial_line_then_new"][:2] == [lat, lon] and got["partial_line_then_new"][12] == 1
