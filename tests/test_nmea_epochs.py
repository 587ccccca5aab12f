"""The NMEA parser's epochs on receivers it has not seen, each defect from sentences written here.

- a climb rate only from consecutive fixes: after a gap (silent, or epochs without a fix) the first fix has none;
- the receiver's GSA fix type is its word: 2D stays 2D when GGA carried an altitude;
- a checksum-valid proprietary sentence longer than the line buffer is a valid sentence (ignored), not garbage;
- RMC-only and GGA-only streams: each epoch's fix is delivered with that epoch's fields, at its own sentence once
  the receiver's epoch end is learned;
- a read holding several epochs delivers every fix, in order (on_fix).
"""

from __future__ import annotations

import json

import pytest

from codegen.sim.harness import generate_app, run_script, sentence
from conftest import board_micropython

DRIVER = r"""
import sys, json
from nmea import Nmea
cases = json.loads(open(sys.argv[1]).read())
result = {}
for name, chunks in cases:
    fixes = []
    def on_fix(f):
        fixes.append([f.utc_ms, f.lat_e7, f.lon_e7, f.alt_m, f.climb_ms, f.mode, f.speed_ms, f.course_deg])
    p = Nmea(on_fix)
    for c in chunks:
        p.feed(c.encode("latin-1"))
    result[name] = {"fixes": fixes, "count": p.fixes, "mode": p.mode, "climb": p.climb_ms, "bad_lines": p.bad_lines,
                    "bad_checksum": p.bad_checksum, "ignored": p.ignored, "sentences": p.sentences}
print(json.dumps(result))
"""

LAT0 = 4002.10513  # ddmm.mmmmm, 40.0350855 N


def hms(t):
    t = 43200 + t
    return f"{t // 3600:02d}{t // 60 % 60:02d}{t % 60:02d}.00"


def lat(t):
    """Latitude field moving north 1e-5 minute per second, so every epoch has its own position."""
    return f"{LAT0 + t * 1e-5:.5f}"


def lat_e7(t):
    minutes = LAT0 - 4000 + t * 1e-5
    return 400000000 + round(minutes * 1e7 / 60)


def rmc(t, valid=True, knots="1.944", course="271.5"):
    if not valid:
        return sentence(f"GPRMC,{hms(t)},V,,,,,,,241013,,,N")
    return sentence(f"GPRMC,{hms(t)},A,{lat(t)},N,07531.20562,W,{knots},{course},241013,,,A")


def gga(t, alt=183.8, valid=True):
    if not valid:
        return sentence(f"GPGGA,{hms(t)},,,,,0,00,99.99,,,,,,")
    return sentence(f"GPGGA,{hms(t)},{lat(t)},N,07531.20562,W,1,07,1.72,{alt:.1f},M,-34.4,M,,")


def gsa(mode=3):
    return sentence(f"GPGSA,A,{mode},28,17,01,08,09,11,32,,,,,,2.94,1.72,2.39")


def vtg():
    return sentence("GPVTG,271.50,T,,M,1.944,N,3.600,K,A")


def epoch(t, alt=183.8, mode=3, valid=True):
    """A NEO-6M epoch: RMC, VTG, GGA, GSA."""
    if not valid:
        return "".join(s + "\r\n" for s in (rmc(t, False), "$GPVTG,,,,,,,,,N*30", gga(t, valid=False), gsa(1)))
    return "".join(s + "\r\n" for s in (rmc(t), vtg(), gga(t, alt), gsa(mode)))


@pytest.fixture(scope="module")
def parse(tmp_path_factory):
    micropython = board_micropython()
    folder = tmp_path_factory.mktemp("nmea")
    app = generate_app("ttgo-tbeam-v1.1", folder / "out") / "app"
    script = folder / "driver.py"
    script.write_text(DRIVER)

    def run(cases):
        (folder / "cases.json").write_text(json.dumps(cases))
        done = run_script(micropython, app, str(script), [str(folder / "cases.json")])
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    return run


