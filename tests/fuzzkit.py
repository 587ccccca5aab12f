"""Generative fuzzing of the CLI (tests/test_hostile_fuzz.py runs a few hundred inputs, benchmarks/hostile_fuzz.py
thousands): seeded mutations of the bundled board files, of a device log, of a run's CSV pair, NMEA and GPX
logs, each run through `deadreckon validate` or `deadreckon post` in this process, and of a raw REPL's replies to
`deadreckon upload` (a peer on loopback TCP that speaks the protocol but answers each command with a mutated reply).

The oracle, for every input: no exception escapes the CLI (a traceback), the exit status is 0 or 2 (2 with an
`error:` on stderr), and the run ends within BOUND_S. Mutations are drawn from a `random.Random(seed)`, so a
failure is reproduced by its kind, seed and index (printed with the input's first bytes).
"""

from __future__ import annotations

import contextlib
import io
import os
import random
import struct
import time
import traceback
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterator

from codegen.paths import board_configs_dir

BOUND_S = 20.0  # one in-process run (a valid 12 s log posts in 0.2 s; a board validates in 0.1 s)
# an upload to a REPL that misbehaves may wait out a reply's deadline (10 s, up to 3x while the port still talks)
BOUNDS = {"repl": 90.0}
KINDS = ("board", "devicelog", "csv", "nmea", "gpx", "repl")
HOSTILE_TOKENS = (".inf", "-.inf", ".nan", "nan", "inf", "-inf", "1e-320", "1e308", "-1e309", "-1", "0", "0.0",
                  "99999999999999999999999", "-99999999999999999999999", "0x7fffffffffffffff", "''", "[]", "{}",
                  "null", "true", "~", '"\\0"', "a" * 300, "../../../../etc/passwd", "*nowhere", "!!binary AAAA",
                  "&a", "\t", "é", "\u202e", "1_000", "0b101", "0o777", "+.5", "1e3", "12:30:00", "2026-13-45")


@dataclass
class Failure:
    kind: str
    index: int
    reason: str
    sample: bytes


@dataclass
class Tally:
    kind: str
    inputs: int = 0
    accepted: int = 0  # exit 0
    refused: int = 0  # exit 2 with an error:
    slowest_s: float = 0.0
    seconds: float = 0.0
    failures: list[Failure] = field(default_factory=list)


def run_cli(argv: list[str], cwd: Path) -> tuple[int | str, str, float]:
    """`deadreckon ARGV` in this process, in `cwd`: (exit status or the traceback's last line, stderr, seconds)."""
    from codegen.cli import main

    err, out = io.StringIO(), io.StringIO()
    started = time.monotonic()
    here = os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status: int | str = main(argv)
            except SystemExit as stop:  # argparse refusing an option
                status = stop.code if isinstance(stop.code, int) else 2
            except BaseException as problem:  # noqa: BLE001 - anything here is the bug the fuzzer looks for
                status = "".join(traceback.format_exception_only(type(problem), problem)).strip()
    finally:
        os.chdir(here)
    return status, err.getvalue(), time.monotonic() - started


# -- the inputs ----------------------------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _run():
    from codegen.post.synthetic import Scenario, make_run

    return make_run(Scenario(duration=12.0, seed=4))[0]


def _mutate_text(text: str, rng: random.Random, separators: str) -> str:
    """1 to 3 edits: a field replaced by a hostile token, a line dropped, doubled or swapped, a character flipped,
    a NUL or a control character inserted, the text cut short."""
    for _ in range(rng.randint(1, 3)):
        lines = text.split("\n")
        choice = rng.randrange(8)
        at = rng.randrange(len(lines))
        if choice <= 2:  # a field (after a separator) replaced
            positions = [i for i, ch in enumerate(lines[at]) if ch in separators]
            if positions:
                start = rng.choice(positions) + 1
                end = min([i for i in positions if i >= start] + [len(lines[at])])
                lines[at] = lines[at][:start] + " " * (separators == ":") + rng.choice(HOSTILE_TOKENS) + lines[at][end:]
        elif choice == 3:
            del lines[at]
        elif choice == 4:
            lines.insert(at, lines[at])
        elif choice == 5:
            other = rng.randrange(len(lines))
            lines[at], lines[other] = lines[other], lines[at]
        elif choice == 6 and lines[at]:
            spot = rng.randrange(len(lines[at]))
            lines[at] = lines[at][:spot] + chr(rng.choice((0, 1, 7, 0x1b, 0x7f, 0xfffd, rng.randrange(32, 127)))) \
                + lines[at][spot + 1:]
        else:
            text = "\n".join(lines)
            lines = text[:rng.randrange(len(text) + 1)].split("\n")
        text = "\n".join(lines)
    return text


