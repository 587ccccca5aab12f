"""Fuzz the generated NMEA parser on the unix-port MicroPython: random and mutated sentences, and byte streams.

    python benchmarks/nmea_fuzz.py [--count 100000] [--seed 1] [--board ttgo-tbeam-v1.1]

Oracle: no exception escapes `Nmea.sentence` / `Nmea.feed`; every sentence whose checksum does not match its
content is rejected; accepted fixes stay in range (|lat| <= 90 deg, |lon| <= 180 deg, speed >= 0, course in
[0, 360]); after any garbage the parser still accepts the next valid sentence. Seeds: the gpsd captures in
../shared/data/nmea-gpsd (when present) plus synthesised NEO-6M sentences. Prints a table; exits 1 on any oracle failure.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data" / "nmea-gpsd"

SYNTHETIC = [
    "GPRMC,143252.00,A,4002.10513,N,07531.20562,W,0.016,,241013,,,A",
    "GPVTG,,T,,M,0.016,N,0.030,K,A",
    "GPGGA,143252.00,4002.10513,N,07531.20562,W,1,07,1.72,183.8,M,-34.4,M,,",
    "GPGSA,A,3,28,17,01,08,09,11,32,,,,,,2.94,1.72,2.39",
    "GNRMC,000000.00,A,8959.99999,S,17959.99999,E,999.9,359.99,311299,,,D",
    "GPGLL,4002.10504,N,07531.20566,W,143251.00,A,A",
    "GPRMC,,V,,,,,,,,,,N",
    "GPGGA,,,,,,0,00,99.99,,,,,,",
]

MP_FUZZER = r"""
import sys, time, random, json
from nmea import Nmea

COUNT = int(sys.argv[2])
random.seed(int(sys.argv[3]))
seeds = [l.rstrip(b"\r\n") for l in open(sys.argv[1], "rb") if l.startswith(b"$")]
HEX = b"0123456789ABCDEF"
JUNK = [b"", b"-", b"+5", b"1e999", b"nan", b"inf", b"99999999999999999999", b"0000.0000", b"9999.9999",
        b"-0.5", b"A", b"V", b"N", b"12.3.4", b"\xff", b"*", b"$", b",", b"  ", b"00", b"60.0"]


def body_of(line):
    star = line.rfind(b"*")
    return line[1:star] if star > 0 else line[1:]


def xor(body):
    c = 0
    for b in body:
        c ^= b
    return c


def with_checksum(body):
    c = xor(body)
    return b"$" + body + b"*" + bytes([HEX[c >> 4], HEX[c & 15]])


def rbyte():
    r = random.getrandbits(3)
    if r == 0:
        return bytes([random.getrandbits(8)])
    return bytes([random.choice(b"0123456789.,-+*$ABCDEFGNSWEMKTVP")])


def mutate(body):
    kind = random.getrandbits(3)
    if kind == 0 and body:  # flip a byte
        i = random.randrange(len(body))
        return body[:i] + rbyte() + body[i + 1:]
    if kind == 1 and body:  # delete a span
        i = random.randrange(len(body))
        return body[:i] + body[i + random.randint(1, 6):]
    if kind == 2:  # insert
        i = random.randrange(len(body) + 1)
        return body[:i] + rbyte() + body[i:]
    fields = body.split(b",")
    i = random.randrange(len(fields))
    if kind == 3:
        fields[i] = random.choice(JUNK)
    elif kind == 4:
        fields[i] = b""
    elif kind == 5:
        fields.insert(i, random.choice(JUNK))
    elif kind == 6 and len(fields) > 2:
        fields = fields[: random.randint(1, len(fields))]
    else:
        j = random.randrange(len(fields))
        fields[i], fields[j] = fields[j], fields[i]
    return b",".join(fields)


def random_sentence():
    n = random.randint(0, 90)
    return b"$" + bytes(random.getrandbits(8) for _ in range(n))


def check_state(p):
    if p.lat_e7 is not None and abs(p.lat_e7) > 900000000:
        return "lat out of range %r" % p.lat_e7
    if p.lon_e7 is not None and abs(p.lon_e7) > 1800000000:
        return "lon out of range %r" % p.lon_e7
    if p.speed_ms is not None and not p.speed_ms >= 0:
        return "speed %r" % p.speed_ms
    if p.course_deg is not None and not 0 <= p.course_deg <= 360:
        return "course %r" % p.course_deg
    if p.mode not in (1, 2, 3):
        return "mode %r" % p.mode
    return None


p = Nmea()
stats = {"sentences": 0, "accepted": 0, "bad_checksum_seen": 0, "bad_checksum_rejected": 0, "streams": 0,
         "exceptions": 0, "failures": []}