def test_climb_only_from_consecutive_fixes(parse):
    steady = [epoch(t, alt=100.0 + t) for t in range(4)]  # +1 m/s
    got = parse([
        ("silent_gap", steady + [epoch(70, alt=560.0), epoch(71, alt=561.0)]),
        ("fixless_gap", steady + [epoch(t, valid=False) for t in range(4, 70)] + [epoch(70, 560.0),
                                                                                   epoch(71, 561.0)]),
        ("steady", steady + [epoch(4, alt=104.0)]),
    ])
    for name in ("silent_gap", "fixless_gap"):
        fixes = got[name]["fixes"]
        after_gap = [f for f in fixes if f[0] == 43270000]
        assert after_gap and after_gap[0][4] is None, (name, fixes)  # not (560 - 103) / 67 s = 6.8 m/s
        assert [f for f in fixes if f[0] == 43271000][0][4] == pytest.approx(1.0), name
    assert [f[4] for f in got["steady"]["fixes"][1:]] == pytest.approx([1.0, 1.0, 1.0, 1.0])


def test_gsa_2d_after_a_gga_altitude_stays_2d(parse):
    got = parse([("2d", [epoch(0, mode=2), epoch(1, mode=2), epoch(2, mode=2)]),
                 ("3d", [epoch(0), epoch(1), epoch(2)])])
    assert got["2d"]["mode"] == 2
    # the first epoch closes at its GGA (the receiver's epoch end is not known yet: RMC and GGA make a fix), before
    # its GSA; from the second on, an epoch closes at its GSA, the learned end, with the receiver's 2D
    assert [f[5] for f in got["2d"]["fixes"]][1:] == [2, 2]
    assert [f[5] for f in got["3d"]["fixes"]] == [3, 3, 3]


def test_long_proprietary_sentence_is_valid_not_garbage(parse):
    pubx = sentence("PUBX,00,081350.00,4717.113210,N,00833.915187,E,546.589,G3,2.1,2.0,0.007,77.52,0.007,,"
                    "0.92,1.19,0.77,9,0,0,PADDING0123456789")
    assert len(pubx) > 110
    bad = pubx[:-2] + ("00" if pubx[-2:] != "00" else "01")
    got = parse([("pubx", [pubx + "\r\n", rmc(0) + "\r\n"]),
                 ("pubx_split", [pubx[:50], pubx[50:100], pubx[100:] + "\r\n"]),
                 ("pubx_bad", [bad + "\r\n"]),
                 ("garbage", ["$" + "\x01" * 120 + "*00\r\n"]),
                 ("no_star", ["$PUBX," + "9" * 150 + "\r\n"])])
    for name in ("pubx", "pubx_split"):
        assert got[name]["bad_lines"] == 0 and got[name]["ignored"] == 1, (name, got[name])
    assert got["pubx"]["sentences"] == 1  # the RMC after it parses
    assert got["pubx_bad"]["bad_checksum"] == 1 and got["pubx_bad"]["bad_lines"] == 0
    assert got["garbage"]["bad_lines"] == 1 and got["no_star"]["bad_lines"] == 1


@pytest.mark.parametrize("kind", ["rmc", "gga"])
def test_single_sentence_streams_deliver_each_epoch_with_its_fields(parse, kind):
    make = rmc if kind == "rmc" else gga
    stream = [make(t) + "\r\n" for t in range(5)]
    got = parse([(kind, stream)])[kind]
    fixes = got["fixes"]
    # the first epoch is closed when the second begins (its end was not known yet); from then on every sentence
    # completes its own epoch at once: five sentences, five fixes, each with its own time and position
    assert [f[0] for f in fixes] == [43200000 + 1000 * t for t in range(5)]
    assert [f[1] for f in fixes] == [lat_e7(t) for t in range(5)]
    if kind == "rmc":
        assert all(f[6] == pytest.approx(1.944 * 0.514444) and f[7] == 271.5 for f in fixes)


def test_one_read_with_several_epochs_delivers_every_fix(parse):
    stream = "".join(epoch(t) for t in range(22))
    chunks = [stream[i : i + 512] for i in range(0, len(stream), 512)]
    got = parse([("reads", chunks)])["reads"]
    times = [f[0] for f in got["fixes"]]
    # the first epoch closed at its GGA, the 21 others at their GSA (the end learned from the first): 22, none lost
    assert times == [43200000 + 1000 * t for t in range(22)], times
    assert [f[1] for f in got["fixes"]] == [lat_e7(t) for t in range(22)]
    assert got["count"] == 22
