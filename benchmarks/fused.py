"""Speed of the fused algorithm per window, beside the kernel's budget (<= 5 ms per 512-sample window at
240 MHz by instruction count).

    python3 benchmarks/fused.py [--before REV] [--repeat N] [--no-device] [--scenario replay-walk|replay-car]

Rows: the C kernel (dr_fused_process + one dr_fused_position and dr_fused_gps) through cffi, the float64 reference
(codegen/kernel/fused.py), the generated fallback's fused_* on the unix-port `micropython` (the template of git
revision REV, default main, beside today's: plain, @micropython.native, viper) and the x64 natmod there, each with
the bytes it allocates per window (benchmarks/mpbench.py says how they are counted); then valgrind callgrind's
instruction count of the C harness native_ext/tests/bench_fused.c per window and what it means at 240 MHz (as
benchmarks/kernel.py does for the seed kernel: x86-64 instructions as a proxy for the ESP32's single-issue LX6),
measured on the x86-64 host; then the boards' instruction sets (benchmarks/device.py: QEMU counts of the natmod and
the fallback on ARM cores, REV's fallback beside today's, the natmod's ESP32 code on Xtensa).
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.generate import render_tree  # noqa: E402
from codegen.kernel import fused as F  # noqa: E402
from codegen.kernel.reference import KernelConfig  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from kernel import build_natmod  # noqa: E402  (benchmarks/kernel.py)
from mpbench import fallback_rows, measure, print_table  # noqa: E402  (benchmarks/mpbench.py)

ESP32_HZ = 240e6

def window(rng, n):
    samples = np.round(rng.normal(0, 300, (n, 6)) + [0, 0, 16384, 0, 0, 0]).astype(np.int16)
    dt = (4900 + rng.integers(0, 200, n)).astype(np.int32)
    return samples, dt


def best_of(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def callgrind(files, folder: Path):
    if not shutil.which("valgrind") or not shutil.which("cc"):
        return None, "valgrind or cc missing"
    src = folder / "c"
    src.mkdir()
    for name, rendered in files.items():
        if name.startswith("native/") and name.endswith((".c", ".h")) and "dr_native" not in name and name.count("/") == 1:
            (src / name[7:]).write_bytes(rendered.content)
    binary = src / "bench_fused"
    subprocess.run(["cc", "-std=c99", "-O2", "-I", str(src), str(ROOT / "native_ext" / "tests" / "bench_fused.c"),
                    *map(str, sorted(src.glob("dr_*.c"))), "-o", str(binary)], check=True)
    totals = []
    for windows in (1, 11):
        out = src / f"callgrind.{windows}"
        subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", str(binary), str(windows)],
                       capture_output=True, check=True)
        totals.append(int(re.search(r"^(?:summary|totals): (\d+)", out.read_text(), re.M).group(1)))
    return (totals[1] - totals[0]) / 10, ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed repetitions of the MicroPython rows (best of)")
    parser.add_argument("--before", default="main", help="git revision whose fallback template to run beside "
                        "today's (default main; '' for none)")
    parser.add_argument("--no-device", action="store_true", help="skip the QEMU rows (boards' instruction sets)")
    parser.add_argument("--scenario", default="replay-walk", choices=("replay-walk", "replay-car"),
                        help="the QEMU rows' recording: the walk, or the real car (a vehicle's windows)")
    args = parser.parse_args(argv)
    loaded = load_board(None)
    board = loaded.board
    files = render_tree(loaded)
    n = board.algorithm.window
    samples, dt = window(np.random.default_rng(1), n)
    kcfg = KernelConfig.from_board(board)
    fcfg = F.FusedConfig.from_board(board)
    rows = []
    from codegen.kernel.hostfused import load_fused

    s = load_fused(loaded).session()

    def c_window():
        s.process(samples, dt)
        s.position(1.0, 0.5, 1.0, 0.5)
        s.gps(1.0, 0.5)

    rows.append(("C dr_fused via cffi (host)", best_of(c_window, 200), None, None, ""))
    st = F.FusedState()

    def ref_window():
        F.process(st, samples, dt, kcfg, fcfg)
        F.position_update(st, 1.0, 0.5, 1.0, 0.5, fcfg)
        F.gps_update(st, 1.0, 0.5, fcfg)

    rows.append(("reference codegen/kernel/fused.py (float64, per-sample Python)", best_of(ref_window, 5), None, None,
                 ""))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rows += fallback_rows(loaded, files, folder, samples, dt, True, args.repeat, args.before, ("fused_process",))
        native, note = build_natmod(folder, files)
        natmod = grown = count = None
        if native is not None:
            natmod, grown, count, note = measure(native, "dr_native", samples, dt, True, 20 * args.repeat)
        rows.append(("x64 natmod dr_native on micropython", natmod, grown, count, note))
        instructions, note = callgrind(files, folder)
    print(f"deadreckon fused benchmark: one window of {n} x 6 samples + one GPS fix (position and velocity) "
          f"(board {board.name}), best of runs, x86-64 host")
    print_table(rows, n)
    if instructions is None:
        print(f"callgrind: - ({note})")
    else:
        print(f"C fused instructions per window (x86-64, callgrind): {instructions:,.0f} "
              f"({instructions / n:.0f} per sample)")
        print(f"  at 240 MHz, 1 instruction per cycle: {instructions / ESP32_HZ * 1e3:.2f} ms per window (budget 5 ms); "
              f"2 cycles per instruction: {2 * instructions / ESP32_HZ * 1e3:.2f} ms")
    if not args.no_device:
        from device import device_table

        device_table(loaded, "fused", before=args.before, scenario=args.scenario)
    return 0


if __name__ == "__main__":
    sys.exit(main())