def board_inputs(rng: random.Random) -> Iterator[tuple[dict[str, bytes], list[str]]]:
    boards = sorted(board_configs_dir().glob("*.yaml"))
    texts = [path.read_text() for path in boards]
    while True:
        text = _mutate_text(rng.choice(texts), rng, ":,[{")
        yield {"b.yaml": text.encode("utf-8", "surrogatepass")}, ["validate", "b.yaml"]


def _device_log_bytes(header: dict | None = None, gps: dict | None = None) -> bytes:
    import inputkit

    return inputkit.device_log(header, gps, run=_run())


def devicelog_inputs(rng: random.Random) -> Iterator[tuple[dict[str, bytes], list[str]]]:
    import inputkit

    base = _device_log_bytes()
    limits = {"B": 255, "H": 0xFFFF, "I": 0xFFFFFFFF}
    gps_formats = "IHBBiiiiHiBBBH"  # the G record after its type and time stamp, as GPS_FIELDS
    while True:
        choice = rng.randrange(5)
        if choice == 0:  # a header value replaced
            key = rng.choice(list(inputkit.HEADER) + ["extra"])
            data = _device_log_bytes(header={key: rng.choice(HOSTILE_TOKENS + ("", "4096", "+0-1+2", "7"))})
        elif choice == 1:  # a GPS record's field at an extreme of its type
            field_index = rng.randrange(len(inputkit.GPS_FIELDS))
            kind = gps_formats[field_index]
            value = rng.choice((0, limits[kind.upper()], rng.randrange(limits[kind.upper()] + 1)))
            if kind.islower():  # signed
                value = rng.choice((-(2**31), 2**31 - 1, 0, rng.randrange(-(2**31), 2**31)))
            record = rng.randrange(12)
            data = _device_log_bytes(gps={record: {inputkit.GPS_FIELDS[field_index]: value}})
        elif choice == 2:  # bytes flipped anywhere
            data = bytearray(base)
            for _ in range(rng.randint(1, 16)):
                data[rng.randrange(len(data))] = rng.randrange(256)
            data = bytes(data)
        elif choice == 3:  # cut short, or blocks doubled or dropped
            blocks = [base[i:i + inputkit.BLOCK] for i in range(0, len(base), inputkit.BLOCK)]
            action = rng.randrange(3)
            if action == 0:
                data = base[:rng.randrange(len(base) + 1)]
            elif action == 1:
                at = rng.randrange(len(blocks))
                data = b"".join(blocks[:at + 1] + blocks[at:])
            else:
                del blocks[rng.randrange(len(blocks))]
                data = b"".join(blocks)
        else:  # a random record type byte, or a header of random length
            data = bytearray(base)
            at = rng.randrange(len(data))
            data[at:at + 4] = struct.pack("<BBH", rng.choice((0x48, 0x49, 0x47, 0x57, 0x45, 0x99)), rng.randrange(3),
                                          rng.randrange(65536))
            data = bytes(data)
        yield {"dr00001.bin": data}, ["post", "dr00001.bin", "-o", "post-out", "--no-plots"]


def _csv_pair() -> tuple[str, str]:
    import tempfile

    from codegen.post.synthetic import write_csv_pair

    with tempfile.TemporaryDirectory() as folder:
        imu, gps = write_csv_pair(_run(), Path(folder))
        return imu.read_text(), gps.read_text()


def _absolute_imu() -> str:
    """The IMU CSV on the UTC axis of the NMEA and GPX logs."""
    import inputkit

    lines = _csv_pair()[0].split("\n")
    out = [lines[0]]
    for line in lines[1:]:
        if line:
            t, rest = line.split(",", 1)
            out.append(f"{float(t) + inputkit.START_UTC:.4f},{rest}")
    return "\n".join(out) + "\n"


