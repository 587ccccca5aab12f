"""Speed of the fused algorithm (issue 8) per window, beside the kernel's budget (<= 5 ms per 512-sample window at
240 MHz by instruction count).

    python3 benchmarks/fused.py [--no-device]

Rows: the C kernel (dr_fused_process + one dr_fused_gps) through cffi, the float64 reference (codegen/kernel/fused.py), the
generated fallback's fused_process on the unix-port `micropython`; then valgrind callgrind's instruction count of the
C harness native_ext/tests/bench_fused.c per window and what it means at 240 MHz (as benchmarks/kernel.py does for
the seed kernel: x86-64 instructions as a proxy for the ESP32's single-issue LX6); then the boards' instruction sets
(benchmarks/device.py: QEMU counts of the natmod and the fallback on ARM cores, the natmod's ESP32 code on Xtensa).
"""

from __future__ import annotations

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
from codegen.tools import find_tool  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from kernel import print_time_table  # noqa: E402  (benchmarks/kernel.py)

ESP32_HZ = 240e6

MP_SCRIPT = """
import time
from array import array
import dr_fallback as dr
n = {n}
st = array('f', [0.0] * dr.FUSED_STATE_LEN)
out = array('f', [0.0] * dr.OUT_LEN)
dr.fused_init(st)
samples = array('h', {samples})
dt = array('i', {dt})
best = 1e9
for _ in range({repeat}):
    t0 = time.ticks_us()
    dr.fused_process(st, samples, dt, out)
    dr.fused_position(st, 1.0, 0.5, 1.0, 0.5)
    dr.fused_gps(st, 1.0, 0.5)
    best = min(best, time.ticks_diff(time.ticks_us(), t0))
print(best)
"""


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
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-device", action="store_true", help="skip the QEMU rows (boards' instruction sets)")
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

    rows.append(("C dr_fused via cffi (host)", best_of(c_window, 200), ""))
    st = F.FusedState()

    def ref_window():
        F.process(st, samples, dt, kcfg, fcfg)
        F.position_update(st, 1.0, 0.5, 1.0, 0.5, fcfg)
        F.gps_update(st, 1.0, 0.5, fcfg)

    rows.append(("reference codegen/kernel/fused.py (float64, per-sample Python)", best_of(ref_window, 5), ""))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "dr_fallback.py").write_bytes(files["app/dr_fallback.py"].content)
        mp = find_tool("micropython")
        if mp:
            script = MP_SCRIPT.format(n=n, samples=samples.ravel().tolist(), dt=dt.tolist(), repeat=5)
            (folder / "bench.py").write_text(script)
            done = subprocess.run([mp, "-X", "heapsize=32M", "bench.py"], cwd=folder, capture_output=True, text=True,
                                  env={"MICROPYPATH": str(folder), "PATH": "/usr/bin:/bin"})
            ok = done.returncode == 0
            rows.append(("dr_fallback.fused_process on micropython (unix port)",
                         int(done.stdout.split()[-1]) * 1e-6 if ok else None, "" if ok else done.stderr[-200:]))
        else:
            rows.append(("dr_fallback.fused_process on micropython", None, "micropython missing"))
        instructions, note = callgrind(files, folder)
    print(f"deadreckon fused benchmark: one window of {n} x 6 samples + one GPS fix (position and velocity) (board {board.name}), best of runs")
    print_time_table(rows)
    if instructions is None:
        print(f"callgrind: - ({note})")
    else:
        print(f"C fused instructions per window (x86-64, callgrind): {instructions:,.0f} "
              f"({instructions / n:.0f} per sample)")
        print(f"  at 240 MHz, 1 instruction per cycle: {instructions / ESP32_HZ * 1e3:.2f} ms per window (budget 5 ms); "
              f"2 cycles per instruction: {2 * instructions / ESP32_HZ * 1e3:.2f} ms")
    if not args.no_device:
        from device import device_table

        device_table(loaded, "fused")
    return 0


if __name__ == "__main__":
    sys.exit(main())
