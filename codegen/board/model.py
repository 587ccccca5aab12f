"""The board model: what one board YAML says, with the seed's values as defaults.

Schemas are composed from reusable parts (a pin, an I2C bus, a UART, an I2C device), as ESPHome composes its
components. This module only describes shapes and per-field ranges; rules that need the whole board (a pin used
twice, an address collision, a rail nobody enables, chip pin capabilities) live in `codegen.board.rules`.
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationInfo,
    WithJsonSchema,
    create_model,
    field_validator,
)
from pydantic_core import PydanticCustomError

from codegen.board.circuitpython import DEFAULT_CIRCUITPYTHON, CircuitPythonBoard, strip_board_prefix
from codegen.kernel.layout import ESKF, FUSED, FUSED_MEDIAN_MAX  # noqa: F401  (FUSED_MEDIAN_MAX: for the rules)

STANDARD_GRAVITY = 9.80665  # m/s^2

ACCEL_RANGES_G = (2, 4, 8, 16)
GYRO_RANGES_DPS = (250, 500, 1000, 2000)
# MPU-6050 full-scale -> sensitivity, datasheet section 6.1/6.2
ACCEL_LSB_PER_G = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
GYRO_LSB_PER_DPS = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
# DLPF_CFG 0 runs the gyro at 8 kHz, 1..6 at 1 kHz (register 0x1A)
DLPF_BANDWIDTH_HZ = {0: 260, 1: 184, 2: 94, 3: 44, 4: 21, 5: 10, 6: 5}

AXIS_NAMES = ("x", "y", "z", "-x", "-y", "-z")
FUSED_KEEP_MOVED_FAILED_HEAP_BYTES = 112 * 1024  # Board.keeps_moved_calibration

# Every number a board file gives is finite (YAML's .inf and .nan are refused) and bounded: a field without a
# physical upper limit of its own takes at most NUMBER_MAX, and a nonzero real number is at least NUMBER_TINY in
# size, so that what the app computes from it (a reciprocal, a square times a sensitivity of 16384 counts/g, a
# period in ms) stays finite in the device's float32 (largest 3.4e38, smallest normal 1.2e-38).
NUMBER_MAX = 1.0e6
NUMBER_TINY = 1.0e-6
INT32_MAX = 2**31 - 1


class Part(BaseModel):
    """Base of every schema part: unknown keys are errors, values are not coerced between kinds silently."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    @field_validator("*")
    @classmethod
    def _not_vanishing(cls, value: object) -> object:
        if isinstance(value, float) and 0.0 < abs(value) < NUMBER_TINY:
            raise PydanticCustomError(
                "number_tiny", "too small to mean anything here (a nonzero number is at least {tiny})",
                {"tiny": NUMBER_TINY, "hint": f"write 0 where 0 is allowed, or a value of at least "
                                                               f"{NUMBER_TINY:g}"},
            )
        return value


class PinSpec(Part):
    """A GPIO, written as a number (MicroPython) or as the board's CircuitPython name (`board.GP4` or `GP4`; target
    circuitpython), or as a mapping with the escape hatch for strapping pins."""

    pin: int = Field(ge=0, le=63, description="GPIO number")
    name: Optional[str] = Field(
        None, pattern=r"^[A-Z][A-Z0-9_]*$",
        description="the board.* name the pin was written as (target circuitpython; set from the board's pin table)",
    )
    strapping_by_design: bool = Field(
        False, description="this strapping pin is used on purpose (silences the warning; an error on other pins)"
    )

    @property
    def label(self) -> str:
        """How messages name the pin: GPIO4, or board.GP4 (GPIO4) on a CircuitPython board."""
        return f"board.{self.name} (GPIO{self.pin})" if self.name else f"GPIO{self.pin}"


# The validation context key under which the loader passes the CircuitPython board whose names pins are written in
# (codegen.board.loader.pin_context): absent for target micropython, None when the board is not known.
CIRCUITPYTHON_PINS = "circuitpython_pins"


