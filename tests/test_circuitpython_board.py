"""`target: circuitpython`: pins as the board's board.* names, checked against its pin table; what CircuitPython
decides itself or lacks, refused or mapped with the place and a hint."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from codegen.board.chips import CHIPS
from codegen.board.circuitpython import BOARDS
from codegen.board.loader import load_board, load_board_report

PICO = "pico-gy521-circuitpython"
S3 = "esp32s3-devkitc-gy521-circuitpython"


def _report(tmp_path: Path, text: str):
    path = tmp_path / "board.yaml"
    path.write_text(textwrap.dedent(text).lstrip("\n"), encoding="utf-8")
    return load_board_report(path)


def _errors(report, severity="error"):
    return [d for d in report.diagnostics if d.severity == severity]


def _only(report, severity="error"):
    found = _errors(report, severity)
    assert len(found) == 1, [d.message for d in report.diagnostics]
    return found[0]


def _at(diagnostic) -> tuple[int, int]:
    return diagnostic.location.line, diagnostic.location.col


@pytest.mark.parametrize("name", [PICO, S3])
def test_bundled_circuitpython_boards_are_clean(name):
    report = load_board_report(name)
    assert not report.failed(strict=True), [d.message for d in report.diagnostics]
    board = report.board
    assert board.target == "circuitpython"


def test_names_resolve_to_the_gpios_of_the_micropython_twin():
    """The CircuitPython boards are wired as their MicroPython twins: the same GPIO behind every name."""
    for cp_name, mp_name in ((PICO, "pico-gy521"), (S3, "esp32s3-devkitc-gy521")):
        cp, mp = load_board(cp_name).board, load_board(mp_name).board
        assert [cp.i2c["main"].sda.pin, cp.i2c["main"].scl.pin] == [mp.i2c["main"].sda.pin, mp.i2c["main"].scl.pin]
        assert cp.uart["gps"].rx.pin == mp.uart["gps"].rx.pin and cp.uart["gps"].tx.pin == mp.uart["gps"].tx.pin
        assert cp.buttons.calibrate.pin.pin == mp.buttons.calibrate.pin.pin
        assert cp.buttons.test_mode.pin.pin == mp.buttons.test_mode.pin.pin
        assert cp.led.pin.pin == mp.led.pin.pin
    pico = load_board(PICO).board
    assert (pico.i2c["main"].sda.name, pico.led.pin.name, pico.led.pin.pin) == ("GP4", "LED", 25)


def test_a_name_the_board_lacks_is_located_with_did_you_mean(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        i2c:
          main: {{sda: GP44, scl: GP5}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "i2c.main.sda: the Raspberry Pi Pico has no pin of that name (got 'GP44')"
    assert _at(diagnostic) == (3, 15)
    assert diagnostic.hint == "did you mean `GP4`?"


@pytest.mark.parametrize("written, hint", [
    ("gp14", "did you mean `GP14`?"),
    ("board.LEDD", "did you mean `LED`?"),
    ("IO14", "did you mean `GP14`?"),
])
def test_near_misses(tmp_path, written, hint):
    report = _report(tmp_path, f"""
        extends: {PICO}
        led: {{pin: {written}}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message.startswith("led.pin: the Raspberry Pi Pico has no pin of that name")
    assert diagnostic.hint == hint


def test_board_prefix_and_aliases_are_the_same_pin(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        led: {{pin: board.GP25}}
        buttons:
          calibrate: {{pin: GP26_A0}}
    """)
    assert not report.failed(strict=True), [d.message for d in report.diagnostics]
    assert report.board.led.pin.pin == 25 and report.board.led.pin.name == "GP25"
    assert report.board.buttons.calibrate.pin.pin == 26


def test_a_gpio_number_on_circuitpython_names_the_pin_to_write(tmp_path):
    report = _report(tmp_path, f"""
        extends: {S3}
        led: {{pin: 21}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == ("led.pin: a CircuitPython pin is written as the board's name for it, not as a GPIO "
                                  "number (got 21)")
    assert diagnostic.hint == "GPIO21 is `IO21` (board.IO21) on the ESP32-S3-DevKitC-1-N8R8"
    assert _at(diagnostic) == (2, 12)


def test_a_board_name_on_micropython_says_whose_names_they_are(tmp_path):
    report = _report(tmp_path, """
        extends: pico-gy521
        led: {pin: GP25}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "led.pin: a pin is a GPIO number, not the string 'GP25'"
    assert "target: circuitpython" in diagnostic.hint


def test_the_name_key_is_not_written_by_hand(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        led: {{pin: {{pin: GP25, name: GP7}}}}
    """)
    assert _only(report).message.startswith("led.pin: `name` is not written in a board file")


def test_unknown_and_missing_board_ids(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        circuitpython: {{board: raspbery_pi_pico}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == ("circuitpython.board: deadreckon has no pin table for the CircuitPython board "
                                  "'raspbery_pi_pico'")
    assert diagnostic.hint == "did you mean `raspberry_pi_pico`?" and _at(diagnostic) == (2, 24)
    report = _report(tmp_path, """
        extends: pico-gy521
        target: circuitpython
    """)
    first = _errors(report)[0]
    assert first.message == "target: circuitpython needs circuitpython.board, the board's CircuitPython board_id"
    assert _at(first) == (2, 9) and "raspberry_pi_pico" in first.hint


def test_chip_flash_and_psram_must_be_the_boards(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        chip: esp32s3
        flash_size: 4MB
        psram: true
    """)
    messages = {d.message: _at(d) for d in _errors(report)}
    assert messages == {
        "chip: the Raspberry Pi Pico (raspberry_pi_pico) is an RP2040, not an ESP32S3": (2, 7),
        "flash_size: the Raspberry Pi Pico has 2MB of flash, not 4MB": (3, 13),
        "psram: the Raspberry Pi Pico has no PSRAM (psram: true)": (4, 8),
    }


def test_micropython_firmware_settings_are_refused(tmp_path):
    report = _report(tmp_path, f"""
        extends: {S3}
        micropython:
          filesystem: {{offset: 0x200000, size: 0x600000}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message.startswith("micropython: describes MicroPython's firmware")
    assert _at(diagnostic) == (2, 1) and "circuitpython.version" in diagnostic.hint


def test_circuitpython_section_on_a_micropython_board_is_a_warning(tmp_path):
    report = _report(tmp_path, """
        extends: pico-gy521
        circuitpython: {board: raspberry_pi_pico}
    """)
    diagnostic = _only(report, "warning")
    assert diagnostic.message.startswith("circuitpython: applies to `target: circuitpython` only")
    assert not _errors(report)


def test_bus_ids_are_not_used_and_say_so(tmp_path):
    report = _report(tmp_path, f"""
        extends: {S3}
        uart:
          gps: {{id: 2, rx: IO18, tx: IO17}}
    """)
    diagnostic = _only(report, "warning")
    assert diagnostic.message == ("uart.gps.id: busio.UART picks the peripheral from the pins; the id is not used on "
                                  "CircuitPython")
    assert _at(diagnostic) == (3, 9)


def test_rp2040_pins_of_one_bus_must_share_a_peripheral(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        i2c:
          main: {{sda: GP4, scl: GP7}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == ("i2c.main: no I2C peripheral of the RP2040 has SDA board.GP4 (GPIO4) and SCL "
                                  "board.GP7 (GPIO7)")
    assert "I2C0: SDA GPIO 0/4/8" in diagnostic.hint


def test_rp2040_two_buses_on_one_peripheral(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        i2c:
          other: {{sda: GP8, scl: GP9}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "i2c.other: its pins are on I2C0, which i2c.main already uses"


def test_chip_rules_apply_to_the_gpio_behind_a_name(tmp_path):
    report = _report(tmp_path, f"""
        extends: {S3}
        buttons:
          test_mode: {{pin: IO35}}
    """)
    diagnostic = _only(report)
    assert diagnostic.message == "buttons.test_mode.pin: board.IO35 (GPIO35) is wired to the PSRAM on this board " \
                                 "(psram: true)"
    warned = _only(_report(tmp_path, f"""
        extends: {S3}
        buttons:
          test_mode: {{pin: IO46}}
    """), "warning")
    assert warned.hint == "if the board is designed this way, write `{pin: IO46, strapping_by_design: true}`"


def test_old_circuitpython_is_refused(tmp_path):
    report = _report(tmp_path, f"""
        extends: {PICO}
        circuitpython: {{version: "8.2.10"}}
    """)
    assert _only(report).message == "circuitpython.version: the app needs CircuitPython 9.0 or newer, not 8.2.10"


@pytest.mark.parametrize("board_id", sorted(BOARDS))
def test_pin_tables_point_at_gpios_the_chip_has(board_id):
    board = BOARDS[board_id]
    chip = CHIPS[board.chip]
    assert set(board.pins.values()) <= chip.existing
    for gpio in set(board.pins.values()):
        names = board.names_of(gpio)
        numbered = [n for n in names if n in (f"GP{gpio}", f"IO{gpio}")]
        assert names[0] == (numbered[0] if numbered else names[0])  # hints name the numbered pin where there is one
