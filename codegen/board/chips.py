"""Per-chip pin capability tables. Pin validation reads these tables; it has no chip-specific `if`s.

Sources: ESP32 datasheet v4 (sections 2.2 and 2.4, strapping pins), ESP32-S3 datasheet v1.9 (section 2.3),
RP2040 datasheet (section 1.4.3, GPIO functions) and the Raspberry Pi Pico datasheet (GPIO23/24/25/29).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ChipPins:
    name: str
    existing: frozenset[int]
    flash: frozenset[int] = frozenset()  # wired to the SPI flash: using them kills the chip
    psram: frozenset[int] = frozenset()  # wired to PSRAM on boards that have it
    input_only: frozenset[int] = frozenset()  # no output driver, no internal pull-up/down
    strapping: frozenset[int] = frozenset()  # sampled at reset: the boot mode depends on them
    board_taken: dict[int, str] = field(default_factory=dict)  # used by the module/board itself (warn)
    i2c_pins: dict[int, dict[str, frozenset[int]]] = field(default_factory=dict)  # fixed pin muxing, by bus id
    uart_pins: dict[int, dict[str, frozenset[int]]] = field(default_factory=dict)
    i2c_ids: frozenset[int] = frozenset({0, 1})
    uart_ids: frozenset[int] = frozenset({0, 1, 2})
    console_uart: int | None = 0  # the UART MicroPython's REPL uses


def _every(start: int, stop: int, step: int = 4) -> frozenset[int]:
    return frozenset(range(start, stop + 1, step))


ESP32 = ChipPins(
    name="ESP32",
    existing=frozenset(set(range(0, 20)) | {21, 22, 23, 25, 26, 27} | set(range(32, 40))),
    flash=frozenset(range(6, 12)),
    psram=frozenset({16, 17}),
    input_only=frozenset(range(34, 40)),
    strapping=frozenset({0, 2, 5, 12, 15}),
)

ESP32S3 = ChipPins(
    name="ESP32-S3",
    existing=frozenset(set(range(0, 22)) | set(range(26, 49))),
    flash=frozenset(range(26, 33)),
    psram=frozenset(range(33, 38)),  # octal PSRAM (ESP32-S3R8 modules) takes GPIO33..37 too
    strapping=frozenset({0, 3, 45, 46}),
    board_taken={19: "USB D-", 20: "USB D+", 43: "UART0 TX (USB-serial bridge)", 44: "UART0 RX (USB-serial bridge)"},
)

RP2040 = ChipPins(
    name="RP2040",
    existing=frozenset(range(0, 30)),
    board_taken={23: "Pico SMPS power-save", 24: "Pico VBUS sense", 29: "Pico VSYS/3 ADC"},
    i2c_pins={
        0: {"sda": _every(0, 28), "scl": _every(1, 29)},
        1: {"sda": _every(2, 26), "scl": _every(3, 27)},
    },
    uart_pins={
        0: {"tx": frozenset({0, 12, 16, 28}), "rx": frozenset({1, 13, 17, 29})},
        1: {"tx": frozenset({4, 8, 20, 24}), "rx": frozenset({5, 9, 21, 25})},
    },
    uart_ids=frozenset({0, 1}),
    console_uart=None,  # the Pico's REPL is on USB CDC
)

CHIPS = {"esp32": ESP32, "esp32s3": ESP32S3, "rp2040": RP2040}

# Power management chips: rail name -> (enable register, bit, voltage register)
PMU_RAILS = {
    "axp192": {
        "dcdc1": (0x12, 0, 0x26),
        "dcdc2": (0x12, 4, 0x23),
        "dcdc3": (0x12, 1, 0x27),
        "ldo2": (0x12, 2, 0x28),
        "ldo3": (0x12, 3, 0x28),
        "exten": (0x12, 6, None),
    },
    "axp2101": {
        "dcdc1": (0x80, 0, 0x82),
        "aldo1": (0x90, 0, 0x92),
        "aldo2": (0x90, 1, 0x93),
        "aldo3": (0x90, 2, 0x94),
        "aldo4": (0x90, 3, 0x95),
        "bldo1": (0x90, 4, 0x96),
        "bldo2": (0x90, 5, 0x97),
        "dldo1": (0x90, 7, 0x99),
    },
}
PMU_CHIP_ID_REGISTER = 0x03
PMU_CHIP_IDS = {"axp192": 0x03, "axp2101": 0x4A}


# The Python heap a chip's release firmware (MicroPython 1.24.1, the bundled boards' release) gives the app, KiB,
# by (chip, PSRAM). Sources (docs/emulated-board.md has the reasoning):
# - ESP32 without PSRAM: ports/esp32/mpconfigport.h starts the heap at 56 KiB (MICROPY_GC_INITIAL_HEAP_SIZE) and
#   grows it from the IDF heap, a size "chosen so they can grow the heap once (double it) and still have enough
#   internal RAM to start WiFi": 112 KiB. (Before the split heap, 1.13 gave 111168 bytes: micropython#7043.)
# - ESP32 with PSRAM (ESP32_GENERIC-SPIRAM, CONFIG_SPIRAM_USE_MALLOC): the heap grows into the PSRAM, of which the
#   ESP32 maps 4 MiB (the pre-split main.c gave exactly 4 MiB for 32/64 Mbit chips): 4096 KiB.
# - ESP32-S3 with octal PSRAM (8 MiB): "max new split: 8257536" on a fresh ESP32-S3 SPIRAM board (micropython#12237,
#   dpgeorge): 8064 KiB. Without PSRAM: 64 KiB initial, grown once: 128 KiB.
# - RP2040 (RPI_PICO): the heap is all RAM after .bss (ports/rp2/memmap_mp_rp2040.ld: __GcHeapStart .. end of the
#   256 KiB); gc.mem_free() after boot 209936 bytes (micropython#12557): 205 KiB.
FIRMWARE_HEAP_KB = {
    ("esp32", False): 112,
    ("esp32", True): 4096,
    ("esp32s3", False): 128,
    ("esp32s3", True): 8064,
    ("rp2040", False): 205,
    ("rp2040", True): 205,  # no PSRAM on an RP2040
}
WATCHDOG_MAX_S = {"rp2040": 8.3}  # the RP2040's watchdog counts at most 0xffffff us (RP2040 datasheet 4.7)


def firmware_heap_kb(chip: str, psram: bool) -> int:
    return FIRMWARE_HEAP_KB[(chip, psram)]
