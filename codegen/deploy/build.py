"""`deadreckon build OUT`: the generated app compiled for the board, ready to flash or upload.

    OUT/app/*.py         (generated)  ->  OUT/build/app/*.mpy   mpy-cross for the board's arch and MicroPython
    OUT/native/Makefile  (generated)  ->  OUT/build/app/dr_native.mpy, where a compiler for the arch exists
                                          (codegen.natmod: compiler route, MicroPython source, checks)
    OUT/build/app/                    ->  OUT/build/fs.img      LittleFS image of the vfs partition (codegen.deploy.fsimage)

`main.py` and `boot.py` stay source: MicroPython only runs those two names as `.py`. Everything else under app/
that is Python becomes `.mpy`; other files are copied. Nothing is written outside OUT/build/.

A CircuitPython tree (`target: circuitpython`) is built differently (build_circuitpython). CircuitPython refuses
MicroPython's .mpy ("MicroPython .mpy file; use CircuitPython mpy-cross": its header starts 'C', not 'M'), so its
modules under lib/ are compiled by CircuitPython's own mpy-cross for the board's release (codegen/deploy/cpmpycross.py:
one the user gives, or built from a CircuitPython source tree); code.py and boot.py stay source. Without that
compiler they stay `.py`, each checked to compile (MicroPython's compiler, from which CircuitPython's comes), and
CircuitPython compiles them as it imports them (code.py imports the largest modules first, for the compiler's room).
Either way every module it imports must be in the app or built into the board's CircuitPython (a library the board
lacks would stop the app at boot). There is no native module (CircuitPython loads none) and no filesystem image (the
files go onto the CIRCUITPY drive: `deadreckon upload OUT --drive PATH`).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from codegen.board.model import Board
from codegen.deploy.buildrecord import prepare_build_folder, record_build, source_hashes
from codegen.errors import UserError
from codegen.tools import find_mpy_cross, mpy_format

BUILD_DIR = "build"
IMAGE_NAME = "fs.img"
KEEP_AS_SOURCE = ("main.py", "boot.py")  # MicroPython runs only these names from the filesystem root
KEEP_AS_SOURCE_CIRCUITPYTHON = ("code.py", "boot.py")  # CircuitPython runs only .py (or .txt) under these names
NATIVE_MODULE = "dr_native"

Progress = Callable[[str], None]


@dataclass(frozen=True)
class GeneratedTree:
    """What `deadreckon generate` wrote: the board it was made for and where its parts are."""

    root: Path
    board: Board
    app_dir: Path
    native_dir: Path

    @property
    def build_dir(self) -> Path:
        return self.root / BUILD_DIR


@dataclass
class BuildResult:
    tree: GeneratedTree
    app_dir: Path  # the files that go on the board's filesystem root
    image: Optional[Path]  # the filesystem image (None for CircuitPython: its files go onto the CIRCUITPY drive)
    files: list[str] = field(default_factory=list)  # relative paths under app_dir
    native: Optional[Path] = None
    native_note: str = ""


def load_tree(out: Path, board: Optional[Board] = None) -> GeneratedTree:
    """Read OUT/MANIFEST.json and load the board it names; `board` overrides that (tests, custom trees)."""
    out = Path(out)
    if not out.is_dir():
        raise UserError(f"{out} is not a folder", hint="run `deadreckon generate BOARD.yaml -o OUT` first")
    app_dir = out / "app"
    if not app_dir.is_dir():
        raise UserError(f"{out} has no app/ folder: not a generated tree", hint="run `deadreckon generate` into it")
    if board is None:
        board = _manifest_board(out)
    return GeneratedTree(root=out, board=board, app_dir=app_dir, native_dir=out / "native")


def _manifest_board(out: Path) -> Board:
    """The board the tree was generated from: its file (found beside OUT, in the working folder or among the bundled
    boards), checked against the manifest's board_sha256 so a board file edited since `generate` is not used."""
    from codegen.board.loader import load_board
    from codegen.generate import read_manifest
    from codegen.paths import board_configs_dir

    manifest_path = out / "MANIFEST.json"
    manifest = read_manifest(out)  # sealed by deadreckon, or a UserError
    board_file = manifest.get("board_path") or (manifest.get("board_files") or [None])[0]
    if not board_file:
        raise UserError(f"{manifest_path} names no board file", hint="regenerate the tree from its board YAML")
    path = Path(board_file)
    places = [path] if path.is_absolute() else [out / path, Path.cwd() / path, out.parent / path,
                                                 board_configs_dir() / path]
    expected = manifest.get("board_sha256")
    changed = None
    for candidate in dict.fromkeys(p.resolve() for p in places if p.is_file()):
        loaded = load_board(candidate)
        if expected is None or loaded.content_sha256 == expected:
            return loaded.board
        changed = changed or candidate
    if changed is not None:
        raise UserError(
            f"the board file {changed} changed since {out} was generated from it",
            hint=f"regenerate: `deadreckon generate {changed} -o {out}`",
        )
    raise UserError(
        f"cannot find the board file {board_file!r} that {manifest_path} names",
        hint="run the command from the folder holding the board YAML, or regenerate the tree",
    )


