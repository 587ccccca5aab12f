"""Does the app fit the board's filesystem, with the room its log needs? Asked by `validate` and `generate`, long
before a build finds out (or, worse, the board: an app that fits but leaves no room logs nothing).

The app is measured as its generated sources, in a LittleFS of the board's vfs size with MicroPython's parameters
(`codegen.deploy.fsimage`): the .mpy files `build` makes from them are smaller, which leaves room for the native
module. With logging on, the app needs `logging.min_free_kb` plus one log block free to open a log file
(templates/micropython/logger.py.j2).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from codegen.board.diagnostics import Diagnostic, error

if TYPE_CHECKING:
    from codegen.board.loader import LoadedBoard


def fit_diagnostics(loaded: "LoadedBoard", app: dict[str, bytes]) -> list[Diagnostic]:
    """An error located at micropython.filesystem.size when the app (its files' contents by their path on the
    board, `codegen.generate.app_contents`) does not fit the board's filesystem with the room its log needs; no
    findings when it does."""
    from codegen.deploy.fsimage import free_after

    board = loaded.board
    if board.target == "circuitpython":
        return []  # its CIRCUITPY drive is the firmware's (FAT, its size per build): `upload --drive` checks the room
    fs = board.micropython.filesystem
    app_bytes = sum(map(len, app.values()))
    log_room = (board.logging.min_free_kb * 1024 + board.logging.block_bytes) if board.logging.enabled else 0
    free = free_after(app, fs.size, fs.block_size)
    where = loaded.source.value(("micropython", "filesystem", "size"))
    if free is not None and free >= log_room:
        return []
    needed_kib = -(-(fs.size - (free or 0) + log_room) // 1024) if free is not None else None
    what = f"the app ({len(app)} files, {app_bytes // 1024} KiB)"
    if free is None:
        message = f"micropython.filesystem.size: {what} does not fit in the {fs.size // 1024} KiB filesystem"
        hint = "enlarge the filesystem (a firmware with a bigger vfs partition), or a board with more flash"
    else:
        message = (f"micropython.filesystem.size: {what} leaves {free // 1024} KiB of the {fs.size // 1024} KiB "
                   f"filesystem free; its log needs {log_room // 1024} KiB (logging.min_free_kb + one block)")
        hint = (f"the filesystem needs at least {needed_kib} KiB; or lower logging.min_free_kb, or set "
                "logging.enabled: false")
    return [error(message, where, hint)]