def _pin_from_written(value: object, info: ValidationInfo) -> object:
    """A pin as written -> the PinSpec mapping: a GPIO number for MicroPython; for CircuitPython a board.* name
    resolved through the board's pin table (a name the board lacks, or a bare number, is an error here)."""
    context = info.context or {}
    mapping = dict(value) if isinstance(value, dict) else {"pin": value}
    if "name" in mapping:
        raise PydanticCustomError(
            "pin_name_key", "`name` is not written in a board file: it is set from the board's pin table",
            {"hint": "write the pin itself: `pin: GP4` on a CircuitPython board, `pin: 4` on a MicroPython one"},
        )
    written = mapping.get("pin")
    if CIRCUITPYTHON_PINS not in context:
        return {"pin": value} if isinstance(value, int) and not isinstance(value, bool) else value
    board: Optional[CircuitPythonBoard] = context[CIRCUITPYTHON_PINS]
    if isinstance(written, int) and not isinstance(written, bool):
        names = board.names_of(written) if board else []
        raise PydanticCustomError(
            "circuitpython_pin_number",
            "a CircuitPython pin is written as the board's name for it, not as a GPIO number",
            {"hint": (f"GPIO{written} is `{names[0]}` (board.{names[0]}) on the {board.title}" if names else
                      f"the {board.title} has no board.* name for GPIO{written}") if board else
                     "set circuitpython.board to the board's CircuitPython board_id"},
        )
    if not isinstance(written, str):
        return value  # the schema says what is wrong with it
    name = strip_board_prefix(written.strip())
    if board is None:
        return {**mapping, "pin": 0, "name": name} if name else value  # unchecked: the board id is reported
    if name not in board.pins:
        close = board.close_names(name)
        raise PydanticCustomError(
            "circuitpython_pin_name",
            "the {title} has no pin of that name",
            {"title": board.title,
             "hint": (f"did you mean `{close[0]}`?" if close else
                      f"its pins: {', '.join(list(board.pins)[:8])}, ... (CircuitPython's pins.c for "
                      f"{board.board_id})")},
        )
    return {**mapping, "pin": board.pins[name], "name": name}


Pin = Annotated[
    PinSpec,
    BeforeValidator(_pin_from_written),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "integer", "minimum": 0, "maximum": 63},
                {"type": "string", "pattern": r"^(board\.)?[A-Z][A-Z0-9_]*$"},
                {
                    "type": "object",
                    "properties": {"pin": {"anyOf": [{"type": "integer", "minimum": 0, "maximum": 63},
                                                     {"type": "string"}]},
                                   "strapping_by_design": {"type": "boolean"}},
                    "required": ["pin"],
                    "additionalProperties": False,
                },
            ],
            "description": "GPIO number (MicroPython), board.* name such as GP4 (CircuitPython), or "
                           "{pin: N, strapping_by_design: true}",
        }
    ),
]


def pin_number(pin: PinSpec) -> int:
    return pin.pin


class Partitions(Part):
    bootloader: int = Field(
        0x1000, ge=0, le=0xFFFFFF, description="bootloader offset: 0x1000 on the ESP32, 0x0 on the ESP32-S3")
    partition_table: int = Field(0x8000, ge=0, le=0xFFFFFF, description="partition table offset")
    app: int = Field(0x10000, ge=0, le=0xFFFFFF, description="MicroPython firmware (app) offset")
    table: Optional[str] = Field(
        None,
        pattern=r"^[^\x00]+\.csv$",
        description="the ESP-IDF partition table CSV of a custom MicroPython build (a path relative to this board "
        "file); by default the layout of MicroPython's own firmware for the chip, flash size and release",
    )


class Filesystem(Part):
    offset: int = Field(0x200000, ge=0, le=0xFFFFFF, description="vfs partition offset, bytes")
    size: int = Field(0x200000, gt=0, le=0x1000000, description="vfs partition size, bytes")
    block_size: int = Field(4096, gt=0, le=65536, description="LittleFS block size, bytes (the flash erase size)")

    @field_validator("offset", "size")
    @classmethod
    def _block_aligned(cls, value: int) -> int:
        if value % 4096:
            raise ValueError(f"{value:#x} is not a multiple of the 4096-byte flash sector")
        return value


class MicroPython(Part):
    version: str = Field("1.28.0", pattern=r"^\d+\.\d+(\.\d+)?$", description="MicroPython release on the board")
    partitions: Partitions = Partitions()
    filesystem: Filesystem = Filesystem()
    # what the firmware gives the app, and how long a stuck app may run
    heap_kb: Optional[int] = Field(
        None, ge=32, le=65536,
        description="KiB of Python heap the firmware gives the app (gc.mem_free() after boot); default: the chip's "
        "release firmware with or without PSRAM (codegen/board/chips.py FIRMWARE_HEAP_KB)",
    )
    watchdog_s: float = Field(
        5.0, ge=1.0, le=60.0,
        description="s: the app feeds machine.WDT from its loop; stuck this long, the board resets (RP2040: <= 8.3)",
    )


