"""Shared test helpers.

`require(condition, reason)`: a test that needs a tool skips locally with the reason, and fails under CI=true,
so a missing install step can never hide behind a skip. Tools are found as the product finds them
(`codegen.tools.find_tool`: the running interpreter's bin/ first, then PATH), so an unactivated virtualenv works.
`mpy_dir()`: the MicroPython source tree for natmod builds, MPY_DIR or the shared v1.28.0 tree beside the project.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from codegen.tools import SHARED_MICROPYTHON, find_tool, micropython_tree

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"
IN_CI = os.environ.get("CI", "").lower() == "true"


def require(condition: bool, reason: str) -> None:
    if condition:
        return
    if IN_CI:
        pytest.fail(f"required under CI=true: {reason}")
    pytest.skip(reason)


def require_tool(name: str) -> str:
    path = find_tool(name)
    require(path is not None, f"{name} is not installed (scripts/setup.sh installs it)")
    return path


def mpy_dir() -> Path:
    """A MicroPython source tree to build natmods against: MPY_DIR, else ../shared/micropython (v1.28.0). Natmod
    builds only read it (they build in the module's folder; bytecode writing is off), so it is not copied."""
    path = micropython_tree()
    where = os.environ.get("MPY_DIR") or SHARED_MICROPYTHON
    require(path is not None, f"{where} is not a MicroPython source tree (no py/dynruntime.mk): set MPY_DIR or put "
            "the shared tree beside the project")
    return path


def require_shared_data(*parts: str) -> Path:
    path = SHARED_DATA.joinpath(*parts)
    require(path.exists(), f"shared recording {path} is missing")
    return path
