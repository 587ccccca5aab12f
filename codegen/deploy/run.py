"""`deadreckon run BOARD.yaml`: from a board YAML to a running device, and its console on the screen.

generate (into OUT, default `out`) -> build -> onto the board -> monitor. Onto the board:
- with `--firmware FW.bin` (an ESP32 board, blank or not): esptool writes the firmware and the app's filesystem
  image (`deadreckon flash`);
- else, when the board answers as MicroPython on its raw REPL: the files that differ are uploaded (`deadreckon
  upload`) and the board soft-resets into the app;
- else the board does not run MicroPython yet: the error says which firmware to pass.
CircuitPython boards take the app over their CIRCUITPY drive (`--drive`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from codegen.errors import UserError

Progress = Callable[[str], None]


@dataclass
class RunResult:
    out: Path
    port: Optional[str]
    how: str  # "flash", "upload" or "drive"
    native: bool


def runs_micropython(port: str) -> bool:
    """Whether the board on `port` answers as MicroPython's raw REPL (its app interrupted, its watchdog held by a
    timer: codegen/deploy/watchdog.py; it is left in the raw REPL, which the upload enters again)."""
    import serial

    from codegen.deploy.ports import close_quietly, open_port
    from codegen.deploy.upload import RawRepl, ReplError
    from codegen.deploy.watchdog import hold_watchdog

    handle = open_port(port)
    try:
        repl = RawRepl(handle)
        repl.enter()
        hold_watchdog(repl)
        return True
    except (ReplError, serial.SerialException, OSError):
        return False
    finally:
        close_quietly(handle)


def run_device(board_file: Optional[str], out: Path, port: Optional[str] = None, firmware: Optional[Path] = None,
               drive: Optional[Path] = None, force: bool = False, progress: Progress = print) -> RunResult:
    """Generate, build and put the app on the board; returns where it went (the caller monitors `port`)."""
    from codegen.board.loader import load_board
    from codegen.deploy.build import build
    from codegen.deploy.ports import choose_port
    from codegen.generate import generate

    loaded = load_board(board_file)
    board = loaded.board
    generated = generate(loaded, Path(out), force=force)
    progress(f"generated {len(generated.files)} files for {board.name} in {generated.root}")
    built = build(Path(out), progress=progress)
    native = built.native is not None
    if board.target == "circuitpython":
        if drive is None:
            raise UserError(f"{board.name} runs CircuitPython: its app goes onto the CIRCUITPY drive",
                            hint=f"deadreckon run {board_file or ''} --drive /media/$USER/CIRCUITPY".replace("  ", " "))
        from codegen.deploy.drive import upload_drive

        upload_drive(Path(out), Path(drive), force=force)
        return RunResult(Path(out), None, "drive", native)
    chosen = choose_port(port)
    if firmware is not None:
        from codegen.deploy.flash import flash

        flash(Path(out), chosen, firmware=Path(firmware), progress=progress)
        return RunResult(Path(out), chosen, "flash", native)
    progress(f"looking for MicroPython on {chosen}")
    if not runs_micropython(chosen):
        from codegen.deploy.flash import FIRMWARE_NAMES

        name = FIRMWARE_NAMES.get(board.chip)
        if name is None:
            raise UserError(f"the board on {chosen} does not answer as MicroPython",
                            hint=f"install MicroPython {board.micropython.version} on the {board.chip} first "
                                 "(micropython.org/download), then run again")
        raise UserError(f"the board on {chosen} does not answer as MicroPython (blank, or another program)",
                        hint=f"flash MicroPython with the app: --firmware {name}-v{board.micropython.version}.bin "
                             f"(micropython.org/download/{name})")
    from codegen.deploy.upload import upload

    upload(Path(out), chosen, force=force, progress=progress)
    return RunResult(Path(out), chosen, "upload", native)
