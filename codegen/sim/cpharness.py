"""Host side of the emulated CircuitPython board: the same world as codegen/sim/harness.py (mpsim's chips, GPS
stream, buttons, filesystem), with CircuitPython's modules (codegen/sim/cpsim/) in front of it instead of
MicroPython's `machine` and `time`.

    scenario = harness.tbeam_scenario(...) or any mpsim scenario, plus circuitpython_world(board) under
               "circuitpython" (the board's pin names, its clock's resolution, the watchdog's limit)
    run_circuitpython(micropython, app_dir, scenario, work)  -> harness.Run

The program runs as CircuitPython runs it: APP_DIR/boot.py at power-on, then APP_DIR/code.py, importing from
APP_DIR and APP_DIR/lib (and `libraries`, folders of further .py libraries, as if they were in lib/).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

from codegen.board.circuitpython import WATCHDOG_MAX_S, find_board
from codegen.board.model import Board
from codegen.font import FONT
from codegen.sim import boardclock
from codegen.sim.harness import MPSIM, Run, pointer_bytes

CPSIM = Path(__file__).resolve().parent / "cpsim"
# the firmware's monotonic_ns() step: RP2040 counts 1/1024 s ticks with 1/32 subticks (shared-module/time),
# the ESP32-S3 microseconds (ports/espressif/common-hal/time)
FAT_SECTOR_BYTES = 512
MONOTONIC_NS_STEP = {"rp2040": 30518, "esp32s3": 1000, "esp32": 1000}


def circuitpython_world(board: Board, usb_connected: bool = True) -> dict:
    """The scenario's "circuitpython" entry for a `target: circuitpython` board (the app's screen font goes in
    beside it: with_circuitpython)."""
    cp = find_board(board.circuitpython.board)
    return {
        "board_id": cp.board_id,
        "chip": cp.chip,
        "pins": dict(cp.pins),
        "usb_connected": usb_connected,
        "monotonic_ns_step": MONOTONIC_NS_STEP[cp.chip],
        "watchdog_max_s": WATCHDOG_MAX_S.get(cp.chip),
    }


def with_circuitpython(scenario: dict, board: Board, usb_connected: bool = True) -> dict:
    """`scenario` (a world of mpsim's) seen by a CircuitPython board: the firmware's settings, and the display read
    back with the app's own font (lib/textfb.py, codegen/font.py)."""
    return dict(scenario, circuitpython=circuitpython_world(board, usb_connected),
                display_font={"first": FONT.first, "cell": FONT.cell, "data": FONT.data.hex()})


def run_circuitpython(micropython: str, app_dir: Path, scenario: dict, work: Path, timeout: float = 600,
                      heap_bytes: int | None = None, clock_chip: str | None = None,
                      libraries: list[Path] = ()) -> Run:
    """Run APP_DIR (boot.py, code.py, lib/) on the emulated CircuitPython board in `scenario`. `heap_bytes`: the
    board's heap for the program (scaled to a 64-bit host as codegen/sim/boardclock.py scales MicroPython's; None: the
    host's 64 MB); `clock_chip`: charge the app's operations the board clock's costs for that chip (None: free)."""
    work.mkdir(parents=True, exist_ok=True)
    scenario = dict(scenario)
    scenario.setdefault("trace", str(work / "trace.jsonl"))
    if scenario.get("fs"):  # the CIRCUITPY drive: FAT in 512-byte sectors (CircuitPython has no LittleFS)
        scenario["fs"] = dict(scenario["fs"], image=scenario["fs"].get("image", str(work / "fs.img")), format="fat",
                              block=FAT_SECTOR_BYTES)
    # the display read back with the CircuitPython app's font: the firmware has no framebuf font to read it with
    scenario.setdefault("display_font", {"first": FONT.first, "cell": FONT.cell, "data": FONT.data.hex()})
    process_heap = 64 * 1024 * 1024
    if heap_bytes is not None:
        scenario["heap_bytes"] = boardclock.host_heap_bytes(heap_bytes, pointer_bytes=pointer_bytes(micropython))
        process_heap = scenario["heap_bytes"] + boardclock.MPSIM_RESERVE_BYTES
    if clock_chip is not None:
        scenario["clock"] = boardclock.scenario_clock(clock_chip)
    scenario_path = work / "scenario.json"
    scenario_path.write_text(json.dumps(scenario))
    app_dir = Path(app_dir).resolve()
    paths = [str(CPSIM), str(app_dir), str(app_dir / "lib"), *(str(Path(p).resolve()) for p in libraries)]
    env = dict(os.environ, MICROPYPATH=":".join(paths), MPSIM_SCENARIO=str(scenario_path))
    proc = subprocess.run(
        [micropython, "-X", f"heapsize={process_heap}", str(CPSIM / "launch.py"), str(MPSIM), str(app_dir)],
        env=env, capture_output=True, text=True, timeout=timeout, cwd=work,
    )
    trace_path = Path(scenario["trace"])
    trace = []
    if trace_path.exists():
        trace = [json.loads(line) for line in trace_path.read_text().splitlines() if line.strip()]
    return Run(proc.returncode, proc.stdout, proc.stderr, trace)


def breadboard_world(board: Board, work: Path, counts_path: Path | None, gps_path: Path | None, duration_s: float,
                     rate_hz: float = 200.0, pins: dict | None = None, fs_bytes: int = 1024 * 1024) -> dict:
    """The world of a breadboard board (an MPU-6050 and the display on the IMU's bus, the GPS on its UART, buttons
    idle high), keyed as mpsim keys it: buses by id with the pins they are wired to, so a MicroPython app (bus ids)
    and a CircuitPython app (pins) of the same wiring meet the same chips."""
    imu_bus = board.i2c[board.imu.bus]
    devices = [{"kind": "mpu6050", "address": board.imu.address, "counts": str(counts_path) if counts_path else None,
                "rate_hz": rate_hz}]
    if board.display is not None:
        devices.append({"kind": board.display.model, "address": board.display.address})
    gps_uart = board.uart[board.gps.uart]
    levels = {}
    for role in ("calibrate", "test_mode"):
        button = getattr(board.buttons, role)
        if button is not None:
            levels[str(button.pin.pin)] = [[0, 1 if button.active_low else 0]]
    for pin, changes in (pins or {}).items():
        levels[pin] = levels.get(pin, [[0, 1]]) + list(changes)
    dump = work / "fs"
    dump.mkdir(parents=True, exist_ok=True)
    return {
        "duration_s": duration_s,
        "i2c": {str(imu_bus.id): devices},
        "i2c_pins": {str(imu_bus.id): [imu_bus.sda.pin, imu_bus.scl.pin]},
        "uart": {str(gps_uart.id): {"stream": str(gps_path) if gps_path else None, "power": None,
                                    "rx": gps_uart.rx.pin}},
        "pins": levels,
        "fs": {"mount": board.logging.directory, "bytes": fs_bytes, "block": 4096, "dump": str(dump)},
    }
