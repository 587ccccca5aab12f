"""Benchmark: one 512x6 window through every implementation of the kernel; prints a table.

    python3 benchmarks/kernel.py [--board BOARD.yaml] [--repeat N] [--before REV] [--no-device]

Rows: the C kernel via cffi, the NumPy reference, the generated dr_fallback on the unix-port `micropython` (the
template of git revision REV, default main, beside today's: plain, @micropython.native, @micropython.viper), the x64
natmod in that same interpreter (built against MPY_DIR or the shared MicroPython tree), each with the bytes it
allocates per window (benchmarks/mpbench.py says how they are counted), and the C kernel's instruction count per
window (valgrind callgrind on a small C harness) with what that means on a 240 MHz ESP32. Then the boards'
instruction sets (benchmarks/device.py): instructions per window in QEMU, the natmod against every fallback variant
on the same ARM core, and the ESP32 code of the natmod on qemu-system-xtensa with the ESP32 time it implies
(--no-device skips them: they take a few minutes, plus the QEMU port's build on first use). A script that prints,
not a timed test: numbers vary with the machine (here: x86-64 host).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from codegen.board.loader import load_board  # noqa: E402
from codegen.generate import render_tree  # noqa: E402
from codegen.kernel import reference as ref  # noqa: E402
from codegen.tools import find_tool, micropython_tree, tool_env  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mpbench import fallback_rows, measure, print_table  # noqa: E402  (benchmarks/mpbench.py)

ESP32_HZ = 240e6
def window(rng, n):
    samples = np.round(rng.normal(0, 300, (n, 6))).astype(np.int16)
    samples[:, 2] += 16384
    return samples, rng.integers(4900, 5100, n).astype(np.int32)


def best_of(fn, repeat):
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def build_natmod(folder: Path, files) -> tuple[Path | None, str]:
    mpy_dir = micropython_tree()
    if mpy_dir is None:
        return None, "no MicroPython tree (MPY_DIR)"
    native = folder / "native"
    native.mkdir()
    for name, rendered in files.items():
        if name.startswith("native/"):
            (native / name[7:]).parent.mkdir(parents=True, exist_ok=True)
            (native / name[7:]).write_bytes(rendered.content)
    done = subprocess.run(["make", f"MPY_DIR={mpy_dir}", "ARCH=x64", f"MPY_CROSS={find_tool('mpy-cross')}",
                           f"PYTHON={sys.executable}"], cwd=native, capture_output=True, text=True,
                          env=tool_env())
    if done.returncode:
        return None, "natmod build failed"
    return native, ""


def callgrind_instructions(folder: Path, files) -> tuple[float | None, str]:
    """Instructions per window of dr_process: callgrind totals of the harness at 11 and 1 windows, / 10."""
    if not shutil.which("valgrind") or not shutil.which("cc"):
        return None, "valgrind or cc missing"
    src = folder / "c"
    src.mkdir()
    for name, rendered in files.items():
        if name.startswith("native/") and name.endswith((".c", ".h")) and "dr_native" not in name:
            (src / name[7:]).write_bytes(rendered.content)
    harness = ROOT / "native_ext" / "tests" / "bench_kernel.c"
    binary = src / "bench_kernel"
    subprocess.run(["cc", "-std=c99", "-O2", "-I", str(src), str(harness), *map(str, sorted(src.glob("dr_*.c"))),
                    "-o", str(binary)], check=True)
    totals = []
    for windows in (1, 11):
        out = src / f"callgrind.{windows}"
        subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", str(binary), str(windows)],
                       capture_output=True, check=True)
        summary = re.search(r"^(?:summary|totals): (\d+)", out.read_text(), re.M)
        totals.append(int(summary.group(1)))
    return (totals[1] - totals[0]) / 10, ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--board", default=None, help="board YAML (default: the bundled default board)")
    parser.add_argument("--repeat", type=int, default=20, help="timed repetitions (best of)")
    parser.add_argument("--before", default="main", help="git revision whose fallback template to run beside "
                        "today's (default main; '' for none)")
    parser.add_argument("--no-device", action="store_true", help="skip the QEMU rows (boards' instruction sets)")
    args = parser.parse_args(argv)

    loaded = load_board(args.board)
    board = loaded.board
    files = render_tree(loaded)
    n = board.algorithm.window
    cfg = ref.KernelConfig.from_board(board)
    samples, dt = window(np.random.default_rng(1), n)
    rows: list[tuple[str, float | None, int | None, float | None, str]] = []

    from codegen.kernel.hostkernel import load_kernel

    kernel = load_kernel(loaded)
    run = kernel.session()
    rows.append(("C kernel via cffi (host)", best_of(lambda: run.process(samples, dt), args.repeat * 10), None, None,
                 ""))
    rows.append(("NumPy reference (float64)",
                 best_of(lambda: ref.process_window(samples, dt, [1, 0, 0, 0], [0, 0, 0], [0, 0, 0], cfg),
                         max(3, args.repeat // 4)), None, None, ""))

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        fallback = fallback_rows(loaded, files, folder, samples, dt, False, max(3, args.repeat // 4), args.before,
                                 ("process",))
        rows += fallback
        mp_rows = [seconds for label, seconds, *_ in fallback if seconds and label.startswith("dr_fallback now")]
        native, note = build_natmod(folder, files)
        natmod = grown = count = None
        if native is not None:
            natmod, grown, count, note = measure(native, "dr_native", samples, dt, False, args.repeat * 10)
        rows.append(("x64 natmod dr_native on micropython", natmod, grown, count, note))
        instructions, note = callgrind_instructions(folder, files)

    print(f"deadreckon kernel benchmark: one window of {n} x 6 samples, block {board.algorithm.block} "
          f"(board {board.name}), best of runs, x86-64 host")
    print_table(rows, n)
    best_mp = min(mp_rows) if mp_rows else None
    if best_mp and natmod:
        print(f"natmod vs best MicroPython fallback variant, same interpreter: {best_mp / natmod:.0f}x (goal >= 20x)")
    elif best_mp:
        print(f"C (cffi) vs best MicroPython fallback variant: {best_mp / rows[0][1]:.0f}x (goal >= 20x; natmod row "
              "needs a MicroPython tree)")
    if instructions is None:
        print(f"callgrind: - ({note})")
    else:
        print(f"C kernel instructions per window (x86-64, callgrind): {instructions:,.0f}")
        print(f"  at 240 MHz and 1 instruction per cycle: {instructions / ESP32_HZ * 1e3:.2f} ms per window "
              f"(goal <= 5 ms; {instructions / n:.0f} instructions per sample). The ESP32's LX6 is single-issue: "
              f"x86-64 counts are a proxy; 2 cycles per instruction would give {2 * instructions / ESP32_HZ * 1e3:.2f} ms")
    if not args.no_device:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from device import device_table

        device_table(loaded, "seed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
