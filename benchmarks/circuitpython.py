"""What the CircuitPython target costs, in five tables, on CircuitPython itself.

    python3 benchmarks/circuitpython.py [precision] [compile] [heap] [loop] [ulab]      (all five by default)

The interpreter is CircuitPython 10.2.1's unix port as its boards compute (30-bit floats, 32-bit objects, ulab),
built once from ../shared/circuitpython into the cache (codegen/portbuild.py); its mpy-cross likewise.

precision  A GPS position kept as a CircuitPython float (30 bits: float32 with the two lowest mantissa bits
           dropped, MICROPY_OBJ_REPR_C; 22 significant bits, as CircuitPython's time.monotonic docs say), as a
           MicroPython float32 and as the app's integer 1e-7 degree: the step between representable values, in
           metres, at a latitude of 40 degrees and a longitude of -105 degrees. This is why the app keeps its own NMEA
           parser (integer 1e-7 degree) rather than adafruit_gps, which keeps latitude and longitude as floats.
           Computed on the host (numpy), exact.
compile    Per module of the generated CircuitPython app: its source bytes and the peak CircuitPython's compiler adds
           to the heap compiling it at import (micropython.mem_info's peak), the cost a .py build leaves to the board.
heap       The heap free at the start of the app (gc.mem_free() after code.py's imports, before the app's buffers)
           on the emulated board with the board's own heap, shipped as .py and as CircuitPython .mpy (deadreckon
           build with CircuitPython's mpy-cross).
loop       The generated CircuitPython app through a simulated walk with a 10 s outage, on the emulated
           CircuitPython board (codegen/sim/cpsim over mpsim: the board clock's costs and the board's heap), at 100 and
           200 Hz: the kernel's board time per window of fallback batch, samples dropped, the least heap free.
           Board times come from the MicroPython cost model (codegen/sim/boardclock.py), not measured on
           CircuitPython's boards.
ulab       Host time (x86-64, CircuitPython's 32-bit unix port) of the same windows through the kernels in pure
           Python and with ulab: the seed's block medians (3 axes x n/b blocks of b samples: the Shell sort of
           lib/dr_fallback.py against ulab's numpy.median on the block) and the fused kernel's window, whose
           per-sample recursion ulab cannot take over: only its conversion of the window's counts to scaled floats
           could be vectorised, timed both ways. The app uses ulab where it is at least 3x faster and equal within the
           30-bit rounding (tests/test_circuitpython_ulab.py): the seed's block medians.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from cpkit import CODE_PY_IMPORTS, walk_world  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.deploy.build import build  # noqa: E402
from codegen.sim.cpharness import run_circuitpython, with_circuitpython  # noqa: E402
from codegen.sim.harness import generate_app  # noqa: E402

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
        print("Compiling the CircuitPython app's modules at import (CircuitPython 10.2.1's 32-bit unix port)")
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
                heap = min(run.heap_free(), default=-1)
                full = [us for n, us in wins if n == max(n for n, _ in wins)] if wins else [0]
                n_max = max((n for n, _ in wins), default=0)
                print(f"{name:38s} {rate:7d} {np.median(full) / 1000:16.1f} {n_max:14d} {dropped:8d} {heap:16d}"
                      + ("" if run.returncode == 0 else f"  (exit {run.returncode})"))


HEAP_CODE = CODE_PY_IMPORTS + "import app\ngc.collect()\nprint('HEAP_FREE', gc.mem_free())\n"


def heap(cp: str) -> None:
    print("Heap free at the app's start (after code.py's imports, before its buffers), on the board's own heap")
    print(f"{'board':38s} {'heap B':>8s} {'.py: free B':>12s} {'.mpy: free B':>13s} {'.mpy - .py B':>13s}")
    for name in BOARDS:
        with tempfile.TemporaryDirectory() as tmp:
            board = load_board(name).board
            out = generate_app(name, Path(tmp) / "out")
            build(out, progress=lambda line: None)
            sources = Path(tmp) / "py"
            shutil.copytree(out / "app", sources)
            world, _ = walk_world(board, "walk", 7, 2.0, [], Path(tmp) / "world")
            free = {}
            for kind, app in (("py", sources), ("mpy", out / "build" / "app")):
                copy = Path(tmp) / f"run-{kind}"
                shutil.copytree(app, copy)
                (copy / "code.py").write_text(HEAP_CODE)
                run = run_circuitpython(cp, copy, with_circuitpython(world, board), Path(tmp) / f"w-{kind}",
                                        heap_bytes=board.heap_bytes)
                found = re.search(r"^HEAP_FREE (\d+)", run.stdout, re.M)
                free[kind] = int(found.group(1)) if found else None
                if not found:
                    print(f"  {kind}: {run.stdout[-300:]}")
            gain = free["mpy"] - free["py"] if None not in free.values() else "-"
            print(f"{name:38s} {board.heap_bytes:8d} {free['py']!s:>12s} {free['mpy']!s:>13s} {gain!s:>13s}")


ULAB_PROBE = r"""
import random
import time
from array import array
from ulab import numpy as np

import dr_fallback as dr

