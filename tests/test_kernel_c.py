"""The C kernel as C: strict host build, its unit tests under ASan/UBSan, and cross compiles from Debian's packages
(ESP32 Xtensa through clang-22/llc-22, Cortex-M4F hard float and Cortex-M0+ through gcc-arm-none-eabi) with the
.text/.data/.bss sizes printed; .data and .bss must be empty (a MicroPython native module can carry neither)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from codegen.kernel.hostkernel import KERNEL_SOURCES, kernel_sources
from codegen.paths import native_ext_dir
from conftest import require_tool

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic"]


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> Path:
    """The kernel files exactly as `deadreckon generate` emits them for the default board."""
    folder = tmp_path_factory.mktemp("kernel")
    for name, content in kernel_sources().items():
        (folder / name).write_bytes(content)
    return folder


def run(cmd, cwd=None):
    done = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True)
    assert done.returncode == 0, f"{' '.join(map(str, cmd))}\n{done.stdout}\n{done.stderr}"
    return done.stdout


def section_sizes(tool: str, obj: Path) -> dict[str, int]:
    """Sizes of the .text*/.rodata*/.data*/.bss* sections (summed by kind) from `size -A`."""
    sizes = {"text": 0, "rodata": 0, "data": 0, "bss": 0}
    for line in run([tool, "-A", obj]).splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            kind = parts[0][1:].split(".")[0]
            if kind in ("sdata", "sbss"):
                kind = kind[1:]
            if kind in sizes:
                sizes[kind] += int(parts[1])
    return sizes


def report(capsys, target: str, sizes: dict[str, int]) -> None:
    with capsys.disabled():
        print(f"\n  kernel {target:<28} .text {sizes['text']:6d}  .rodata {sizes['rodata']:5d}  "
              f".data {sizes['data']}  .bss {sizes['bss']}")


def test_host_strict_build(sources, tmp_path):
    cc = require_tool("cc")
    for source in KERNEL_SOURCES:
        run([cc, *STRICT, "-O2", "-I", sources, "-c", sources / source, "-o", tmp_path / (source + ".o")])


def test_unit_tests_under_asan_and_ubsan(sources, tmp_path):
    cc = require_tool("gcc")
    binary = tmp_path / "test_kernel"
    run([cc, *STRICT, "-g", "-O1", "-fsanitize=address,undefined", "-fno-sanitize-recover=all",
         "-fno-omit-frame-pointer", "-I", sources, native_ext_dir() / "tests" / "test_kernel.c",
         *[sources / s for s in KERNEL_SOURCES], "-lm", "-o", binary])
    out = run([binary])
    assert "kernel C tests passed" in out


def test_xtensa_esp32_object_has_no_undefined_symbols(sources, tmp_path, capsys):
    clang = require_tool("clang-22")
    llc = require_tool("llc-22")
    link = require_tool("llvm-link-22")
    nm = require_tool("llvm-nm-22")
    size = require_tool("llvm-size-22")
    irs = []
    for source in KERNEL_SOURCES:
        ir = tmp_path / (source + ".ll")
        run([clang, "--target=xtensa", *STRICT, "-Os", "-ffreestanding", "-I", sources, "-S", "-emit-llvm",
             sources / source, "-o", ir])
        irs.append(ir)
    linked = tmp_path / "kernel.ll"
    run([link, "-S", *irs, "-o", linked])
    obj = tmp_path / "kernel_esp32.o"
    # -function-sections: without it llc reports "fixup value must be 4-byte aligned" (see DESIGN.md)
    run([llc, "-mtriple=xtensa", "-mcpu=esp32", "-O2", "-function-sections", "-filetype=obj", linked, "-o", obj])
    undefined = run([nm, "-u", obj]).split()
    assert undefined == [], f"ESP32 object needs {undefined} (soft-float helpers or libm crept in)"
    sizes = section_sizes(size, obj)
    report(capsys, "esp32 (llc-22 xtensa)", sizes)
    assert sizes["data"] == 0 and sizes["bss"] == 0


@pytest.mark.parametrize("target,flags", [
    ("cortex-m4f (hard float)", ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16"]),
    ("cortex-m0+", ["-mcpu=cortex-m0plus", "-mthumb"]),
])
def test_arm_cross_compile(sources, tmp_path, capsys, target, flags):
    gcc = require_tool("arm-none-eabi-gcc")
    ld = require_tool("arm-none-eabi-ld")
    size = require_tool("arm-none-eabi-size")
    nm = require_tool("arm-none-eabi-nm")
    objects = []
    for source in KERNEL_SOURCES:
        obj = tmp_path / (source + ".o")
        run([gcc, *flags, *STRICT, "-Os", "-ffreestanding", "-fsingle-precision-constant", "-ffunction-sections",
             "-I", sources, "-c", sources / source, "-o", obj])
        objects.append(obj)
    combined = tmp_path / "kernel_arm.o"
    run([ld, "-r", *objects, "-o", combined])
    undefined = run([nm, "-u", combined]).split()
    if "m4f" in target:
        assert [u for u in undefined if u != "U"] == [], f"hard-float object needs {undefined}"
    else:  # no FPU: single-float helpers only, never a double one
        assert not [u for u in undefined if u.startswith("__aeabi_d") or "df" in u], undefined
    sizes = section_sizes(size, combined)
    report(capsys, target, sizes)
    assert sizes["data"] == 0 and sizes["bss"] == 0