class CircuitPython(Part):
    """The CircuitPython firmware a `target: circuitpython` board runs (codegen/board/circuitpython.py)."""

    board: str = Field(
        pattern=r"^[a-z0-9][a-z0-9_]*$",
        description="the board's CircuitPython board_id (board.board_id on the device), e.g. raspberry_pi_pico; "
        "pins are written as its board.* names",
    )
    version: str = Field(DEFAULT_CIRCUITPYTHON, pattern=r"^\d+\.\d+(\.\d+)?$",
                         description="CircuitPython release on the board")
    heap_kb: Optional[int] = Field(
        None, ge=32, le=65536,
        description="KiB of Python heap the app gets (gc.mem_free() in the REPL); default: MicroPython's figure for "
        "the chip (codegen/board/chips.py FIRMWARE_HEAP_KB), not measured on CircuitPython",
    )
    watchdog_s: float = Field(
        5.0, ge=1.0, le=60.0,
        description="s: the app feeds microcontroller.watchdog from its loop; stuck this long, the board resets "
        "(CircuitPython on the RP2040 takes at most 8)",
    )


class I2CBus(Part):
    id: int = Field(0, ge=0, le=1)
    sda: Pin
    scl: Pin
    frequency: int = Field(400000, ge=10000, le=1000000, description="Hz")


class UARTBus(Part):
    id: int = Field(1, ge=0, le=2)
    rx: Pin
    tx: Optional[Pin] = None
    baud: int = Field(9600, ge=1200, le=921600)


class I2CDevice(Part):
    bus: str = Field(description="name of an entry under i2c:")
    address: int = Field(ge=0, le=0xFF, description="7-bit I2C address")


class Imu(I2CDevice):
    model: Literal["mpu6050"] = "mpu6050"
    address: int = Field(0x68, ge=0, le=0xFF, description="7-bit I2C address: 0x68 (AD0 low) or 0x69")
    accel_range_g: Literal[2, 4, 8, 16] = 2
    gyro_range_dps: Literal[250, 500, 1000, 2000] = 250
    dlpf: int = Field(3, ge=0, le=6, description="DLPF_CFG, register 0x1A")
    sample_rate_hz: float = Field(200.0, gt=0, le=8000, description="sample rate the app runs the IMU at")
    axes: list[str] = Field(
        ["x", "y", "z"],
        min_length=3,
        max_length=3,
        description="board x, y, z <- sensor axis, e.g. [-y, x, z] for a sensor turned 90 degrees",
    )
    use_fifo: bool = Field(
        True,
        description="read the samples from the MPU-6050's FIFO (85 samples): the app keeps its rate through a flash erase (~45 ms), a GPS epoch or a kernel batch; false: poll the data-ready flag",
    )

    @field_validator("axes")
    @classmethod
    def _axes_permutation(cls, axes: list[str]) -> list[str]:
        for axis in axes:
            if axis not in AXIS_NAMES:
                raise ValueError(f"axis {axis!r} is not one of {', '.join(AXIS_NAMES)}")
        if sorted(a[-1] for a in axes) != ["x", "y", "z"]:
            raise ValueError(f"axes {list(axes)} must use each of x, y, z exactly once")
        return axes

    @property
    def accel_lsb_per_g(self) -> float:
        return ACCEL_LSB_PER_G[self.accel_range_g]

    @property
    def gyro_lsb_per_dps(self) -> float:
        return GYRO_LSB_PER_DPS[self.gyro_range_dps]

    @property
    def gyro_output_rate_hz(self) -> int:
        return 8000 if self.dlpf in (0, 7) else 1000

    @property
    def sample_rate_divider(self) -> int:
        """SMPLRT_DIV (register 0x19): sample rate = gyro output rate / (1 + SMPLRT_DIV)."""
        return max(0, round(self.gyro_output_rate_hz / self.sample_rate_hz) - 1)

    @property
    def achieved_sample_rate_hz(self) -> float:
        return self.gyro_output_rate_hz / (1 + self.sample_rate_divider)

    @property
    def axis_map(self) -> tuple[tuple[int, int], ...]:
        """Per board axis: (sensor axis index 0..2, sign +1/-1)."""
        return tuple(("xyz".index(a[-1]), -1 if a.startswith("-") else 1) for a in self.axes)


