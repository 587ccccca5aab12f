"""Every validation rule, with its exact message and the place it points at."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from codegen.board.loader import load_board_report


def _report(tmp_path: Path, text: str, name: str = "board.yaml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text).lstrip("\n"), encoding="utf-8")
    return load_board_report(path)


def _only(report, severity="error"):
    found = [d for d in report.diagnostics if d.severity == severity]
    assert len(found) == 1, [d.message for d in report.diagnostics]
    return found[0]


def _at(diagnostic) -> tuple[int, int]:
    return diagnostic.location.line, diagnostic.location.col


def test_default_board_is_clean():
    report = load_board_report(None)
    assert not report.failed(strict=True), [d.message for d in report.diagnostics]


@pytest.mark.parametrize("pin, message", [
    (7, "led.pin: GPIO7 is wired to the SPI flash on the ESP32"),
    (20, "led.pin: GPIO20 does not exist on the ESP32"),
    (24, "led.pin: GPIO24 does not exist on the ESP32"),
    (30, "led.pin: GPIO30 does not exist on the ESP32"),
    (36, "led.pin: GPIO36 is input-only on the ESP32 and cannot drive an output"),
    (16, "led.pin: GPIO16 is wired to the PSRAM on this board (psram: true)"),
])
def test_esp32_pin_table(tmp_path, pin, message):
    report = _report(tmp_path, f"""
        extends: ttgo-tbeam-v1.1
        led:
          pin: {pin}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == message
    assert str(diagnostic.location) == f"{tmp_path / 'board.yaml'}:3:8" or _at(diagnostic) == (3, 8)


def test_psram_pins_are_free_without_psram(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        psram: false
        led: {pin: 16}
    """)
    assert not report.failed(strict=True), [d.message for d in report.diagnostics]


def test_input_only_pin_with_pull(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        buttons:
          test_mode: {pin: 35, pull: up}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "buttons.test_mode.pin: GPIO35 has no internal pull resistor on the ESP32"
    assert _at(diagnostic) == (3, 20)
    assert "pull: none" in diagnostic.hint


def test_strapping_pin_warns_and_strict_fails(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        led: {pin: 2}
    """)
    diagnostic = _only(report, "warning")
    assert diagnostic.message == "led.pin: GPIO2 is a strapping pin: the level at reset selects the boot mode"
    assert _at(diagnostic) == (2, 12)
    assert not report.failed()
    assert report.failed(strict=True)


