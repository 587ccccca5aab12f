"""The generated native module built as a MicroPython dynamic native module (.mpy) from a MicroPython source tree.

Built against MPY_DIR, or the shared MicroPython v1.28.0 tree beside the project (conftest.mpy_dir). x64: the
equivalence vectors run through dr_native inside the unix-port `micropython` and must equal the cffi build of the
same C bit for bit. xtensawin: linked from clang-22/llc-22 objects (tests/xtensa_llvm_gcc.py stands in for the
missing xtensa-esp32-elf-gcc).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from codegen.tools import tool_env
from conftest import mpy_dir, require_tool
from kernelkit import run_c, run_driver
from test_kernel_equivalence import _mp_cases


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


def test_xtensawin_natmod_links_with_llvm_objects(tmp_path, capsys):
    """MicroPython's natmod linker (tools/mpy_ld.py) takes the clang-22/llc-22 objects once tests/xtensa_llvm_gcc.py
    has reshaped them the way GCC lays them out; the .mpy is checked by its header (no ESP32 here to run it)."""
    mpy_dir()
    require_tool("make")
    for tool in ("clang-22", "llc-22", "llvm-mc-22"):
        require_tool(tool)
    native = native_tree(tmp_path)
    wrapper = tmp_path / "bin" / "xtensa-llvm-gcc"
    wrapper.parent.mkdir()
    shutil.copy(Path(__file__).with_name("xtensa_llvm_gcc.py"), wrapper)
    wrapper.chmod(0o755)
    done = make(native, "xtensawin", f"CROSS={wrapper.parent}/xtensa-llvm-")
    lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip() and not line.startswith("make")]
    sizes = " ".join(line.strip() for line in lines if line.startswith(("text size", "rodata size", "bss size")))
    with capsys.disabled():
        print(f"\n  xtensawin natmod from llc-22 objects: {'linked, ' + sizes if done.returncode == 0 else lines[-1]}")
    assert done.returncode == 0, "\n".join(lines[-20:])
    mpy = (native / "dr_native.mpy").read_bytes()
    # header: "M", version 6, arch xtensawin (MP_NATIVE_ARCH_XTENSAWIN = 10) in the top 6 bits of the flags byte
    assert mpy[0:1] == b"M" and mpy[1] == 6 and mpy[2] >> 2 == 10, mpy[:4]
    assert "bss size:     0" in done.stdout