def compile_py(source: Path, target: Path, board: Board, relname: str) -> None:
    """Compile one .py to .mpy for the board's arch and MicroPython release; raise UserError with its message."""
    mpy_format(board.micropython.version)  # rejects releases mpy-cross cannot target
    target.parent.mkdir(parents=True, exist_ok=True)
    command = [find_mpy_cross(board.micropython.version), f"-march={board.mpy_arch}", "-s", relname,
               "-o", str(target), str(source)]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0 or not target.exists():
        message = (result.stderr or result.stdout).strip() or f"exit status {result.returncode}"
        raise UserError(f"mpy-cross failed on {relname}: {message}")


def build_native(tree: GeneratedTree, target_dir: Path, progress: Progress) -> tuple[Optional[Path], str]:
    """Build and check the natmod (codegen.natmod.build); without a compiler for the arch, say why the fallback is
    used. A module that builds but fails its checks stops the build (UserError): it would crash the board."""
    from codegen.natmod.build import NoRoute, build_module

    board = tree.board
    if not (tree.native_dir / "Makefile").is_file():
        return None, "no native/Makefile in the tree: the app will use the pure-Python fallback"
    try:
        built = build_module(tree.native_dir, tree.build_dir / "native", board.mpy_arch, board.micropython.version,
                             progress)
    except NoRoute as reason:
        return None, f"{reason}: the app will use the pure-Python fallback instead of the native module"
    target = target_dir / built.module.name
    shutil.copy2(built.module, target)
    return target, (f"native module {target.name} ({target.stat().st_size} bytes) built for {board.mpy_arch} by the "
                    f"{built.route.name}\n  verifier passed: {built.checks}")


def build(out: Path, board: Optional[Board] = None, progress: Progress = print, image: bool = True) -> BuildResult:
    """Compile OUT/app into OUT/build/app and make OUT/build/fs.img; return what was built."""
    from codegen.deploy.fsimage import make_image

    tree = load_tree(out, board)
    board = tree.board
    if board.target == "circuitpython":
        return build_circuitpython(tree, progress)
    built_from, target_dir, sources = _start_app_build(tree)
    progress(
        f"building {len(sources)} app files for {board.name} "
        f"(MicroPython {board.micropython.version}, {board.mpy_arch}, .mpy {mpy_format(board.micropython.version)})"
    )
    result = BuildResult(tree=tree, app_dir=target_dir, image=tree.build_dir / IMAGE_NAME)
    for index, source in enumerate(sources, 1):
        rel = source.relative_to(tree.app_dir).as_posix()
        if source.suffix == ".py" and rel not in KEEP_AS_SOURCE:
            out_rel = rel[:-3] + ".mpy"
            compile_py(source, target_dir / out_rel, board, rel)
            action = "mpy-cross"
        else:
            out_rel = rel
            (target_dir / out_rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target_dir / out_rel)
            action = "copy"
        result.files.append(out_rel)
        progress(f"  [{index}/{len(sources)}] {action:9s} {rel} -> {out_rel}")
    check_names(result.files)
    result.native, result.native_note = build_native(tree, target_dir, progress)
    if result.native is not None:
        result.files.append(result.native.name)
    progress(f"  {result.native_note}")
    if image:
        fs = board.micropython.filesystem
        make_image(target_dir, result.image, size=fs.size, block_size=fs.block_size)
        progress(f"  filesystem image {result.image} ({fs.size // 1024} KiB LittleFS v2 for the vfs at {fs.offset:#x})")
    record_build(tree.root, built_from)
    return result