def test_strapping_mark_on_ordinary_pin_is_an_error(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        led:
          pin: {pin: 13, strapping_by_design: true}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == (
        "led.pin: `strapping_by_design` on GPIO13, which is not a strapping pin of the ESP32"
    )
    assert _at(diagnostic) == (3, 39)  # the `true`


def test_pin_used_twice_names_both(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        led: {pin: 25}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "GPIO25 is used twice: by buttons.test_mode.pin and by led.pin"
    assert "ttgo-tbeam-v1.1.yaml:" in diagnostic.hint


def test_reserved_lora_pin(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        led: {pin: 26}
    """)
    assert _only(report).message == "GPIO26 is used twice: by reserved.lora and by led.pin"


def test_eight_bit_address_hint(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu:
          address: 0xD0
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "imu.address: 0xd0 is an 8-bit address: I2C addresses here are 7-bit"
    assert diagnostic.hint == "0xd0 >> 1 = 0x68: the MPU-6050 is 0x68"
    assert _at(diagnostic) == (3, 12)


def test_mpu6050_address_and_collision(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {address: 0x3c}
    """)
    messages = sorted(d.message for d in report.diagnostics if d.severity == "error")
    assert messages == [
        "display.address: 0x3c on bus 'main' is already taken by imu",
        "imu.address: the MPU-6050 answers only at 0x68 (AD0 low) or 0x69 (AD0 high), not 0x3c",
    ]


def test_unknown_bus_reference(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {bus: mian}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "imu.bus: there is no i2c bus named 'mian'"
    assert diagnostic.hint == "did you mean `main`?"


def test_block_must_divide_window(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        algorithm:
          block: 15
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "algorithm.block: b = 15 does not divide n = 512"
    assert diagnostic.hint == "the nearest b that divides 512 is 16"
    assert _at(diagnostic) == (3, 10)


def test_fused_median_needs_a_block_its_ring_holds(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        algorithm: {fused_median: true, block: 64}
    """)
    found = _only(report)
    assert found.message == ("algorithm.block: b = 64 is longer than the 32 samples the fused median option "
                             "(fused_median: true) keeps")
    assert _at(found) == (2, 40)  # the value 64
    assert found.hint == "use b <= 32, or fused_median: false"
    assert not _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        algorithm: {fused_median: true, block: 32}
    """).diagnostics


def test_fused_turn_ends_below_where_it_starts(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        algorithm: {fused_turn_start_dps: 5, fused_turn_end_dps: 8}
    """)
    found = _only(report)
    assert found.message == ("algorithm.fused_turn_end_dps: a turn that ends at 8 degree/s cannot start at the "
                             "lower 5 degree/s")
    assert _at(found) == (2, 58)  # the value 8
    assert found.hint == "use fused_turn_end_dps <= fused_turn_start_dps (the defaults are 7 and 12)"
    assert not _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        algorithm: {fused_turn_start_dps: 8, fused_turn_end_dps: 8}
    """).diagnostics


def test_deadband_below_range(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        algorithm: {deadband_g: 2.5}
    """)
    assert _only(report).message == "algorithm.deadband_g: l = 2.5 g is not below the accelerometer range ±2 g"


def test_sample_rate_reachable(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {sample_rate_hz: 2000}
    """)
    assert _only(report).message == "imu.sample_rate_hz: 2000 Hz is above the MPU-6050's 1 kHz accelerometer rate"
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {sample_rate_hz: 300}
    """)
    assert _only(report, "warning").message == "imu.sample_rate_hz: the MPU-6050 can run at 333.333 Hz, not 300 Hz"


def test_auto_platform_needs_the_vibration_band(tmp_path):
    """fused_platform auto sees a vehicle by its shaking above fused_vibration_hz (8 Hz): a DLPF at 10 Hz or a
    25 Hz sample rate hides it; a fixed platform needs none of it."""
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {dlpf: 5}
    """)
    diagnostic = _only(report, "warning")
    assert diagnostic.message == ("algorithm.fused_platform: auto tells a vehicle from a walker by the shaking above "
                                  "fused_vibration_hz (8 Hz), but the IMU passes only up to 10 Hz (imu.dlpf's "
                                  "limit): every shaken vehicle will look like a walker")
    assert _at(diagnostic) == (2, 13)
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {sample_rate_hz: 25}
        logging: {imu_rate_hz: 25}
    """)
    assert "passes only up to 12.5 Hz (imu.sample_rate_hz's limit)" in _only(report, "warning").message
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu: {dlpf: 5}
        algorithm: {fused_platform: vehicle}
    """)
    assert not report.diagnostics


def test_gps_rail_must_be_enabled(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        power:
          rails:
            ldo3: {enable: false}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "gps.power: the GPS rail 'ldo3' is switched off (power.rails.ldo3.enable: false)"
    assert _at(diagnostic) == (4, 20)
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        power:
          rails:
            ldo3: null
    """)
    assert _only(report).message == "gps.power: the GPS is powered from rail 'ldo3', which the board does not enable"


def test_rail_names_come_from_the_pmu_table(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        power:
          rails:
            ldo4: {enable: true}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "power.rails.ldo4: the axp192 has no rail 'ldo4'"
    assert diagnostic.hint == "did you mean `ldo3`?"


def test_rp2040_fixed_pin_muxing(tmp_path):
    report = _report(tmp_path, """
        extends: pico-gy521
        i2c:
          main: {sda: 6}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "i2c.main.sda: GPIO6 cannot be I2C0 SDA on the RP2040"
    assert diagnostic.hint == "I2C0 SDA is on GPIO 0, 4, 8, 12, 16, 20, 24, 28"


def test_esp32s3_table(tmp_path):
    report = _report(tmp_path, """
        extends: esp32s3-devkitc-gy521
        led: {pin: 35}
    """)
    assert _only(report).message == "led.pin: GPIO35 is wired to the PSRAM on this board (psram: true)"
    report = _report(tmp_path, """
        extends: esp32s3-devkitc-gy521
        led: {pin: 22}
    """)
    assert _only(report).message == "led.pin: GPIO22 does not exist on the ESP32-S3"


def test_all_errors_of_a_run_are_reported(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        led: {pin: 7}
        imu: {address: 0xD0}
        algorithm: {block: 15}
    """)
    assert len([d for d in report.diagnostics if d.severity == "error"]) == 3


def test_console_uart_warns(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        uart:
          gps: {id: 0}
    """)
    assert _only(report, "warning").message == "uart.gps.id: UART0 carries MicroPython's REPL console"


def test_filesystem_beyond_flash(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        micropython:
          filesystem: {offset: 0x300000}
    """)
    assert _only(report).message == "micropython.filesystem: ends at 0x500000, beyond the 4MB flash"


# --- what the board's PCB wires for good (`wired:` in the bundled board files) --------------------------------


@pytest.mark.parametrize("lines, at, message", [
    ("i2c:\n  main: {sda: 13, scl: 14}\n", (3, 15),
     "i2c.main.sda: GPIO13, but this board's AXP192 power chip (power.bus: main) is soldered to "
     "SDA GPIO21 / SCL GPIO22"),
    ("i2c:\n  main: {scl: 15}\n", (3, 15),
     "i2c.main.scl: GPIO15, but this board's AXP192 power chip (power.bus: main) is soldered to "
     "SDA GPIO21 / SCL GPIO22"),
    ("i2c:\n  side: {id: 1, sda: 13, scl: 14}\npower: {bus: side}\n", (3, 22),
     "i2c.side.sda: GPIO13, but this board's AXP192 power chip (power.bus: side) is soldered to "
     "SDA GPIO21 / SCL GPIO22"),
    ("uart:\n  gps: {rx: 35}\n", (3, 13),
     "uart.gps.rx: GPIO35, but this board's NEO-6M GPS is soldered to RX GPIO34 / TX GPIO12"),
    ("uart:\n  gps: {tx: 13}\n", (3, 13),
     "uart.gps.tx: GPIO13, but this board's NEO-6M GPS is soldered to RX GPIO34 / TX GPIO12"),
    ("power: {chip: none, rails: null}\ngps: {power: always_on}\n", (2, 15),
     "power.chip: none, but this board has its power chip soldered on I2C SDA GPIO21 / SCL GPIO22"),
])
def test_a_part_the_board_solders_cannot_move(tmp_path, lines, at, message):
    report = _report(tmp_path, "extends: ttgo-tbeam-v1.1\n" + lines)
    diagnostic = _only(report)
    assert diagnostic.message == message
    assert _at(diagnostic) == at
    assert diagnostic.hint


def test_a_part_the_user_added_moves_to_a_second_bus(tmp_path):
    """The README's retarget: the GY-521 on I2C1 at header pins 13/14; the AXP192 and the OLED stay on 21/22."""
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        i2c:
          imu: {id: 1, sda: 13, scl: 14}
        imu: {bus: imu, address: 0x69, axes: [-y, x, z]}
    """)
    assert not report.failed(strict=True), [d.message for d in report.diagnostics]
    display = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        i2c:
          oled: {id: 1, sda: 13, scl: 14}
        display: {bus: oled}
    """, name="oled.yaml")
    assert not display.failed(strict=True), [d.message for d in display.diagnostics]


def test_the_v0_7_gps_is_soldered_to_its_strapping_pins(tmp_path):
    report = _report(tmp_path, "extends: ttgo-tbeam-v0.7\nuart:\n  gps: {rx: 34}\n")
    assert _only(report).message == ("uart.gps.rx: GPIO34, but this board's NEO-6M GPS is soldered to "
                                     "RX GPIO12 / TX GPIO15")


def test_a_file_that_extends_a_board_cannot_rewrite_its_wiring(tmp_path):
    report = _report(tmp_path, """
        extends: ttgo-tbeam-v1.1
        wired:
          power: null
        i2c:
          main: {sda: 13, scl: 14}
    """)
    diagnostic = _only(report)
    assert diagnostic.message.startswith("`wired:` says what the PCB of the board this file extends "
                                         "(ttgo-tbeam-v1.1) solders to fixed pins")
    assert _at(diagnostic) == (2, 1) and "without `extends:`" in diagnostic.hint


def test_a_board_file_of_its_own_declares_its_wiring(tmp_path):
    """A board described from scratch may say what its PCB solders; the rule then holds for it."""
    base = (Path(__file__).resolve().parents[1] / "board_configs" / "esp32-devkitc-gy521.yaml").read_text()
    report = _report(tmp_path, base + "\nwired:\n  imu: {sda: 18, scl: 19}\n")
    assert _only(report).message == ("i2c.main.sda: GPIO21, but this board's MPU-6050 (imu.bus: main) is soldered "
                                     "to SDA GPIO18 / SCL GPIO19")