def _nmea() -> str:
    import math

    import inputkit

    run = _run()
    lines = []
    for i, t in enumerate(run.gps.t):
        stamp = time.gmtime(inputkit.START_UTC + t)
        hms = time.strftime("%H%M%S", stamp) + f".{int(round((t % 1) * 100)):02d}"
        lat, lon = run.gps.lat[i], run.gps.lon[i]
        v = run.gps.vel[i]
        knots = math.hypot(v[0], v[1]) / 0.514444
        course = math.degrees(math.atan2(v[0], v[1])) % 360.0
        ns = f"{int(abs(lat)):02d}{(abs(lat) % 1) * 60:08.5f},{'N' if lat >= 0 else 'S'}"
        ew = f"{int(abs(lon)):03d}{(abs(lon) % 1) * 60:08.5f},{'E' if lon >= 0 else 'W'}"
        for body in (f"GPRMC,{hms},A,{ns},{ew},{knots:.3f},{course:.2f},{time.strftime('%d%m%y', stamp)},,,A",
                     f"GPGGA,{hms},{ns},{ew},1,08,0.9,400.0,"
                     "M,46.9,M,,"):
            checksum = 0
            for ch in body:
                checksum ^= ord(ch)
            lines.append(f"${body}*{checksum:02X}")
    return "\r\n".join(lines) + "\r\n"


def _gpx() -> str:
    import inputkit

    run = _run()
    points = "".join(
        f'<trkpt lat="{run.gps.lat[i]:.8f}" lon="{run.gps.lon[i]:.8f}"><ele>400.0</ele>'
        f'<time>{time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(inputkit.START_UTC + t))}.'
        f'{int(round((t % 1) * 1000)):03d}Z</time></trkpt>\n'
        for i, t in enumerate(run.gps.t))
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<gpx version="1.1" creator="fuzz" '
            f'xmlns="http://www.topografix.com/GPX/1/1">\n<trk><trkseg>\n{points}</trkseg></trk>\n</gpx>\n')


def _text_inputs(rng, make: Callable[[], tuple[str, str]], name: str, separators: str, extra=()):
    imu, gps = make()
    while True:
        if rng.random() < 0.25:
            files = {"imu.csv": _mutate_text(imu, rng, ","), name: gps}
        else:
            mutated = _mutate_text(gps, rng, separators)
            if extra and rng.random() < 0.2:
                mutated = rng.choice(extra)(mutated)
            files = {"imu.csv": imu, name: mutated}
        yield ({k: v.encode("utf-8", "surrogatepass") for k, v in files.items()},
               ["post", "imu.csv", "--gps", name, "-o", "post-out", "--no-plots"])


def csv_inputs(rng):
    return _text_inputs(rng, _csv_pair, "gps.csv", ",")


def nmea_inputs(rng):
    return _text_inputs(rng, lambda: (_absolute_imu(), _nmea()), "gps.nmea", ",*")


GPX_DAMAGE = (
    lambda text: text.replace("<?xml version=\"1.0\" encoding=\"UTF-8\"?>",
                              '<?xml version="1.0"?><!DOCTYPE gpx [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;">]>'),
    lambda text: text.replace("</trkseg>", ""),
    lambda text: text.replace('lat="', 'lat="9', 3),
    lambda text: text.replace("<time>", "<time>9999-", 2),
    lambda text: text.replace("<ele>400.0</ele>", "<ele>1e999</ele>"),
)


def gpx_inputs(rng):
    return _text_inputs(rng, lambda: (_absolute_imu(), _gpx()), "gps.gpx", "\"<>", GPX_DAMAGE)


