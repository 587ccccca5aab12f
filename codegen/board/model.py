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
    WithJsonSchema,
    field_validator,
)

STANDARD_GRAVITY = 9.80665  # m/s^2
FUSED_MEDIAN_MAX = 32  # samples: the longest block the fused median option keeps (dr_fused.h DR_FUSED_MEDIAN_MAX)

ACCEL_RANGES_G = (2, 4, 8, 16)
GYRO_RANGES_DPS = (250, 500, 1000, 2000)
# MPU-6050 full-scale -> sensitivity, datasheet section 6.1/6.2
ACCEL_LSB_PER_G = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
GYRO_LSB_PER_DPS = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
# DLPF_CFG 0 runs the gyro at 8 kHz, 1..6 at 1 kHz (register 0x1A)
DLPF_BANDWIDTH_HZ = {0: 260, 1: 184, 2: 94, 3: 44, 4: 21, 5: 10, 6: 5}

AXIS_NAMES = ("x", "y", "z", "-x", "-y", "-z")


class Part(BaseModel):
    """Base of every schema part: unknown keys are errors, values are not coerced between kinds silently."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class PinSpec(Part):
    """A GPIO, written either as a number or as a mapping with the escape hatch for strapping pins."""

    pin: int = Field(ge=0, le=63, description="GPIO number")
    strapping_by_design: bool = Field(
        False, description="this strapping pin is used on purpose (silences the warning; an error on other pins)"
    )


def _pin_from_number(value: object) -> object:
    return {"pin": value} if isinstance(value, int) and not isinstance(value, bool) else value


Pin = Annotated[
    PinSpec,
    BeforeValidator(_pin_from_number),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "integer", "minimum": 0, "maximum": 63},
                {
                    "type": "object",
                    "properties": {"pin": {"type": "integer"}, "strapping_by_design": {"type": "boolean"}},
                    "required": ["pin"],
                    "additionalProperties": False,
                },
            ],
            "description": "GPIO number, or {pin: N, strapping_by_design: true}",
        }
    ),
]


def pin_number(pin: PinSpec) -> int:
    return pin.pin


class Partitions(Part):
    bootloader: int = Field(0x1000, ge=0, description="bootloader offset")
    partition_table: int = Field(0x8000, ge=0, description="partition table offset")
    app: int = Field(0x10000, ge=0, description="MicroPython firmware (app) offset")


class Filesystem(Part):
    offset: int = Field(0x200000, ge=0, description="vfs partition offset, bytes")
    size: int = Field(0x200000, gt=0, description="vfs partition size, bytes")
    block_size: int = Field(4096, gt=0, description="LittleFS block size, bytes (the flash erase size)")

    @field_validator("offset", "size")
    @classmethod
    def _block_aligned(cls, value: int) -> int:
        if value % 4096:
            raise ValueError(f"{value:#x} is not a multiple of the 4096-byte flash sector")
        return value


class MicroPython(Part):
    version: str = Field("1.24.1", pattern=r"^\d+\.\d+(\.\d+)?$", description="MicroPython release on the board")
    partitions: Partitions = Partitions()
    filesystem: Filesystem = Filesystem()
    # issue 16: what the firmware gives the app, and how long a stuck app may run
    heap_kb: Optional[int] = Field(
        None, ge=32, le=65536,
        description="KiB of Python heap the firmware gives the app (gc.mem_free() after boot); default: the chip's "
        "release firmware with or without PSRAM (codegen/board/chips.py FIRMWARE_HEAP_KB)",
    )
    watchdog_s: float = Field(
        5.0, ge=1.0, le=60.0,
        description="s: the app feeds machine.WDT from its loop; stuck this long, the board resets (RP2040: <= 8.3)",
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
    sample_rate_hz: float = Field(200.0, gt=0, description="sample rate the app runs the IMU at")
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
    fix_timeout_s: float = Field(3.0, gt=0, description="the fix counts as lost after this long without a valid one")

    @property
    def fix_timeout_ms(self) -> int:
        return round(self.fix_timeout_s * 1000)


class Display(I2CDevice):
    model: Literal["ssd1306", "ssd1315", "sh1106"] = "ssd1306"
    address: int = Field(0x3C, ge=0, le=0xFF)
    width: Literal[64, 72, 128] = 128
    height: Literal[32, 48, 64] = 64
    refresh_ms: int = Field(500, ge=50, description="screen refresh period")


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


class Algorithm(Part):
    mode: Literal["seed", "fused"] = Field(
        "fused",
        description="seed: the seed's windows (block median, deadband, double integration); fused: tilt kept by "
        "gravity, rest detection, heading and speed from GPS (issue 8; beats the seed and both baselines on the "
        "walk, car and real-walk benchmarks)",
    )
    block: int = Field(16, ge=1, description="b: samples per block median")
    window: int = Field(512, ge=1, le=4096, description="n: samples per processing window")
    deadband_g: float = Field(0.03125, ge=0, description="l: |a| below this (in g) becomes 0")
    calibration_s: float = Field(10.0, gt=0, le=120, description="seconds at rest for calibration")
    motion_threshold_g: float = Field(
        0.02, gt=0, description="accel standard deviation above this during calibration means 'moved'"
    )
    # mode "fused" (codegen/kernel/fused.py, native_ext/dr_fused.c): defaults tuned on the simulator's walk/car scenarios
    fused_tilt_tau_s: float = Field(100.0, gt=0, description="s: tilt correction time constant while GPS fixes arrive")
    fused_accel_reject_g: float = Field(0.1, gt=0, description="g: no tilt correction while ||f| - g| exceeds this")
    fused_tilt_tau_dark_s: float = Field(0.0, ge=0, description="s: tilt correction time constant without GPS (0: none)")
    fused_steady_accel_ms2: float = Field(0.3, gt=0, description="m/s^2: tilt corrected only while the GPS acceleration changes less between fixes")
    fused_speed_tau_s: float = Field(0.0, ge=0, description="s: a vehicle's speed relaxes towards the last GPS speed (0: never)")
    fused_gps_timeout_s: float = Field(2.0, gt=0, description="s: GPS counts as lost this long after its last fix")
    fused_stat_tau_s: float = Field(0.5, gt=0, description="s: time constant of the motion statistics")
    fused_rest_accel_g: float = Field(0.01, gt=0, description="g: |f| standard deviation below which the device may be at rest")
    fused_rest_gyro_dps: float = Field(0.5, gt=0, description="degree/s: rate below which the device may be at rest")
    fused_rest_time_s: float = Field(0.4, ge=0, description="s: both below their limits this long means at rest")
    fused_bias_tau_s: float = Field(30.0, ge=0, description="s: gyro bias re-estimation time constant at rest (0: off)")
    fused_walk_accel_g: float = Field(0.03, gt=0, description="g: |f| standard deviation above which a walker carries the device")
    fused_min_speed_ms: float = Field(0.5, ge=0, description="m/s: GPS speeds below this carry no course")
    fused_heading_gain: float = Field(0.3, ge=0, le=1, description="per fix: pull of the travel direction towards the GPS course")
    fused_align_forget: float = Field(0.98, ge=0, le=1, description="per fix: forgetting factor of the heading alignment")
    fused_speed_gain: float = Field(0.5, ge=0, le=1, description="per fix: pull of the speed towards the GPS speed")
    fused_bias_gain: float = Field(0.1, ge=0, le=1, description="per fix: along-track accel bias correction gain")
    fused_walk_speed_gain: float = Field(0.2, ge=0, le=1, description="per fix: pull of the walking speed towards the GPS speed")
    fused_kf_bias_init_g: float = Field(0.05, ge=0, description="g: initial sigma of the horizontal accelerometer offsets (0: no tilt/offset filter)")
    fused_kf_bias_noise: float = Field(0.001, ge=0, description="m/s^2/sqrt(s): random walk of those offsets")
    fused_kf_tilt_noise: float = Field(0.002, ge=0, description="m/s^2/sqrt(s): random walk of the gravity leak (tilt error times g)")
    fused_kf_turn_noise: float = Field(0.1, ge=0, description="m/s^2 per rad: gravity leak a turn may add (gyro scale and cross-axis errors)")
    fused_kf_vel_sigma_ms: float = Field(0.15, gt=0, description="m/s: GPS Doppler velocity error per axis, with unmodelled motion")
    fused_kf_align_min: float = Field(20.0, ge=0, description="(m/s)^2: heading alignment sums needed before the filter updates")
    fused_pos_sigma_m: float = Field(2.1, ge=0, description="m: the receiver's position error per axis, for smoothing the fix an outage starts from (0: raw fixes)")
    fused_pos_tau_s: float = Field(60.0, gt=0, description="s: correlation time of that error")
    fused_pos_step_sigma_ms: float = Field(0.1, gt=0, description="m/s: error of the step between fixes (Doppler trapezoid + IMU), per second")
    fused_turn_hold_tau_s: float = Field(10.0, ge=0, description="s: a walker's slow rotations about Up (the hand swinging about the course) reach the travel direction over this; turns at once (0: everything at once)")
    fused_turn_start_dps: float = Field(12.0, gt=0, description="degree/s: a walker's turn starts when the smoothed rate about Up exceeds this")
    fused_turn_end_dps: float = Field(7.0, ge=0, description="degree/s: and ends when it falls below this (at most fused_turn_start_dps)")
    fused_median: bool = Field(False, description="a vehicle's along-track acceleration is the median of the last b (block) samples: the seed's block median, sliding (b <= 32)")


class Logging(Part):
    enabled: bool = True
    imu_rate_hz: float = Field(50.0, gt=0)
    directory: str = Field("/logs", pattern=r"^/[A-Za-z0-9_./-]*$")
    block_bytes: int = Field(4096, ge=256, le=65536)
    max_files: int = Field(20, ge=1, le=1000)
    min_free_kb: int = Field(256, ge=16)


Chip = Literal["esp32", "esp32s3", "rp2040"]


class Board(Part):
    """A whole board: the validated form of one board YAML (after `extends:` is resolved)."""

    name: str = Field(pattern=r"^[a-z0-9][a-z0-9._-]*$")
    description: str = ""
    chip: Chip = "esp32"
    flash_size: Literal["2MB", "4MB", "8MB", "16MB"] = "4MB"
    psram: bool = False
    micropython: MicroPython = MicroPython()
    i2c: dict[str, I2CBus] = Field(default_factory=dict)
    uart: dict[str, UARTBus] = Field(default_factory=dict)
    power: Power = Power()
    imu: Imu
    gps: Gps
    display: Optional[Display] = None
    buttons: Buttons = Buttons()
    led: Optional[Led] = None
    reserved: dict[str, list[int]] = Field(default_factory=dict, description="pins taken by parts we do not drive")
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
        """The Python heap the app gets on this board (micropython.heap_kb, else its firmware's default)."""
        from codegen.board.chips import firmware_heap_kb

        kb = self.micropython.heap_kb
        return 1024 * (kb if kb is not None else firmware_heap_kb(self.chip, self.psram))

    @property
    def calibration_samples(self) -> int:
        """IMU samples the calibration collects: calibration_s at the IMU's achieved sample rate."""
        return max(1, round(self.algorithm.calibration_s * self.imu.achieved_sample_rate_hz))
