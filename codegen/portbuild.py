"""Interpreters and compilers built from a MicroPython or CircuitPython source tree, once per content, into the cache.

    board-micropython    MicroPython's unix port as the ESP32 and RP2040 compute: single-precision floats, 32-bit
                         (Debian gcc-multilib); `16777217.0` prints `16777216.0`
    circuitpython        CircuitPython's unix port as its boards compute: 30-bit floats (MICROPY_OBJ_REPR_C with
                         single precision), 32-bit, sys.implementation.name 'circuitpython', ulab with float32 arrays
    circuitpython-mpy-cross
                         CircuitPython's own mpy-cross (its .mpy start with b'C'), the compiler `deadreckon build`
                         uses for a CircuitPython board
    qemu-arm             MicroPython's QEMU port per ARM board (its Product is made by codegen/natmod/qemu_arm.py,
                         one per board's flags)

The make lines are the ones the trees' SOURCE.txt give. A source tree may be read-only (the shared trees are, in
CI), so each build copies the folders it reads into $DEADRECKON_CACHE/PRODUCT/KEY/src, builds there, keeps the one
file it wants as $DEADRECKON_CACHE/PRODUCT/KEY/NAME and removes the copy. KEY hashes the copied folders' paths and
contents, the make line and the host compiler's version, so a changed tree or flag builds anew and an unchanged one
never again (CI builds each once per content). A lock file makes concurrent test workers wait for one build.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from codegen.errors import UserError

Log = Optional[Callable[[str], None]]


class PortBuildError(UserError):
    pass


@dataclass(frozen=True)
class Product:
    name: str  # the cache folder's name
    dirs: tuple[str, ...]  # the tree's folders the build reads (copied)
    make_dir: str  # where make runs, inside the tree
    make_args: tuple[str, ...]
    built: str  # the file the build leaves, relative to make_dir
    needs: str = "gcc"  # the compiler the build uses (its version is part of the key)
    hint: str = "apt-get install gcc-multilib make"


BOARD_MICROPYTHON = Product(
    name="board-micropython",
    dirs=("py", "extmod", "shared", "lib", "drivers", "ports/unix", "tools", "mpy-cross"),
    make_dir="ports/unix",
    make_args=("VARIANT=standard", "BUILD=build-board", "FROZEN_MANIFEST=", "MICROPY_FORCE_32BIT=1",
               "MICROPY_PY_FFI=0", "MICROPY_PY_BTREE=0", "MICROPY_PY_SSL=0",
               "CFLAGS_EXTRA=-DMICROPY_FLOAT_IMPL=MICROPY_FLOAT_IMPL_FLOAT"),
    built="build-board/micropython",
)
CIRCUITPYTHON_DIRS = ("py", "extmod", "shared", "shared-bindings", "shared-module", "supervisor", "ports/unix",
                      "mpy-cross", "lib", "tools", "locale")
CIRCUITPYTHON = Product(
    name="circuitpython",
    dirs=CIRCUITPYTHON_DIRS,
    make_dir="ports/unix",
    make_args=("VARIANT=standard", "BUILD=build-board", "MICROPY_FORCE_32BIT=1", "MICROPY_PY_FFI=0",
               "FROZEN_MANIFEST=",
               "CFLAGS_EXTRA=-DMICROPY_PY_MICROPYTHON_RINGIO=0 -DMICROPY_OBJ_REPR=MICROPY_OBJ_REPR_C "
               "-DMICROPY_FLOAT_IMPL=MICROPY_FLOAT_IMPL_FLOAT"),
    built="build-board/micropython",
)
CIRCUITPYTHON_MPY_CROSS = Product(
    name="circuitpython-mpy-cross",
    dirs=CIRCUITPYTHON_DIRS,
    make_dir="mpy-cross",
    make_args=(),
    built="build/mpy-cross",
    hint="apt-get install gcc make",
)


def cache_root() -> Path:
    root = os.environ.get("DEADRECKON_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "deadreckon"


def tree_digest(tree: Path, dirs: tuple[str, ...]) -> str:
    """SHA-256 over the paths and contents of the files in `dirs` of `tree` (what the build reads)."""
    h = hashlib.sha256()
    for top in dirs:
        for path in sorted((tree / top).rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                h.update(path.relative_to(tree).as_posix().encode() + b"\0")
                h.update(path.read_bytes())
    return h.hexdigest()


def _compiler_version(name: str, hint: str) -> str:
    cc = shutil.which(name)
    if cc is None:
        raise PortBuildError(f"{name} is not installed", hint=hint)
    return subprocess.run([cc, "--version"], capture_output=True, text=True).stdout.splitlines()[0]


def build(product: Product, tree: Path, version: str = "", log: Log = None) -> Path:
    """The file `product` builds from `tree`, built into the cache on first use. `version`: CircuitPython's release
    (its trees carry no git tag to read it from; CP_VERSION in the build's environment)."""
    tree = Path(tree)
    missing = [d for d in product.dirs if not (tree / d).is_dir()]
    if missing:
        raise PortBuildError(f"{tree} has no {', '.join(missing)}: not a source tree {product.name} builds from",
                             hint="point at the top of the MicroPython or CircuitPython source tree")
    env = {"CP_VERSION": version} if version else {}
    key = hashlib.sha256(f"{tree_digest(tree, product.dirs)} {product.make_args} {sorted(env.items())} "
                         f"{_compiler_version(product.needs, product.hint)}".encode()).hexdigest()
    home = cache_root() / product.name / key[:24]
    result = home / Path(product.built).name
    if result.is_file():
        return result
    home.mkdir(parents=True, exist_ok=True)
    with open(home / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process may be building the same product
        if result.is_file():
            return result
        source = home / "src"
        if source.exists():
            shutil.rmtree(source)
        for top in product.dirs:
            shutil.copytree(tree / top, source / top, symlinks=True)
        for path in source.rglob("*"):  # the tree may be read-only; the copy must take build output
            path.chmod(path.stat().st_mode | 0o200)
        if log:
            log(f"building {product.name} in {source} (once; cached by content)")
        command = ["make", "-C", str(source / product.make_dir), *product.make_args, f"-j{os.cpu_count() or 1}"]
        done = subprocess.run(command, capture_output=True, text=True, env=dict(os.environ, **env))
        built = source / product.make_dir / product.built
        if done.returncode or not built.is_file():
            raise PortBuildError(f"{product.name} did not build from {tree}:\n{(done.stderr or done.stdout)[-3000:]}",
                                 hint=product.hint)
        temporary = home / (result.name + ".tmp")
        shutil.copy2(built, temporary)
        temporary.rename(result)
        shutil.rmtree(source)
    return result
