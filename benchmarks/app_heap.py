"""Whether the app runs on the smallest board's heap, over runs that differ only in where the emulator's files lie.

    python3 benchmarks/app_heap.py [--layouts 8] [--heaps 112,116,120]

MicroPython's collector scans the C stack conservatively, and which blocks a stale word there holds alive, and so
how the heap fragments, moves with anything that shifts memory before the app starts: the length of the work
directory's path in the scenario and the environment, for one. The emulated board runs with address-space
randomisation off (codegen/sim/harness.py), so each such layout is reproducible; this runs the same drive in
`--layouts` of them (work directories whose names differ in length) per configuration and heap, and prints how many
ran through (a MemoryError, or any failure, counts against). The configurations are the ones tests/test_app_boards.py
holds at the edge: the bundled esp32-devkitc-gy521 (fused) on its fallback kernel, walking (its smallest-heap test),
and the same board with mode eskf, driving, with its native module and with the fused fallback that runs when the
module is refused. "least heap_free" is the least gc.mem_free() the app's DIAG lines printed, without a
collection first: garbage not yet collected counts as used, so it is no margin, only a hint.
Conditions: x86-64 host, the 32-bit unix-port MicroPython built from ../shared/micropython (the board's float and
pointer size), the board's heap and clock; 40 s, one 10 s outage.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT)]


def one(kernel: str, heap_kib: int, layout: int, base: Path) -> tuple[bool, int | None]:
    from test_app_boards import _eskf_devkitc_run, smallest_heap_run

    work = base / ("w" + "x" * (3 * layout))
    shutil.rmtree(work, ignore_errors=True)
    if kernel == "fused fallback":  # the bundled board itself, on its own heap
        _, run = smallest_heap_run("esp32-devkitc-gy521", work)
    else:
        _, run = _eskf_devkitc_run(work, kernel, heap_kib * 1024)
    free = run.heap_free()
    ran = run.returncode == 0 and "MemoryError" not in run.stdout + run.stderr
    return ran, (min(free) if free else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--layouts", type=int, default=8)
    parser.add_argument("--heaps", default="112,116,120", help="KiB, comma-separated")
    args = parser.parse_args()
    base = Path(tempfile.mkdtemp(prefix="app-heap-"))
    print(f"## esp32-devkitc-gy521's app, {args.layouts} layouts per row")
    print()
    print("| app | heap [KiB] | ran | least heap_free [B] per layout |")
    print("|---|---|---|---|")
    rows = [("fused fallback", 112)] + [(kernel, int(h)) for kernel in ("native", "python")
                                        for h in args.heaps.split(",")]
    for kernel, heap in rows:
        results = [one(kernel, heap, layout, base) for layout in range(args.layouts)]
        ran = sum(r for r, _ in results)
        frees = ", ".join("-" if f is None else str(f) for _, f in results)
        app = "fused, its fallback (a walk)" if kernel == "fused fallback" else f"eskf, {kernel} (a drive)"
        print(f"| {app} | {heap} | {ran}/{args.layouts} | {frees} |", flush=True)
    shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