random.seed(1)
N = 10
B = dr.BLOCK
W = dr.WINDOW
src = array("f", [random.random() * 4 - 2 for _ in range(W)])
x = array("f", src)
pure = fast = 0
for _ in range(N):
    for axis in range(3):
        x[:] = src
        t0 = time.ticks_us()
        for j in range(W // B):
            dr._median(x, j * B, B)
        pure += time.ticks_diff(time.ticks_us(), t0)
        x[:] = src
        t0 = time.ticks_us()
        for j in range(W // B):
            np.median(np.frombuffer(x, dtype=np.float, count=B, offset=4 * j * B))
        fast += time.ticks_diff(time.ticks_us(), t0)
print("MEDIANS", W, B, pure / N, fast / N)
if hasattr(dr, "fused_process"):
    st = array("f", bytes(4 * dr.FUSED_STATE_LEN))
    dr.fused_init(st)
    cal = array("h", bytes(12 * dr.CALIBRATION_SAMPLES))
    for i in range(dr.CALIBRATION_SAMPLES):
        cal[6 * i + 2] = 16384
    dr.fused_calibrate(st, cal)
    m = 128
    s = array("h", [random.randint(-200, 200) for _ in range(6 * m)])
    for i in range(m):
        s[6 * i + 2] += 16384
    dt = array("i", [5000] * m)
    out = array("f", bytes(24))
    t0 = time.ticks_us()
    for _ in range(N):
        dr.fused_process(st, s, dt, out)
    window = time.ticks_diff(time.ticks_us(), t0) / N
    scale = 9.80665 / 16384
    f = array("f", bytes(4 * 6 * m))
    t0 = time.ticks_us()
    for _ in range(N):
        for i in range(6 * m):
            f[i] = s[i] * scale
    conv_pure = time.ticks_diff(time.ticks_us(), t0) / N
    t0 = time.ticks_us()
    for _ in range(N):
        g = np.frombuffer(s, dtype=np.int16) * scale
    conv_fast = time.ticks_diff(time.ticks_us(), t0) / N
    print("FUSED", m, window, conv_pure, conv_fast)
"""


def ulab_table(cp: str) -> None:
    print("Pure Python against ulab on the same windows (host x86-64, CircuitPython 10.2.1's 32-bit unix port, us)")
    for mode in ("seed", "fused"):
        with tempfile.TemporaryDirectory() as tmp:
            yaml = Path(tmp) / f"{mode}.yaml"
            yaml.write_text(f"extends: pico-gy521-circuitpython\nname: {mode}\nalgorithm: {{mode: {mode}}}\n")
            out = generate_app(yaml, Path(tmp) / "out")
            probe = Path(tmp) / "probe.py"
            probe.write_text(ULAB_PROBE)
            done = subprocess.run([cp, "-X", "heapsize=16M", str(probe)], capture_output=True, text=True,
                                  timeout=600, env=dict(os.environ, MICROPYPATH=str(out / "app" / "lib")))
            if done.returncode:
                print(f"  {mode}: {(done.stderr or done.stdout)[-500:]}")
                continue
            for line in done.stdout.splitlines():
                part = line.split()
                if part[0] == "MEDIANS" and mode == "seed":
                    w, b, pure, fast = int(part[1]), int(part[2]), float(part[3]), float(part[4])
                    print(f"seed: {3 * (w // b)} block medians of {b} samples per window of {w}: pure Python "
                          f"{pure:.0f}, ulab {fast:.0f} ({pure / fast:.1f}x)")
                elif part[0] == "FUSED" and mode == "fused":
                    m, window, conv_pure, conv_fast = int(part[1]), *(float(v) for v in part[2:])
                    print(f"fused: a batch of {m} samples {window:.0f} in pure Python; of it, the counts to scaled "
                          f"floats: pure Python {conv_pure:.0f}, ulab {conv_fast:.0f} ({conv_pure / conv_fast:.1f}x, "
                          f"at most {conv_pure / window:.0%} of the batch)")


TABLES = ("precision", "compile", "heap", "loop", "ulab")


def main() -> None:
    from codegen import portbuild
    from codegen.tools import SHARED_CIRCUITPYTHON

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", nargs="*", help=", ".join(TABLES) + " (default: all)")
    args = parser.parse_args()
    tables = args.tables or list(TABLES)
    unknown = [t for t in tables if t not in TABLES]
    if unknown:
        parser.error(f"unknown table {unknown[0]!r}: {', '.join(TABLES)}")
    cp = None
    if any(t != "precision" for t in tables):
        try:
            cp = str(portbuild.build(portbuild.CIRCUITPYTHON, SHARED_CIRCUITPYTHON, version="10.2.1", log=print))
        except portbuild.PortBuildError as e:
            print(f"no CircuitPython unix port: {e} ({e.hint})")
    for table in tables:
        if table == "precision":
            precision()
        elif cp is None:
            print(f"{table}: needs CircuitPython's unix port (../shared/circuitpython and gcc-multilib)")
        elif table == "compile":
            compile_peaks(cp)
        elif table == "heap":
            heap(cp)
        elif table == "ulab":
            ulab_table(cp)
        else:
            loop(cp)
        print()


if __name__ == "__main__":
    main()
