"""The interpreters the app tests run on compute as the boards do (codegen/portbuild.py, docs/board-precision.md)."""

from __future__ import annotations

import subprocess

import pytest

from codegen import portbuild
from conftest import board_micropython, circuitpython, circuitpython_mpy_cross

PROBE = "import sys\nprint(sys.implementation.name, sys.maxsize, 16777217.0, 1.0 + 2**-23 == 1.0)"


def _run(interpreter: str, code: str) -> str:
    done = subprocess.run([interpreter, "-c", code], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr + done.stdout
    return done.stdout.strip()


def test_board_micropython_is_single_precision_and_32_bit():
    assert _run(board_micropython(), PROBE) == "micropython 2147483647 16777216.0 False"


def test_circuitpython_has_30_bit_floats_and_ulab():
    assert _run(circuitpython(), PROBE) == "circuitpython 2147483647 16777220.0 True"
    assert _run(circuitpython(), "from ulab import numpy as np\nprint(np.array([1, 2]).dtype == np.float)") == "True"


def test_circuitpython_mpy_cross_writes_circuitpython_mpy(tmp_path):
    source = tmp_path / "m.py"
    source.write_text("x = 1.5\n")
    subprocess.run([circuitpython_mpy_cross(), str(source)], check=True, timeout=30)
    assert (tmp_path / "m.mpy").read_bytes()[:2] == b"C\x06"


def test_a_tree_without_the_ports_folders_is_named(tmp_path):
    (tmp_path / "py").mkdir()
    with pytest.raises(portbuild.PortBuildError, match=r"has no extmod, shared, .*ports/unix"):
        portbuild.build(portbuild.BOARD_MICROPYTHON, tmp_path)
