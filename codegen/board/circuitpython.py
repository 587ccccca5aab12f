"""CircuitPython boards deadreckon targets (`target: circuitpython`): each board's `board.*` pin names and what its
firmware brings.

A CircuitPython app names its pins as the board module does (`board.GP4`, `board.IO8`), so a board YAML for this
target writes those names, and validation checks them against the board's own table. The tables below are the
names of each board's `pins.c` in CircuitPython's source (ports/raspberrypi/boards/raspberry_pi_pico/pins.c,
ports/espressif/boards/espressif_esp32s3_devkitc_1_*/pins.c, release 10.2.1; every ESP32-S3-DevKitC-1 variant
names the same pins), written here as data: a name and the GPIO it stands for. Names that are objects rather than
pins (STEMMA_I2C, UART, board_id) are left out. The GPIO lets the chip's own rules (flash, PSRAM, strapping pins,
fixed pin muxing; codegen/board/chips.py) apply to a CircuitPython board as they do to a MicroPython one.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

# CircuitPython releases whose APIs the generated app uses (supervisor.ticks_ms, microcontroller.watchdog,
# storage.remount with disable_concurrent_write_protection); 9.0 is the first whose .py the app is written for.
MIN_CIRCUITPYTHON = (9, 0)
DEFAULT_CIRCUITPYTHON = "10.2.1"
# microcontroller.watchdog.timeout limits: the RP2040 port validates the timeout as an int <= 8
# (ports/raspberrypi/common-hal/watchdog/WatchDogTimer.c: 8.388 s of its 24-bit counter, rounded down)
WATCHDOG_MAX_S = {"rp2040": 8.0}

# Built into the firmware of every board below (CIRCUITPY_FULL_BUILD): the app imports these without a lib/ copy.
FULL_BUILD_MODULES = frozenset({
    "adafruit_bus_device", "array", "board", "busio", "digitalio", "fontio", "gc", "math", "microcontroller",
    "micropython", "os", "storage", "struct", "supervisor", "sys", "terminalio", "time", "traceback", "ulab",
    "watchdog",
})


def _numbered(prefix: str, gpios: range | list[int]) -> dict[str, int]:
    return {f"{prefix}{gpio}": gpio for gpio in gpios}


@dataclass(frozen=True)
class CircuitPythonBoard:
    """One board CircuitPython is built for: its board_id, the chip deadreckon knows it by, its pin names."""

    board_id: str  # board.board_id on the device, and the name of its download on circuitpython.org
    title: str  # MICROPY_HW_BOARD_NAME
    chip: str  # deadreckon's chip key (codegen/board/chips.py)
    pins: dict[str, int]  # board.* name -> GPIO number, in the order pins.c lists them
    flash_size: str
    psram: bool
    builtin_modules: frozenset[str] = FULL_BUILD_MODULES

    def names_of(self, gpio: int) -> list[str]:
        """The board.* names of a GPIO, the plain numbered one (GP4, IO4) first."""
        names = [name for name, number in self.pins.items() if number == gpio]
        return sorted(names, key=lambda name: name.lstrip("GPIO") != str(gpio))

    def close_names(self, name: str) -> list[str]:
        """Names of this board that a mistyped `name` may have meant: the same name in other case, the board's name
        for the GPIO number the name ends in (IO14 or D14 on a Pico: GP14), then names that look alike."""
        folded = {pin.lower(): pin for pin in self.pins}
        if name.lower() in folded:
            return [folded[name.lower()]]
        digits = name[len(name.rstrip("0123456789")):]
        by_number = self.names_of(int(digits))[:1] if digits and len(digits) <= 2 else []
        alike = [folded[m] for m in difflib.get_close_matches(name.lower(), list(folded), n=3, cutoff=0.6)]
        return list(dict.fromkeys(by_number + alike))


_PICO_PINS = {
    **_numbered("GP", range(0, 23)),
    "SMPS_MODE": 23, "GP23": 23,
    "VBUS_SENSE": 24, "GP24": 24,
    "LED": 25, "GP25": 25,
    "GP26_A0": 26, "GP26": 26, "A0": 26,
    "GP27_A1": 27, "GP27": 27, "A1": 27,
    "GP28_A2": 28, "GP28": 28, "A2": 28,
    "A3": 29, "VOLTAGE_MONITOR": 29,
}

_DEVKITC_1_PINS = {
    **_numbered("IO", [*range(0, 22), *range(35, 49)]),
    "NEOPIXEL": 48,
    "TX": 43,
    "RX": 44,
}

BOARDS = {
    board.board_id: board
    for board in (
        CircuitPythonBoard("raspberry_pi_pico", "Raspberry Pi Pico", "rp2040", _PICO_PINS, "2MB", False),
        CircuitPythonBoard("espressif_esp32s3_devkitc_1_n8", "ESP32-S3-DevKitC-1-N8", "esp32s3", _DEVKITC_1_PINS,
                           "8MB", False),
        CircuitPythonBoard("espressif_esp32s3_devkitc_1_n8r2", "ESP32-S3-DevKitC-1-N8R2", "esp32s3",
                           _DEVKITC_1_PINS, "8MB", True),
        CircuitPythonBoard("espressif_esp32s3_devkitc_1_n8r8", "ESP32-S3-DevKitC-1-N8R8", "esp32s3",
                           _DEVKITC_1_PINS, "8MB", True),
        CircuitPythonBoard("espressif_esp32s3_devkitc_1_n16", "ESP32-S3-DevKitC-1-N16", "esp32s3", _DEVKITC_1_PINS,
                           "16MB", False),
    )
}


def find_board(board_id: str) -> CircuitPythonBoard | None:
    return BOARDS.get(board_id)


def close_board_ids(board_id: str) -> list[str]:
    return difflib.get_close_matches(board_id, list(BOARDS), n=2, cutoff=0.5)


def strip_board_prefix(name: str) -> str:
    """`board.GP4` and `GP4` name the same pin."""
    return name[len("board."):] if name.startswith("board.") else name
