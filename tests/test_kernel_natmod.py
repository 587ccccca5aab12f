"""The generated native module built as a MicroPython dynamic native module (.mpy) from a MicroPython source tree.

Built against MPY_DIR, or the shared MicroPython v1.28.0 tree beside the project (conftest.mpy_dir). x64: the
equivalence vectors run through dr_native inside the unix-port `micropython` and must equal the cffi build of the
same C bit for bit. Every bundled board: `deadreckon build` makes and checks the natmod for its arch (the ESP32 code
itself is run in tests/test_natmod_xtensa.py, the ARM code in tests/test_natmod_qemu.py).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from codegen.board.loader import bundled_boards
from codegen.tools import find_tool, tool_env
from conftest import mpy_dir, require_tool
from kernelkit import run_c, run_driver
from test_kernel_equivalence import _mp_cases

BOARDS = [name for name, _, _ in bundled_boards("micropython")]  # CircuitPython boards have no native module


def native_tree(folder: Path) -> Path:
    """OUT/native/ as `deadreckon generate` writes it for the default board."""
    from codegen.board.loader import load_board
    from codegen.generate import render_tree

    native = folder / "native"
    for name, rendered in render_tree(load_board()).items():
        if name.startswith("native/"):
            target = folder / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(rendered.content)
    return native


def make(native: Path, arch: str, *extra: str) -> subprocess.CompletedProcess:
    mpy_cross = require_tool("mpy-cross")
    return subprocess.run(["make", f"MPY_DIR={mpy_dir()}", f"ARCH={arch}", f"MPY_CROSS={mpy_cross}",
                           f"PYTHON={sys.executable}", *extra], cwd=native, capture_output=True, text=True,
                          env=tool_env())


def test_x64_natmod_equals_cffi_kernel(tmp_path):
    mpy_dir()
    require_tool("make")
    require_tool("micropython")
    from codegen.kernel.hostkernel import load_kernel

    native = native_tree(tmp_path)
    done = make(native, "x64")
    assert done.returncode == 0, done.stdout + done.stderr
    assert (native / "dr_native.mpy").is_file()
    cases = _mp_cases()
    rng = np.random.default_rng(9)
    medians = [(rng.normal(0, 2, 48).astype(np.float32), b) for b in (1, 2, 3, 16, 48)]
    answer = run_driver("dr_native", native, cases, medians, work=tmp_path)
    kernel = load_kernel()
    for (values, b), got in zip(medians, answer["medians"]):
        assert np.array_equal(np.array(got, np.float32), kernel.block_median(values, b))
    for case, mp in zip(cases, answer["cases"]):
        for (d, v, q, _), (out, mq) in zip(run_c(kernel, case), mp["windows"]):
            assert np.array_equal(np.array(out, np.float32), np.concatenate([d, v]).astype(np.float32))
            assert np.array_equal(np.array(mq, np.float32), q.astype(np.float32))


@pytest.mark.parametrize("board_name", BOARDS)
def test_deadreckon_build_makes_a_verified_natmod_for_every_bundled_board(board_name, tmp_path, monkeypatch, capsys):
    """`deadreckon build` on each bundled board's generated tree: the route it names, the checks it passed, and a
    dr_native.mpy for the board's arch in the app (ESP32 boards through the LLVM route when Espressif's GCC is
    absent, the Pico through arm-none-eabi-gcc with libgcc's helpers)."""
    from codegen.board.loader import load_board
    from codegen.cli import main
    from codegen.natmod import mpyfile

    mpy_dir()
    require_tool("make")
    loaded = load_board(board_name)
    arch = loaded.board.mpy_arch
    if arch == "xtensawin":
        for tool in ("clang-22", "llc-22", "llvm-mc-22", "deadreckon-xtensa-llvm-gcc"):
            require_tool(tool)
    else:
        require_tool("arm-none-eabi-gcc")
    monkeypatch.delenv("CROSS", raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["generate", str(loaded.files[0]), "-o", "out"]) == 0
    capsys.readouterr()
    assert main(["build", "out"]) == 0
    text = capsys.readouterr().out
    module = tmp_path / "out" / "build" / "app" / "dr_native.mpy"
    assert module.is_file(), text
    header = mpyfile.parse(module.read_bytes()).header
    assert (header.arch, header.format) == (arch, "6.3")
    route = "LLVM 22 Xtensa route" if arch == "xtensawin" and find_tool("xtensa-esp32-elf-gcc") is None else "gcc"
    assert f"built for {arch} by the" in text and route in text, text
    assert "verifier passed" in text and "what MicroPython 1.28.0 loads" in text, text
    if arch == "xtensawin":
        assert "relocations verified" in text, text