class Gps(Part):
    model: Literal["neo-6m", "neo-m8n", "generic-nmea"] = "neo-6m"
    uart: str = Field(description="name of an entry under uart:")
    rate_hz: float = Field(1.0, gt=0, le=10)
    power: str = Field("always_on", description="'always_on' or the name of a power rail under power.rails")
    fix_timeout_s: float = Field(
        3.0, ge=0.1, le=3600, description="the fix counts as lost after this long without a valid one")

    @property
    def fix_timeout_ms(self) -> int:
        return round(self.fix_timeout_s * 1000)


class Display(I2CDevice):
    model: Literal["ssd1306", "ssd1315", "sh1106"] = "ssd1306"
    address: int = Field(0x3C, ge=0, le=0xFF)
    width: Literal[64, 72, 128] = 128
    height: Literal[32, 48, 64] = 64
    refresh_ms: int = Field(500, ge=50, le=60000, description="screen refresh period")


class Rail(Part):
    enable: bool = True
    millivolts: int = Field(3300, ge=500, le=3500)


PowerChip = Literal["axp192", "axp2101", "none"]


class Power(Part):
    chip: PowerChip = "none"
    bus: Optional[str] = None
    address: int = Field(0x34, ge=0, le=0xFF)
    rails: dict[str, Rail] = Field(default_factory=dict)


class Button(Part):
    pin: Pin
    pull: Literal["up", "down", "none"] = "up"
    active: Literal["low", "high"] = "low"
    debounce_ms: int = Field(50, ge=0, le=1000)

    @property
    def active_low(self) -> bool:
        return self.active == "low"


class Buttons(Part):
    calibrate: Optional[Button] = None
    test_mode: Optional[Button] = None


class Led(Part):
    pin: Pin
    active_low: bool = False


class _AlgorithmKeys(Part):
    """The algorithm's keys the seed mode reads; Algorithm adds one key per fused parameter."""

    mode: Literal["seed", "fused", "eskf"] = Field(
        "fused",
        description="seed: the seed's windows (block median, deadband, double integration); fused: tilt kept by "
        "gravity, rest detection, heading and speed from GPS (it beats the seed and both baselines on the "
        "walk, car and real-walk benchmarks); eskf: an error-state Kalman filter for a vehicle (position, velocity, "
        "attitude, biases, mounting; docs/eskf.md), in the native module only (MicroPython)",
    )
    block: int = Field(16, ge=1, le=4096, description="b: samples per block median")
    window: int = Field(512, ge=1, le=4096, description="n: samples per processing window")
    deadband_g: float = Field(0.03125, ge=0, le=16, description="l: |a| below this (in g) becomes 0")
    calibration_s: float = Field(10.0, gt=0, le=120, description="seconds at rest for calibration")
    motion_threshold_g: float = Field(
        0.02, gt=0, le=16, description="accel standard deviation above this during calibration means 'moved'"
    )


def algorithm_model(kernel=FUSED, eskf=ESKF) -> type:
    """The `algorithm` section: the seed's keys, and for mode "fused" (codegen/kernel/fused.py, native_ext/dr_fused.c)
    and mode "eskf" (codegen/kernel/eskf.py, native_ext/dr_eskf.c) one key `fused_<name>` / `eskf_<name>` per
    parameter of the kernel's declaration (codegen/kernel/layout.py; not the eskf's cadences), with its default,
    unit and limits from there; a limit the kernel does not declare is the board's (NUMBER_MAX, INT32_MAX)."""
    keys = {}
    for kernel, p in ((k, p) for k in (kernel, eskf) for p in k.params if p.board):
        kind = Literal[p.choices] if p.kind == "choice" else {"float": float, "int": int, "bool": bool}[p.kind]
        description = f"{p.unit}: {p.doc}" if p.unit else p.doc
        limits = {}
        if p.kind in ("float", "int"):
            limits["le"] = p.le if p.le is not None else (NUMBER_MAX if p.kind == "float" else INT32_MAX)
        keys[kernel.board_key(p)] = (kind, Field(p.default, gt=p.gt, ge=p.ge, description=description,
                                                 **(limits or {"le": p.le})))
    return create_model("Algorithm", __base__=_AlgorithmKeys, __module__=__name__, **keys)


Algorithm = algorithm_model()


class Logging(Part):
    enabled: bool = True
    imu_rate_hz: float = Field(50.0, ge=0.01, le=1000, description="Hz: IMU samples logged per second")
    directory: str = Field("/logs", pattern=r"^/[A-Za-z0-9_./-]*$")
    block_bytes: int = Field(4096, ge=256, le=65536)
    max_files: int = Field(20, ge=1, le=1000)
    min_free_kb: int = Field(256, ge=16, le=16384)