@lru_cache(maxsize=1)
def _built_tree() -> dict[str, bytes]:
    """The default board's generated and built tree, as relative path -> bytes (made once per process)."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="deadreckon-fuzz-tree-") as folder:
        status, stderr, _ = run_cli(["generate", "-o", "out"], Path(folder))
        assert status == 0, stderr
        status, stderr, _ = run_cli(["build", "out"], Path(folder))
        assert status == 0, stderr
        root = Path(folder)
        return {str(path.relative_to(root)): path.read_bytes() for path in sorted(root.rglob("*")) if path.is_file()}


ERRNOS = (2, 5, 12, 13, 17, 19, 21, 22, 28, 30, 39, 110)


def _repl_reply(rng: random.Random, command: bytes) -> bytes:
    """A raw REPL's answer to `command`, damaged: the OK, the output, the error text or the terminators."""
    hex64 = "".join(rng.choice("0123456789abcdef") for _ in range(64))
    outputs = (b"", bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))),
               f"/main.py {hex64}\r\n/app.py -\r\n".encode(), f"{hex64} ?\r\n".encode() * rng.randint(1, 40),
               b"\xff\xfe" * rng.randint(1, 500), b"x" * rng.randrange(100000), rng.choice(HOSTILE_TOKENS).encode(),
               command[:rng.randrange(len(command) + 1)])
    errors = (b"", f"Traceback (most recent call last):\r\n  File \"<stdin>\", line {rng.randint(1, 99)}\r\n"
                   f"OSError: [Errno {rng.choice(ERRNOS)}] E\r\n".encode(),
              b"MemoryError: memory allocation failed\r\n", bytes(rng.randrange(256) for _ in range(40)))
    ok = rng.choice((b"OK", b"OK", b"OK", b"", b"ok", b"O"))
    reply = ok + rng.choice(outputs) + b"\x04" + rng.choice(errors) + b"\x04>"
    if rng.random() < 0.1:  # terminators lost: the client's deadline must end it
        reply = reply[:rng.randrange(len(reply) + 1)]
    return reply


def repl_inputs(rng: random.Random) -> Iterator[tuple[dict[str, bytes], list[str]]]:
    from peers.bad_ports import BadPort

    class MutatingRepl(BadPort):
        """A raw REPL on loopback whose every reply is mutated (after `honest` commands answered like a liar)."""

        def __init__(self, seed: int):
            super().__init__("liar")
            self.behaviour = "mutating"
            self.seed = seed

        def _mutating(self, conn) -> None:
            replies = random.Random(self.seed)
            honest = replies.randrange(6)
            for count, command in enumerate(self._commands(conn)):
                if count < honest:
                    conn.sendall(b"OK\x04\x04>")
                elif replies.random() < 0.03:
                    conn.shutdown(2)  # unplugged mid-transfer
                    return
                else:
                    conn.sendall(_repl_reply(replies, command))

    tree = _built_tree()
    while True:
        seed = rng.randrange(2**32)
        with MutatingRepl(seed) as port:  # the peer's seed first: a failure's sample names the replies
            yield {"peer-seed.txt": f"{seed}\n".encode(), **tree}, ["upload", "out", "--port", port.url]


GENERATORS = {"board": board_inputs, "devicelog": devicelog_inputs, "csv": csv_inputs, "nmea": nmea_inputs,
              "gpx": gpx_inputs, "repl": repl_inputs}


def fuzz(kind: str, count: int, seed: int, folder: Path, bound_s: float | None = None) -> Tally:
    """Run `count` inputs of `kind` (seeded) in fresh subfolders of `folder`; the oracle's verdict in a Tally.
    `bound_s`: seconds one run may take (default the kind's own bound, else BOUND_S)."""
    import shutil

    bound_s = BOUNDS.get(kind, BOUND_S) if bound_s is None else bound_s
    tally = Tally(kind)
    inputs = GENERATORS[kind](random.Random(f"{kind}:{seed}"))
    started = time.monotonic()
    for index in range(count):
        files, argv = next(inputs)
        work = folder / f"{kind}-{index}"
        work.mkdir(parents=True)
        for name, data in files.items():
            (work / name).parent.mkdir(parents=True, exist_ok=True)  # a tree's files sit in folders
            (work / name).write_bytes(data)
        status, stderr, seconds = run_cli(argv, work)
        tally.inputs += 1
        tally.slowest_s = max(tally.slowest_s, seconds)
        sample = b"".join(files.values())[:200]
        if isinstance(status, str):
            tally.failures.append(Failure(kind, index, f"traceback: {status[-300:]}", sample))
        elif status not in (0, 2):
            tally.failures.append(Failure(kind, index, f"exit status {status}: {stderr[-300:]}", sample))
        elif status == 2 and "error:" not in stderr:
            tally.failures.append(Failure(kind, index, f"exit 2 without an error: {stderr[-300:]}", sample))
        elif seconds > bound_s:
            tally.failures.append(Failure(kind, index, f"{seconds:.1f} s, over the {bound_s:g} s bound", sample))
        else:
            tally.accepted += status == 0
            tally.refused += status == 2
        shutil.rmtree(work, ignore_errors=True)
    tally.seconds = time.monotonic() - started
    return tally