reference = with_checksum(b"GPGGA,120000.00,4002.10513,N,07531.20562,W,1,07,1.72,183.8,M,-34.4,M,,")
t0 = time.ticks_ms()
for k in range(COUNT):
    r = random.getrandbits(4)
    if r == 0:
        line = random_sentence()
    else:
        seed_line = random.choice(seeds)
        body = body_of(seed_line)
        for _ in range(random.randint(1, 3)):
            body = mutate(body)
        if random.getrandbits(1):
            line = with_checksum(body)
        else:
            line = b"$" + body + seed_line[seed_line.rfind(b"*"):] if b"*" in seed_line else b"$" + body
    stats["sentences"] += 1
    # the oracle: a line "$<body>*hh" whose hh does not match is a bad checksum and must be rejected
    star = line.rfind(b"*")
    declared = line[star + 1:] if star > 0 else b""
    actual = xor(line[1:star]) if star > 0 else None
    bad = (star > 0 and len(declared) == 2 and declared.upper() != bytes([HEX[actual >> 4], HEX[actual & 15]]))
    try:
        ok = p.sentence(line)
    except Exception as e:
        stats["exceptions"] += 1
        stats["failures"].append("sentence raised %r on %r" % (e, line))
        continue
    if ok:
        stats["accepted"] += 1
    if bad:
        stats["bad_checksum_seen"] += 1
        if not ok:
            stats["bad_checksum_rejected"] += 1
        else:
            stats["failures"].append("accepted bad checksum %r" % line)
    problem = check_state(p)
    if problem:
        stats["failures"].append(problem + " after %r" % line)
    if k % 16 == 0:  # byte streams: lines glued, split at random, garbage, overlong
        stats["streams"] += 1
        chunks = []
        for _ in range(random.randint(1, 6)):
            c = random.getrandbits(2)
            if c == 0:
                chunks.append(bytes(random.getrandbits(8) for _ in range(random.randint(0, 200))))
            elif c == 1:
                chunks.append(random.choice(seeds)[: random.randint(0, 90)])
            else:
                chunks.append(line + b"\r\n")
        stream = b"".join(chunks) + b"\r\n" + reference + b"\r\n"
        before = p.sentences
        try:
            i = 0
            while i < len(stream):
                n = random.randint(1, 64)
                p.feed(stream[i:i + n])
                i += n
        except Exception as e:
            stats["exceptions"] += 1
            stats["failures"].append("feed raised %r" % e)
            continue
        if p.sentences == before or p.lat_e7 != 400350855:
            stats["failures"].append("no recovery after %r" % stream[:120])
stats["ms"] = time.ticks_diff(time.ticks_ms(), t0)
stats["failures"] = stats["failures"][:20]
stats["parser"] = {"sentences": p.sentences, "bad_checksum": p.bad_checksum, "bad_lines": p.bad_lines,
                   "ignored": p.ignored, "fixes": p.fixes}
print(json.dumps(stats))
"""


def seed_corpus(path: Path) -> Path:
    lines = []
    if SHARED.is_dir():
        for log in sorted(SHARED.glob("*.log")):
            lines += [line for line in log.read_text(errors="replace").splitlines() if line.startswith("$")]
    for body in SYNTHETIC:
        check = 0
        for ch in body.encode():
            check ^= ch
        lines.append(f"${body}*{check:02X}")
    path.write_text("\n".join(lines) + "\n")
    return path


def run_fuzz(micropython: str, app_dir: Path, count: int, seed: int, work: Path) -> dict:
    corpus = seed_corpus(work / "corpus.txt")
    script = work / "fuzz_mp.py"
    script.write_text(MP_FUZZER)
    env = dict(os.environ, MICROPYPATH=str(app_dir))
    proc = subprocess.run([micropython, "-X", "heapsize=16M", str(script), str(corpus), str(count), str(seed)],
                          capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr or proc.stdout)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--board", default="ttgo-tbeam-v1.1")
    parser.add_argument("--micropython", default="micropython")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from codegen.board.loader import load_board
    from codegen.generate import generate

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        generate(load_board(args.board), work / "out")
        started = time.perf_counter()
        stats = run_fuzz(args.micropython, work / "out" / "app", args.count, args.seed, work)
        wall = time.perf_counter() - started
    rows = [
        ("sentences fuzzed", stats["sentences"]),
        ("byte streams fed (random splits)", stats["streams"]),
        ("accepted", stats["accepted"]),
        ("bad checksums generated", stats["bad_checksum_seen"]),
        ("bad checksums rejected", stats["bad_checksum_rejected"]),
        ("exceptions escaped", stats["exceptions"]),
        ("oracle failures", len(stats["failures"])),
        ("parser counters", json.dumps(stats["parser"])),
        ("MicroPython time (ms)", stats["ms"]),
        ("wall time incl. startup (s)", f"{wall:.1f}"),
        ("sentences per second", f"{stats['sentences'] / max(stats['ms'], 1) * 1000:.0f}"),
    ]
    width = max(len(name) for name, _ in rows)
    print(f"NMEA parser fuzz, board {args.board}, seed {args.seed}")
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    for failure in stats["failures"]:
        print("  FAIL", failure)
    return 1 if stats["failures"] or stats["exceptions"] else 0


if __name__ == "__main__":
    sys.exit(main())
