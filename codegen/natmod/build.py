"""OUT/native -> a checked dr_native.mpy for the board: the compiler route, MicroPython's natmod make, the checks.

Routes, first found wins:
    CROSS=prefix             the user's compiler (`$(CROSS)gcc`), for any arch
    xtensawin (ESP32, -S3)   xtensa-esp32-elf-gcc (Espressif's GCC), else Debian's LLVM 22 (codegen.natmod.xtensa_llvm)
    armv6m, armv7m           arm-none-eabi-gcc (Debian gcc-arm-none-eabi); the Makefile links libgcc's helpers
    x64                      the host's gcc (the unix port)
The make runs in OUT/build/native with V=1 (mpy_ld -vvv), its output kept in build.log. Afterwards the .mpy's header
is checked against the MicroPython release the board declares (codegen.natmod.abi) and, for xtensawin, every
relocated instruction and word against the link map (codegen.natmod.verify). A module that fails either check is
not installed: the build stops with the reason.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from codegen.errors import UserError
from codegen.natmod import abi, linkmap, mpyfile, verify, xtensa_llvm
from codegen.natmod.sources import micropython_source
from codegen.tools import find_mpy_cross, find_tool, mpy_format, tool_env

GNU_PREFIXES = {"xtensawin": "xtensa-esp32-elf-", "armv6m": "arm-none-eabi-", "armv7m": "arm-none-eabi-",
                "armv7emsp": "arm-none-eabi-", "x64": ""}
LOG_NAME = "build.log"
Progress = Callable[[str], None]


@dataclass(frozen=True)
class Route:
    name: str  # what built the module, as `deadreckon build` prints it
    cross: str  # CROSS for dynruntime.mk


@dataclass
class NativeBuild:
    module: Path
    route: Route
    tree: Path
    tree_from: str
    checks: str  # what was verified, one line


class NoRoute(Exception):
    """No compiler for the arch or no MicroPython source: the message says what to do (the app then uses the
    fallback)."""


def choose_route(arch: str) -> Route:
    cross = os.environ.get("CROSS")
    if cross:
        if find_tool(f"{cross}gcc") is None:
            raise NoRoute(f"no cross compiler for {arch}: CROSS={cross} is set but {cross}gcc is not found")
        return Route(f"CROSS={cross} ({cross}gcc)", cross)
    if arch not in GNU_PREFIXES:
        raise NoRoute(f"deadreckon has no compiler route for {arch}")
    prefix = GNU_PREFIXES[arch]
    gcc = find_tool(f"{prefix}gcc")
    if gcc is not None:
        return Route(f"GNU {prefix}gcc ({gcc})", str(Path(gcc).parent / prefix) if prefix else "")
    if arch == "xtensawin":
        missing = xtensa_llvm.missing_tools()
        prefix = xtensa_llvm.cross_prefix()
        if not missing and prefix is not None:
            return Route(f"LLVM {xtensa_llvm.LLVM_VERSION} Xtensa route (clang/llc/llvm-mc -mcpu=esp32 via "
                         f"{xtensa_llvm.COMMAND})", prefix)
        what = ", ".join(missing) or f"the {xtensa_llvm.COMMAND} command (reinstall deadreckon)"
        raise NoRoute(f"no compiler for ESP32 code: neither xtensa-esp32-elf-gcc nor the LLVM route ({what} "
                      f"missing); {xtensa_llvm.INSTALL_HINT}")
    raise NoRoute(f"{prefix}gcc not found (Debian: apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi)")


def _failure(log: str) -> str:
    """The lines of a failed make that say why: the linker's and compiler's errors first, then the tail."""
    lines = [line for line in log.splitlines() if line.strip()]
    causes = [line for line in lines if re.search(r"(LinkError|[Ee]rror:|undefined symbol|error\b)", line)
              and not line.startswith("make")]
    shown = causes[-8:] or lines[-8:]
    return "\n    ".join(shown)


def build_module(native_dir: Path, work: Path, arch: str, release: str, progress: Progress = print) -> NativeBuild:
    """Build native_dir's Makefile for `arch` in `work` (replaced) against MicroPython `release`; check it."""
    route = choose_route(arch)
    try:
        tree, tree_from = micropython_source(release, progress)
    except UserError as exc:  # offline, a refused download: the app still runs, on the fallback
        raise NoRoute(f"{exc.message}; {exc.hint}" if exc.hint else exc.message) from None
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(native_dir, work)
    progress(f"  native module for {arch}: {route.name}, MicroPython tree {tree_from}")

    command = ["make", "-C", str(work), "V=1", f"MPY_DIR={tree}", f"ARCH={arch}", f"CROSS={route.cross}",
               f"MPY_CROSS={find_mpy_cross(release)}", f"PYTHON={sys.executable}"]
    done = subprocess.run(command, capture_output=True, text=True, env=tool_env())
    log = done.stdout + done.stderr
    (work / LOG_NAME).write_text(log)
    built = work / "dr_native.mpy"
    if done.returncode != 0 or not built.is_file():
        raise UserError(f"the native module did not build for {arch} ({route.name}):\n    {_failure(log)}",
                        hint=f"the whole make output is in {work / LOG_NAME}")
    data = built.read_bytes()
    module = mpyfile.parse(data, built.name)
    tree_abi = abi.tree_abi(tree)
    abi.check_header(module.header, mpy_format(release), arch, release, built.name)
    checks = (f".mpy {module.header.format} for {arch}, what MicroPython {release} loads "
              f"(mp_fun_table {len(tree_abi.fun_table)} entries, layout {tree_abi.fun_table_digest})")
    if tree_abi.version != release:
        checks += f"; built against a {tree_abi.version} tree with the same native ABI"
    if arch == "xtensawin":
        report = verify.verify(module, linkmap.parse(log, work), tree_abi, built.name)
        checks = f"relocations verified: {report.summary()}; " + checks
    return NativeBuild(built, route, tree, tree_from, checks)

