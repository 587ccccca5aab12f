"""Shared test helpers.

`require(condition, reason)`: a test that needs a tool skips locally with the reason, and fails under CI=true,
so a missing install step can never hide behind a skip. Tools are found as the product finds them
(`codegen.tools.find_tool`: the running interpreter's bin/ first, then PATH), so an unactivated virtualenv works.
`mpy_dir()`: the MicroPython source tree for natmod builds, MPY_DIR or the shared v1.28.0 tree beside the project.
`board_micropython()`: MicroPython's unix port computing as the ESP32 and RP2040 do (single precision, 32-bit), and
`circuitpython()`: CircuitPython's unix port (30-bit floats, 32-bit, ulab), each built once per content of the shared
tree into the cache (codegen/portbuild.py); `circuitpython_mpy_cross()` likewise. The PyPI `micropython` (64-bit,
double precision) stays for tests that need nothing of the boards' arithmetic.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import pytest

from codegen import portbuild
from codegen.tools import SHARED_CIRCUITPYTHON, SHARED_MICROPYTHON, find_tool, micropython_tree

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


CIRCUITPYTHON_RELEASE = "10.2.1"  # ../shared/circuitpython's release: the bundled CircuitPython boards declare it


@functools.cache
def _built(product: portbuild.Product, tree: Path, version: str) -> tuple[str | None, str]:
    try:
        return str(portbuild.build(product, tree, version=version)), ""
    except portbuild.PortBuildError as e:
        return None, f"{e} ({e.hint})" if e.hint else str(e)


def _require_built(product: portbuild.Product, tree: Path, version: str = "") -> str:
    require(tree.is_dir(), f"{tree} is missing: {product.name} is built from it")
    path, why = _built(product, tree, version)
    require(path is not None, f"{product.name} could not be built: {why}")
    return path


def board_micropython() -> str:
    """The single-precision 32-bit unix MicroPython (from ../shared/micropython), built on first use."""
    return _require_built(portbuild.BOARD_MICROPYTHON, SHARED_MICROPYTHON)


def circuitpython() -> str:
    """CircuitPython's 30-bit-float 32-bit unix port with ulab (from ../shared/circuitpython), built on first use."""
    return _require_built(portbuild.CIRCUITPYTHON, SHARED_CIRCUITPYTHON, CIRCUITPYTHON_RELEASE)


def circuitpython_mpy_cross() -> str:
    """CircuitPython's own mpy-cross for the shared tree's release, built on first use."""
    return _require_built(portbuild.CIRCUITPYTHON_MPY_CROSS, SHARED_CIRCUITPYTHON, CIRCUITPYTHON_RELEASE)