class WiredI2C(Part):
    """The pins an I2C part is soldered to on the board itself."""

    sda: Pin
    scl: Pin


class WiredUART(Part):
    """The pins a UART part is soldered to on the board itself (rx: the board's receive pin)."""

    rx: Pin
    tx: Optional[Pin] = None


class Wired(Part):
    """What the board's PCB wires for good: a board file may not move these parts' buses to other pins (the part
    stays soldered where it is). Written by the board file that describes the PCB, inherited by those that extend
    it; parts a user adds (a GY-521 on the header) are not listed."""

    power: Optional[WiredI2C] = Field(None, description="the power chip (power.chip) on its I2C pins")
    display: Optional[WiredI2C] = Field(None, description="an OLED soldered to the board")
    imu: Optional[WiredI2C] = Field(None, description="an IMU soldered to the board")
    gps: Optional[WiredUART] = Field(None, description="the GPS module's UART")


Chip = Literal["esp32", "esp32s3", "rp2040"]
Target = Literal["micropython", "circuitpython"]


class Board(Part):
    """A whole board: the validated form of one board YAML (after `extends:` is resolved)."""

    name: str = Field(pattern=r"^[a-z0-9][a-z0-9._-]*$")
    description: str = ""
    target: Target = Field(
        "micropython",
        description="the firmware the app is generated for: micropython (app + native module) or circuitpython "
        "(code.py + lib/, pins as board.* names, the pure-Python kernel)",
    )
    chip: Chip = "esp32"
    flash_size: Literal["2MB", "4MB", "8MB", "16MB"] = "4MB"
    psram: bool = False
    micropython: MicroPython = MicroPython()
    circuitpython: Optional[CircuitPython] = None
    i2c: dict[str, I2CBus] = Field(default_factory=dict)
    uart: dict[str, UARTBus] = Field(default_factory=dict)
    power: Power = Power()
    imu: Imu
    gps: Gps
    display: Optional[Display] = None
    buttons: Buttons = Buttons()
    led: Optional[Led] = None
    reserved: dict[str, list[Annotated[int, Field(ge=0, le=63)]]] = Field(
        default_factory=dict, description="GPIO numbers taken by parts we do not drive")
    wired: Wired = Field(Wired(), description="the parts the board's PCB wires to fixed pins")
    algorithm: Algorithm = Algorithm()
    logging: Logging = Logging()

    @property
    def flash_bytes(self) -> int:
        return int(self.flash_size[:-2]) * 1024 * 1024

    @property
    def mpy_arch(self) -> str:
        return {"esp32": "xtensawin", "esp32s3": "xtensawin", "rp2040": "armv6m"}[self.chip]

    @property
    def heap_bytes(self) -> int:
        """The Python heap the app gets on this board (micropython.heap_kb or circuitpython.heap_kb, else the
        chip's MicroPython firmware's default)."""
        from codegen.board.chips import firmware_heap_kb

        kb = self.circuitpython.heap_kb if self.target == "circuitpython" else self.micropython.heap_kb
        return 1024 * (kb if kb is not None else firmware_heap_kb(self.chip, self.psram))

    @property
    def keeps_moved_calibration(self) -> bool:
        """Whether the app keeps a calibration the board moved in when the last fix shows it travelling (a device
        switched on in a moving car): eskf boards, and fused boards with more heap than the smallest (an ESP32
        without PSRAM, 112 KiB), where the fused fallback kernel with those lines ran out of heap in 1 of 16 heap
        layouts on the emulated board and without them in none (docs/eskf.md). The seed's windows take the
        calibration for rest."""
        if self.algorithm.mode == "eskf":
            return True
        return self.algorithm.mode == "fused" and self.heap_bytes > FUSED_KEEP_MOVED_FAILED_HEAP_BYTES

    @property
    def drive_button(self) -> Optional[tuple[str, Button]]:
        """(role, button) a CircuitPython board's boot.py reads to leave the CIRCUITPY drive to the computer: the
        first configured button that is not a strapping pin (one held at reset would select the chip's boot
        mode instead), or None."""
        from codegen.board.chips import CHIPS

        for role in ("calibrate", "test_mode"):
            button = getattr(self.buttons, role)
            if button is not None and button.pin.pin not in CHIPS[self.chip].strapping:
                return role, button
        return None

    @property
    def calibration_samples(self) -> int:
        """IMU samples the calibration collects: calibration_s at the IMU's achieved sample rate."""
        return max(1, round(self.algorithm.calibration_s * self.imu.achieved_sample_rate_hz))
