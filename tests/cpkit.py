"""Helpers for the CircuitPython app's tests: one simulated walk for a board and its MicroPython twin (the same
wiring, the same recording), and runs of the generated CircuitPython app on the emulated CircuitPython board."""

from __future__ import annotations

import shutil
from pathlib import Path

from codegen.sim import harness
from codegen.sim.cpharness import breadboard_world, run_circuitpython, with_circuitpython

# code.py's own order of imports (the largest modules first, for the compiler's room), for a test script that
# stands in for code.py
CODE_PY_IMPORTS = "import gc\ngc.collect()\nimport dr_fallback\ngc.collect()\nimport nmea\ngc.collect()\n" \
                  "import logger\ngc.collect()\n"


def walk_world(board, scenario: str, seed: int, duration: float, outages, work: Path, pins: dict | None = None):
    """A simulated `scenario` (walk, car) for a breadboard board: the MPU-6050 model's counts and the NEO-6M
    model's NMEA with `outages` cut in (each epoch 0.1 s after its time), wired as `board` says. The world is the
    same for a board and its twin of the other target. Returns (world, GPS track)."""
    work.mkdir(parents=True, exist_ok=True)
    _, track, imu, gps = harness.modelled_streams(board, scenario, seed, duration, outages, work)
    world = breadboard_world(board, work, imu, gps, duration, rate_hz=board.imu.achieved_sample_rate_hz, pins=pins)
    world["i2c"][str(board.i2c[board.imu.bus].id)][0].update(accel_range_g=board.imu.accel_range_g,
                                                           gyro_range_dps=board.imu.gyro_range_dps)
    return world, track


def run_cp(micropython: str, out: Path, board, world: dict, work: Path, code: str | None = None,
           heap_bytes: int | None = None, clock: bool = True):
    """Run the built CircuitPython app of OUT (OUT/build/app) on the emulated board; `code` replaces code.py (a
    test's script), `heap_bytes` the board's heap (default: the board's own)."""
    app = out / "build" / "app"
    if code is not None:
        copy = work / "app"
        if copy.exists():
            shutil.rmtree(copy)
        shutil.copytree(app, copy)
        (copy / "code.py").write_text(code)
        app = copy
    return run_circuitpython(micropython, app, with_circuitpython(world, board), work / "w",
                             heap_bytes=board.heap_bytes if heap_bytes is None else heap_bytes,
                             clock_chip=board.chip if clock else None)
