"""The emulated board's clock and heap: what a step of the app costs on the board, and the room its heap gives.

The model. The app runs on the unix-port MicroPython of the host, which says nothing about the board's
time, so the emulated board (codegen/sim/mpsim) charges every operation of the app its cost on the board:

    board microseconds = Thumb-2 instructions / (R_pyb * S_board)

- Thumb-2 instructions: MicroPython v1.28.0's QEMU port (MPS2-AN500, a Cortex-M7 with the single-precision float
  a 32-bit board has) runs the generated app's own code for each operation under `-icount shift=0` (one virtual
  nanosecond per instruction); `benchmarks/board_clock.py --calibrate` measures them into board_clock.json.
- R_pyb, Thumb-2 instructions per microsecond of a pyboard v1.0 (STM32F405, Cortex-M4F at 168 MHz): the same QEMU
  run's instruction counts of MicroPython's own benchmarks (tests/perf_bench, N=100 M=100) divided by the times
  Damien George published for them on that board (micropython#4858).
- S_board, the board's MicroPython speed relative to the pyboard, on one float-heavy program run on all of them
  (scruss.com, "Parallel MicroPython Benchmarking", 2024-25: pyboard v1.1 13.0 s, ESP32 at 160 MHz 15.4 s,
  ESP32-S3 at 240 MHz 8.9 s, Raspberry Pi Pico (RP2040, 125 MHz) 19.8 s), scaled to the board's CPU clock.
- The native module: its armv7emsp build (the same C, hardware single float) in the same QEMU run, same scaling.
- Buses and flash: I2C and UART by their bit times (mpsim/machine.py); the filesystem by the flash chip's page
  program and sector erase times (FLASH below, mpsim/simworld.py), during which the CPU waits.
Operations the app does that the table has no entry for cost nothing: the table lists what it covers, and
`benchmarks/board_clock.py` prints it per board.

The heap: the board declares the heap its firmware gives (micropython.heap_kb, codegen/board/chips.py). The host's
MicroPython stores every pointer in 8 bytes where the board uses 4, so the same app needs more room; the calibration
loads the app into the 32-bit QEMU port and into the 64-bit host and records the ratio of their footprints
(`host_heap_scale`): the emulated board gives the app heap_kb * that ratio, no more. A 32-bit interpreter (the
single-precision unix port the app tests run on, CircuitPython's unix port) stores pointers as the board does and
gives the app heap_kb itself.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

TABLE = Path(__file__).resolve().parent / "board_clock.json"
CPU_MHZ = {"esp32": 240.0, "esp32s3": 240.0, "rp2040": 125.0}
# Seconds of the same float-heavy program (scruss.com, 2024-25): the board at the clock it ran at, the pyboard v1.1
SCRUSS_S = {"pyboard": (13.0, 168.0), "esp32": (15.4, 160.0), "esp32s3": (8.9, 240.0), "rp2040": (19.8, 125.0)}
# SPI NOR flash (Winbond W25Q32JV datasheet, typical): 256-byte page program 0.4 ms, 4 KiB sector erase 45 ms; reads
# through the ESP32's flash cache at about 10 MB/s. The CPU waits for all of it (code runs from the same flash).
FLASH = {"page_bytes": 256, "page_program_us": 400.0, "sector_erase_us": 45000.0, "read_us_per_byte": 0.1}
MPSIM_RESERVE_BYTES = 512 * 1024  # the emulated board's own modules and buffers, beside the app's heap


def load_table(path: Path = TABLE) -> dict:
    return json.loads(Path(path).read_text())


def speed_vs_pyboard(chip: str) -> float:
    """S_board: the board's MicroPython speed over the pyboard's, at the board's own CPU clock."""
    seconds, mhz = SCRUSS_S[chip]
    pyb_seconds, _ = SCRUSS_S["pyboard"]
    return pyb_seconds / (seconds * mhz / CPU_MHZ[chip])


@dataclass(frozen=True)
class BoardClock:
    chip: str
    instructions_per_us: float  # R_pyb * S_board
    ops: dict  # name -> Thumb-2 instructions (or [per call, per sample] for the kernels)

    def us(self, instructions: float) -> float:
        return instructions / self.instructions_per_us

    def costs_us(self) -> dict:
        """Every operation's cost on this board in microseconds, as mpsim/boardclock.py charges them."""
        out = {}
        for name, value in self.ops.items():
            if isinstance(value, dict):
                out[name] = {k: [self.us(v[0]), self.us(v[1])] if isinstance(v, list) else self.us(v)
                             for k, v in value.items()}
            elif isinstance(value, list):
                out[name] = [self.us(v) for v in value]
            else:
                out[name] = self.us(value)
        return out


def board_clock(chip: str, table: dict | None = None) -> BoardClock:
    table = load_table() if table is None else table
    rate = table["pyboard_instructions_per_us"] * speed_vs_pyboard(chip)
    return BoardClock(chip, rate, table["ops"])


def scenario_clock(chip: str, table: dict | None = None) -> dict:
    """The "clock" entry of an mpsim scenario: per-operation costs in board microseconds, and the flash."""
    table = load_table() if table is None else table
    clock = board_clock(chip, table)
    return {"chip": chip, "costs": clock.costs_us(), "flash": dict(FLASH)}


def host_heap_bytes(board_heap_bytes: int, table: dict | None = None, pointer_bytes: int = 8) -> int:
    """The room an interpreter storing pointers in `pointer_bytes` gives the app for a board heap of
    `board_heap_bytes`: a 32-bit build (the board-precision unix ports) gives the board's own figure, the 64-bit
    host that figure times the calibrated footprint ratio (see the module docstring)."""
    if pointer_bytes == 4:
        return int(board_heap_bytes)
    table = load_table() if table is None else table
    return int(board_heap_bytes * table["host_heap_scale"])
