"""Write docs/boards.md from the bundled board files: per board, the wiring table, the screen and the buttons.
    .venv/bin/python scripts/boards_doc.py            # rewrite docs/boards.md
    .venv/bin/python scripts/boards_doc.py --check    # exit 1 when docs/boards.md is not what the boards say
tests/test_docs.py runs the check, so the page cannot drift from board_configs/*.yaml.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from codegen.board.loader import bundled_boards, load_board  # noqa: E402

PAGE = ROOT / "docs" / "boards.md"
FONT_PX = 8  # the app's text is 8x8 pixels (framebuf's font; codegen/font.py on CircuitPython)

INTRO = """\
# The bundled boards: wiring, screen and buttons

Written by `scripts/boards_doc.py` from `board_configs/*.yaml` (a test checks this page against them). A board file
of your own starts from one of these with `extends:` ([board files](board-files.md)). "On the board" marks what the
board's PCB solders to fixed pins (its `wired:` section): validation refuses a board file that moves those; every
other part is one you connect.

## What the screen shows

The app draws up to 8 lines of text (8x8 pixel characters, so a 128x64 OLED shows 8 lines of 16 characters; a
smaller one cuts them), refreshed every `display.refresh_ms`:

| line | with a GPS fix | without one (dead reckoning) |
|---|---|---|
| 1 | `GPS fix 0.4s`: the mode and the age of the last fix (`CAL 3s` while calibrating, `no fix` before the first) | `IMU fix 12.0s` (`TEST` in test mode) |
| 2, 3 | latitude and longitude of the fix | the position dead-reckoned from the last fix |
| 4 | speed over ground and course: `1.32m/s  87deg` | the IMU's speed and course |
| 5 | `sats 7 hdop 1.2` | `E+12.3 N-4.1`: metres East and North of the last fix |
| 6 | `imu 200Hz drop 0`: the IMU's measured rate and the samples the loop missed (`IMU missing` without one) | the same |
| 7 | the status: `calibrating`, `calibrated` (`moved! again`: it was moved while calibrating), or the last warning (`GPS silent`, `IMU lost`, `reset: watchdog`, ...) | the same |
| 8 | `TEST MODE` while the test-mode button has the GPS ignored | the same |

## What the buttons do

- **calibrate**: starts a new calibration: keep the device still for `algorithm.calibration_s` seconds (the screen
  counts them); it measures the gyro's bias and the tilt, and starts again by itself when the device moved. The app
  also calibrates once at start.
- **test mode**: ignores the GPS from the press on, as if the fix were lost (the screen says `TEST MODE` and the
  LED lights); press again to take the GPS back. This is how to see dead reckoning without walking into a tunnel.
"""


def _i2c_label(board, bus_name: str) -> str:
    bus = board.i2c[bus_name]
    where = "I2C" if board.target == "circuitpython" else f"I2C{bus.id}"
    return f"{where} `{bus_name}`, SDA {bus.sda.label}, SCL {bus.scl.label}, {bus.frequency // 1000} kHz"


def _on_board(wired) -> str:
    return "on the board" if wired is not None else "you connect it"


def board_section(name: str) -> str:
    board = load_board(name).board
    rows = []
    if board.power.chip != "none":
        rows.append((f"{board.power.chip.upper()} power chip at {board.power.address:#04x}",
                     _i2c_label(board, board.power.bus), _on_board(board.wired.power)))
    rows.append((f"MPU-6050 at {board.imu.address:#04x}, axes {', '.join(board.imu.axes)}",
                 _i2c_label(board, board.imu.bus), _on_board(board.wired.imu)))
    if board.display is not None:
        d = board.display
        rows.append((f"{d.model.upper()} OLED {d.width}x{d.height} at {d.address:#04x}", _i2c_label(board, d.bus),
                     _on_board(board.wired.display)))
    uart = board.uart[board.gps.uart]
    link = f"board RX {uart.rx.label} <- GPS TX"
    if uart.tx is not None:
        link += f", board TX {uart.tx.label} -> GPS RX"
    uart_name = "UART" if board.target == "circuitpython" else f"UART{uart.id}"
    power = "always powered" if board.gps.power == "always_on" else f"powered from the {board.gps.power} rail"
    rows.append((f"{board.gps.model.upper()} GPS, {uart.baud} baud, {board.gps.rate_hz:g} Hz, {power}",
                 f"{uart_name} `{board.gps.uart}`: {link}", _on_board(board.wired.gps)))
    for role, title in (("calibrate", "calibrate button"), ("test_mode", "test-mode button")):
        button = getattr(board.buttons, role)
        if button is not None:
            pull = "no internal pull" if button.pull == "none" else f"internal pull-{button.pull}"
            rows.append((title, f"{button.pin.label}, active {button.active}, {pull}", ""))
    if board.led is not None:
        rows.append(("LED (lit in test mode)",
                     f"{board.led.pin.label}" + (", active low" if board.led.active_low else ""), ""))
    for group, pins in board.reserved.items():
        rows.append((f"reserved: {group}", "GPIO " + ", ".join(map(str, pins)), "never assigned"))

    firmware = (f"CircuitPython {board.circuitpython.version} (`{board.circuitpython.board}`)"
                if board.target == "circuitpython" else f"MicroPython {board.micropython.version}")
    lines = [f"## `{name}`", "", board.description + ".", "",
             f"{board.chip.upper()}, {board.flash_size} flash{', PSRAM' if board.psram else ''}; {firmware}; "
             f"heap {board.heap_bytes // 1024} KiB; the IMU at {board.imu.sample_rate_hz:g} Hz, algorithm "
             f"`{board.algorithm.mode}`.", "",
             "| part | connection | |", "|---|---|---|"]
    lines += [f"| {part} | {connection} | {where} |" for part, connection, where in rows]
    if board.display is not None:
        d = board.display
        lines += ["", f"Screen: {d.height // FONT_PX} lines of {d.width // FONT_PX} characters."]
    return "\n".join(lines) + "\n"


def page() -> str:
    sections = [board_section(name) for name, _path, _description in bundled_boards()]
    return INTRO + "\n" + "\n".join(sections)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    args = parser.parse_args(argv)
    text = page()
    if args.check:
        current = PAGE.read_text(encoding="utf-8") if PAGE.exists() else ""
        if current != text:
            print(f"{PAGE.relative_to(ROOT)} is stale: run scripts/boards_doc.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