def _start_app_build(tree: GeneratedTree) -> tuple[dict[str, str], Path, list[Path]]:
    """The start of every app build, MicroPython's and CircuitPython's: OUT/build checked as ours, OUT/app's hashes
    taken before anything is written (what the build record will say it was built from), OUT/build/app emptied.
    Returns those hashes, the app folder and OUT/app's files to build."""
    prepare_build_folder(tree.build_dir)
    built_from = source_hashes(tree.root)
    target_dir = tree.build_dir / "app"
    if target_dir.exists():
        shutil.rmtree(target_dir)
    target_dir.mkdir(parents=True)
    sources = sorted(p for p in tree.app_dir.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    return built_from, target_dir, sources


_SAFE_NAME = re.compile(r"^[A-Za-z0-9_.\-/]+$")


def check_names(paths: list[str]) -> None:
    """Reject file names a board's filesystem or the raw REPL would mangle."""
    for rel in paths:
        if not _SAFE_NAME.match(rel):
            raise UserError(f"app file name {rel!r} has characters the device tools do not handle")


def build_circuitpython(tree: GeneratedTree, progress: Progress = print) -> BuildResult:
    """Compile a CircuitPython tree's modules with CircuitPython's mpy-cross for the board's release (code.py and
    boot.py stay source: CircuitPython runs only those names) into OUT/build/app, as the CIRCUITPY drive takes them;
    without that compiler, check them and ship .py."""
    from codegen.deploy import cpmpycross
    from codegen.deploy.cpimports import check_imports

    board = tree.board
    version = board.circuitpython.version
    built_from, target_dir, sources = _start_app_build(tree)
    mpy_cross, where = cpmpycross.find(version, progress)
    how = f".mpy by CircuitPython's mpy-cross ({where})" if mpy_cross else ".py as CircuitPython runs them"
    progress(f"building {len(sources)} app files for {board.name} (CircuitPython {version} "
             f"on {board.circuitpython.board}): {how}")
    if mpy_cross is None:
        progress(f"  {where}; CircuitPython compiles each .py at import, in the app's heap")
    result = BuildResult(tree=tree, app_dir=target_dir, image=None)
    check_names([source.relative_to(tree.app_dir).as_posix() for source in sources])
    for source in sources:
        rel = source.relative_to(tree.app_dir).as_posix()
        (target_dir / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source, target_dir / rel)
    found = check_imports(target_dir, board)  # on the sources, before any becomes bytecode
    for index, source in enumerate(sources, 1):
        rel = source.relative_to(tree.app_dir).as_posix()
        out_rel = rel
        if source.suffix != ".py":
            action = "copy"
        elif mpy_cross is None or rel in KEEP_AS_SOURCE_CIRCUITPYTHON:
            check_compiles(source, rel, tree.build_dir)
            action = "checked"
        else:
            out_rel = rel[:-3] + ".mpy"
            cpmpycross.compile_module(mpy_cross, source, target_dir / out_rel, rel)
            (target_dir / rel).unlink()
            action = "mpy-cross"
        result.files.append(out_rel)
        progress(f"  [{index}/{len(sources)}] {action:9s} {rel}" + (f" -> {out_rel}" if out_rel != rel else ""))
    progress(f"  imports: {', '.join(sorted(found.builtin))} built into CircuitPython on {board.circuitpython.board}; "
             f"{len(found.local)} modules of the app")
    result.native_note = ("no native module: CircuitPython loads none, the app runs the pure-Python kernel "
                          "(lib/dr_fallback.py)")
    progress(f"  {result.native_note}")
    progress(f"  next: deadreckon upload {tree.root} --drive PATH-OF-CIRCUITPY")
    record_build(tree.root, built_from)
    return result


def check_compiles(source: Path, rel: str, scratch: Path) -> None:
    """A syntax check of one module with MicroPython's compiler (CircuitPython's is the same parser and compiler,
    with the same limits); the .mpy it writes is thrown away."""
    target = scratch / "check.mpy"
    command = [find_mpy_cross("1.28.0"), "-o", str(target), "-s", rel, str(source)]
    done = subprocess.run(command, capture_output=True, text=True)
    if target.exists():
        target.unlink()
    if done.returncode != 0:
        message = (done.stderr or done.stdout).strip() or f"exit status {done.returncode}"
        raise UserError(f"{rel} does not compile: {message}", hint="this is a bug in deadreckon's templates")
