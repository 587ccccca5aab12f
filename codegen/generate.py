"""Render a validated board into the output tree: OUT/app/ (the board's files), OUT/native/ (C module), MANIFEST.json.

For `target: micropython` (the default):

    templates/micropython/NAME.j2  ->  OUT/app/NAME
    templates/native/NAME.j2       ->  OUT/native/NAME
    native_ext/*                   ->  OUT/native/*   (copied byte for byte: the C kernel is not a template)

For `target: circuitpython` (the CIRCUITPY drive's files; CircuitPython loads no native module):

    templates/circuitpython/NAME.j2      ->  OUT/app/NAME        (code.py, boot.py, lib/: CircuitPython's own)
    templates/micropython/NAME.j2        ->  OUT/app/lib/NAME    (the app's modules that run on both, rendered from
                                                                  the same templates: SHARED_WITH_CIRCUITPYTHON)

Rendering is pure (`render_tree`) and deterministic: same board content, byte-identical tree. A template sees the
board and `layout`, the kernels' declaration (codegen/kernel/layout.py: state fields, parameters, flags). While a
template renders, every board key it reads is recorded, so the manifest can say which keys produced which file.
`generate` writes the tree, and refuses to touch a folder it did not generate or files the user edited since. A
folder is deadreckon's when its MANIFEST.json carries deadreckon's seal (the SHA-256 of the rest of the manifest)
and names only paths under app/ and native/; nothing is written through a symbolic link or outside the folder.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Optional

import jinja2
from pydantic import BaseModel

from codegen import __version__
from codegen.board.loader import LoadedBoard
from codegen.errors import UserError
from codegen.font import FONT
from codegen.kernel.layout import LAYOUT
from codegen.paths import native_ext_dir, templates_dir
from codegen.safeio import read_bounded, regular_file_sha256, write_atomically

MANIFEST = "MANIFEST.json"
GENERATOR = "deadreckon"
SEAL = "seal"
UNFINISHED = "unfinished"  # a manifest written as a claim, before the files it lists
EARLIER = "was"  # in a claim's entry: the SHA-256s the file had before, deadreckon's (not yet rewritten)
# what safeio.write_atomically leaves of a file when the process dies before its rename: .NAME.XXXXXXXX.tmp
LEFTOVER = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp$")
MAX_MANIFEST_BYTES = 1024 * 1024  # a manifest lists a few dozen files: tens of KB
TEMPLATE_OUTPUTS = {"micropython": "app", "native": "native"}
# The MicroPython app's templates a CircuitPython app renders too (into app/lib/): everything but main.py, which
# CircuitPython names code.py. Their few lines that differ (imports: CircuitPython has no `machine`, no ticks_* in
# `time`, no `framebuf`) switch on board.target; the rest is the same text.
SHARED_WITH_CIRCUITPYTHON = ("app.py", "board_config.py", "buttons.py", "display.py", "dr_fallback.py", "logger.py",
                             "mpu6050.py", "nmea.py", "power.py")


def template_sources(target: str) -> list[tuple[str, str, Optional[tuple[str, ...]]]]:
    """(template folder, output folder, only these outputs or None for all) rendered for a target."""
    if target == "circuitpython":
        return [("circuitpython", "app", None), ("micropython", "app/lib", SHARED_WITH_CIRCUITPYTHON)]
    return [("micropython", "app", None), ("native", "native", None)]
COPIED_NATIVE_SKIP = {"__init__.py", "__pycache__", "tests"}


@dataclass(frozen=True)
class RenderedFile:
    content: bytes
    keys: tuple[str, ...]  # board keys (dotted) the file was produced from; empty for copied sources
    origin: str  # the template or source file it came from


@dataclass(frozen=True)
class GenerateResult:
    root: Path
    files: dict[str, RenderedFile]
    kept: list[str] = field(default_factory=list)  # edited files no longer generated, left in place


class _KeyRecorder:
    """Remembers the dotted path of every board model object handed to a template, and which ones were read."""

    def __init__(self, board: BaseModel):
        self.paths: dict[int, str] = {id(board): ""}
        self.keep_alive: list[Any] = [board]
        self.used: set[str] = set()

    def child(self, parent: Any, name: str, value: Any) -> Any:
        base = self.paths.get(id(parent))
        if base is None:
            return value
        path = f"{base}.{name}" if base else str(name)
        if isinstance(value, (BaseModel, dict, list, tuple)):
            self.paths[id(value)] = path
            self.keep_alive.append(value)
        self.used.add(path)
        return value

    def prune(self) -> tuple[str, ...]:
        """Keep only the deepest keys read (`imu.address` makes `imu` redundant)."""
        keys = sorted(self.used)
        return tuple(k for k in keys if not any(other.startswith(k + ".") for other in keys))


class _TrackingEnvironment(jinja2.Environment):
    recorder: _KeyRecorder | None = None

    def getattr(self, obj: Any, attribute: str) -> Any:
        value = super().getattr(obj, attribute)
        if self.recorder is not None and not callable(value):
            value = self.recorder.child(obj, attribute, value)
        elif self.recorder is not None and isinstance(obj, dict):
            base = self.recorder.paths.get(id(obj))
            if base:
                self.recorder.used.add(base)
        return value

    def getitem(self, obj: Any, argument: Any) -> Any:
        value = super().getitem(obj, argument)
        if self.recorder is not None:
            value = self.recorder.child(obj, str(argument), value)
        return value


def _environment() -> _TrackingEnvironment:
    env = _TrackingEnvironment(
        loader=jinja2.FileSystemLoader(str(templates_dir())),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
        autoescape=False,
    )
    env.filters["hex"] = lambda value, width=2: f"0x{int(value):0{width}X}"
    env.filters["cfloat"] = _c_float
    env.filters["pybytes_lines"] = _bytes_literal_lines
    return env


def _bytes_literal_lines(data: bytes, width: int) -> list[str]:
    """`data` as Python bytes literals of at most `width` characters each (lines of one parenthesised literal)."""
    lines, current = [], ""
    for byte in data:
        piece = f"\\x{byte:02x}"
        if current and len(current) + len(piece) + 3 > width:
            lines.append(f'b"{current}"')
            current = ""
        current += piece
    if current:
        lines.append(f'b"{current}"')
    return lines


def _c_float(value: float) -> str:
    """A float as a C float literal with its `f` suffix, exactly as repr() gives it."""
    text = repr(float(value))
    if "e" not in text and "." not in text:
        text += ".0"
    return f"{text}f"


def _banner(loaded: LoadedBoard, template: str):
    files = " <- ".join(path.name for path in loaded.files)

    def banner(prefix: str, suffix: str = "") -> str:
        lines = [
            f"Generated by deadreckon {__version__} from {files} (board {loaded.board.name}), template {template}.",
            f"Board content sha256 {loaded.content_sha256[:16]}. Do not edit: change the board YAML and regenerate.",
        ]
        return "\n".join(f"{prefix} {line}{suffix}".rstrip() for line in lines)

    return banner


def render_tree(loaded: LoadedBoard) -> dict[str, RenderedFile]:
    """Every output file (relative path -> content and provenance), in memory."""
    env = _environment()
    files: dict[str, RenderedFile] = {}
    for folder, out_folder, only in template_sources(loaded.board.target):
        base = templates_dir() / folder
        if not base.is_dir():
            continue
        for template_path in sorted(base.rglob("*.j2")):
            if only is not None and template_path.relative_to(base).as_posix()[:-3] not in only:
                continue
            name = template_path.relative_to(templates_dir()).as_posix()
            recorder = _KeyRecorder(loaded.board)
            env.recorder = recorder
            try:
                text = env.get_template(name).render(board=loaded.board, layout=LAYOUT, font=FONT,
                                                     banner=_banner(loaded, name))
            except jinja2.TemplateError as problem:
                line = getattr(problem, "lineno", None)
                raise UserError(
                    f"template {name}{f':{line}' if line else ''} failed to render: {problem}",
                    hint="this is a bug in deadreckon's templates, not in your board file",
                ) from None
            finally:
                env.recorder = None
            relative = f"{out_folder}/{template_path.relative_to(base).as_posix()[:-3]}"
            files[relative] = RenderedFile(text.encode("utf-8"), recorder.prune(), f"templates/{name}")
    if loaded.board.target == "circuitpython":
        return files
    native = native_ext_dir()
    for source in sorted(native.rglob("*")):
        relative_source = source.relative_to(native)
        if source.is_dir() or any(part in COPIED_NATIVE_SKIP or part.startswith(".") for part in relative_source.parts):
            continue
        relative = f"native/{relative_source.as_posix()}"
        if relative in files:
            raise UserError(f"{relative} comes both from a template and from native_ext/ (a deadreckon bug)")
        files[relative] = RenderedFile(source.read_bytes(), (), f"native_ext/{relative_source.as_posix()}")
    return files


def app_contents(files: dict[str, RenderedFile]) -> dict[str, bytes]:
    """The app folder's rendered files by their path on the board's filesystem (app/x.py -> x.py)."""
    prefix = TEMPLATE_OUTPUTS["micropython"] + "/"
    return {rel[len(prefix):]: rendered.content for rel, rendered in files.items() if rel.startswith(prefix)}


def render_template_text(loaded: LoadedBoard, source: str, name: str) -> str:
    """A template's text (say, an older revision's, for a benchmark) rendered as render_tree renders `name`."""
    env = _environment()
    return env.from_string(source).render(board=loaded.board, layout=LAYOUT, font=FONT, banner=_banner(loaded, name))


def manifest_for(loaded: LoadedBoard, files: dict[str, RenderedFile], root: Path) -> dict:
    """The manifest of a generated tree, sealed (see `seal`)."""
    body = {
        "generator": f"{GENERATOR} {__version__}",
        "board": loaded.board.name,
        "board_files": [path.name for path in loaded.files],
        # the board file as seen from the output folder, so `build` finds it from any working folder
        "board_path": Path(os.path.relpath(loaded.files[0].resolve(), root.resolve())).as_posix(),
        "board_sha256": loaded.content_sha256,
        "files": {
            relative: {
                "sha256": hashlib.sha256(rendered.content).hexdigest(),
                "from": rendered.origin,
                "keys": list(rendered.keys),
            }
            for relative, rendered in sorted(files.items())
        },
    }
    return seal(body)


def _seal_of(body: dict) -> str:
    canonical = json.dumps({k: v for k, v in body.items() if k != SEAL}, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def seal(body: dict) -> dict:
    """`body` with its seal: the SHA-256 of the rest of the manifest. A MANIFEST.json another tool (or a hand)
    wrote has none, or one that does not match, and marks a folder deadreckon did not make."""
    return {**body, SEAL: _seal_of(body)}


def is_sealed(document: dict) -> bool:
    """Whether `document` carries the seal `seal` gives it (and so was written by deadreckon, unchanged)."""
    return isinstance(document, dict) and document.get(SEAL) == _seal_of(document)


def _foreign(path: Path, why: str) -> UserError:
    return UserError(
        f"{path} was not written by deadreckon ({why}); refusing to touch the folder it is in",
        hint="generate into a new or empty folder with -o; if the folder is yours to replace, remove it first "
             "(--force does not override this)",
    )


def safe_relative(relative: object) -> Optional[PurePosixPath]:
    """A manifest path as deadreckon writes them (app/... or native/..., relative, no `..`), or None."""
    if not isinstance(relative, str) or not relative or "\\" in relative or "\0" in relative:
        return None
    path = PurePosixPath(relative)
    if path.is_absolute() or any(part in ("", ".", "..") for part in relative.split("/")):
        return None
    return path if path.parts[0] in TEMPLATE_OUTPUTS.values() and len(path.parts) > 1 else None


def read_manifest(root: Path, unfinished_too: bool = False) -> dict:
    """The sealed manifest of a folder deadreckon generated, or a UserError saying the folder is not one (no
    manifest, a link, not a regular file, too large, not JSON, no valid seal, a path that leaves the folder).
    A generate's claim (written before its files, see `generate`) is the manifest of an unfinished tree: refused
    unless `unfinished_too` (generate itself, which finishes the folder)."""
    path = root / MANIFEST
    try:
        status = path.lstat()
    except FileNotFoundError:
        raise UserError(
            f"{root} was not generated by deadreckon (no {MANIFEST})", hint="run `deadreckon generate -o FOLDER`"
        ) from None
    except OSError as problem:
        raise UserError(f"{path} is unreadable: {problem.strerror}") from None
    if stat.S_ISLNK(status.st_mode):
        raise _foreign(path, "it is a symbolic link")
    try:
        raw = read_bounded(path, str(path), MAX_MANIFEST_BYTES, what="MANIFEST.json")
        manifest = json.loads(raw.decode("utf-8"))
    except UserError as problem:
        raise _foreign(path, problem.message) from None
    except (ValueError, RecursionError) as problem:
        raise _foreign(path, f"not JSON: {str(problem)[:80]}") from None
    if not isinstance(manifest, dict) or not str(manifest.get("generator", "")).startswith(GENERATOR + " "):
        raise _foreign(path, "no generator field of deadreckon")
    if not is_sealed(manifest):
        raise _foreign(path, "its seal does not match its content" if SEAL in manifest else "it has no seal")
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(isinstance(entry, dict) for entry in files.values()):
        raise _foreign(path, "no list of files")
    unsafe = [relative for relative in files if safe_relative(relative) is None]
    if unsafe:
        raise _foreign(path, f"it names {unsafe[0]!r}, outside app/ and native/ of the folder")
    if manifest.get(UNFINISHED) and not unfinished_too:
        raise UserError(f"{root} is a tree whose `deadreckon generate` was interrupted before it finished",
                        hint=f"run the same `deadreckon generate ... -o {root}` again: it finishes the folder")
    return manifest


def _edited_files(root: Path, manifest: dict, files: dict[str, RenderedFile]) -> list[str]:
    """Files of the old manifest that are no longer what deadreckon wrote (edited, replaced by a link, ...): neither
    what the manifest says nor what this run writes there (which an interrupted run of it may have written)."""
    edited = []
    for relative, entry in manifest["files"].items():
        path = root / relative
        if not os.path.lexists(path):
            continue
        digest = regular_file_sha256(path)
        written = {entry.get("sha256"), *_earlier(entry)}  # a claim's file may still hold what it held before
        if digest not in written and (relative not in files
                                      or digest != hashlib.sha256(files[relative].content).hexdigest()):
            edited.append(relative)
    return edited


def _earlier(entry: dict) -> list[str]:
    """The SHA-256s a claim's entry says its file had before the interrupted run (see `generate`)."""
    earlier = entry.get(EARLIER)
    return [digest for digest in earlier if isinstance(digest, str)] if isinstance(earlier, list) else []


def _leftovers(root: Path, names: list[str]) -> list[Path]:
    """The temporary files an interrupted run left beside the files it writes (`names`, relative to root): regular
    files named .NAME.XXXXXXXX.tmp for one of those NAMEs in the same folder, never a link or anything else."""
    wanted: dict[Path, set[str]] = {}
    for relative in names:
        path = root / relative
        wanted.setdefault(path.parent, set()).add(path.name)
    found = []
    for folder, own in wanted.items():
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            match = LEFTOVER.match(entry.name)
            if match and match.group("name") in own and entry.is_file(follow_symlinks=False):
                found.append(Path(entry.path))
    return found


def _check_inside(root: Path, relative: str) -> Path:
    """root/relative, after checking no folder on the way is a symbolic link or a file (so a write cannot land
    outside root); the target itself may be missing or a regular file."""
    target = root / relative
    current = root
    for part in PurePosixPath(relative).parts[:-1]:
        current = current / part
        if current.is_symlink():
            raise UserError(
                f"{current} is a symbolic link (to {os.readlink(current)}); generate writes only inside {root}",
                hint="remove the link, or generate into a new folder with -o",
            )
        if current.exists() and not current.is_dir():
            raise UserError(f"{current} is a file where generate puts a folder", hint="move it away, or use -o")
    if os.path.lexists(target) and not stat.S_ISREG(target.lstat().st_mode):
        raise UserError(f"{target} is not a regular file (a link, a folder or a device) where generate puts one",
                        hint="move it away, or generate into a new folder with -o")
    return target


def generate(loaded: LoadedBoard, root: Path, force: bool = False) -> GenerateResult:
    """Write the tree for `loaded` into `root`; never touches anything outside it, never a file it did not write.

    `root` must be new, empty or a folder generated before (a sealed MANIFEST.json whose paths all stay inside).
    Generated files edited since are overwritten only with `force`; files no longer generated are removed only
    when unedited (edited ones are kept and listed in the result)."""
    from codegen.board.diagnostics import DiagnosticsError
    from codegen.deploy.capacity import fit_diagnostics

    files = render_tree(loaded)
    problems = fit_diagnostics(loaded, app_contents(files))
    if problems:
        raise DiagnosticsError(problems, loaded.lines_by_file)
    root = Path(root)
    if os.path.lexists(root) and not root.is_dir():
        raise UserError(f"{root} exists and is not a folder")
    old_files: dict[str, dict] = {}
    if root.exists() and not os.path.lexists(root / MANIFEST):
        # killed while writing its claim, a run leaves only the claim's temporary file: the folder is still empty
        foreign = [entry for entry in root.iterdir() if entry not in _leftovers(root, [MANIFEST])]
        if foreign:
            raise UserError(
                f"{root} is not empty and was not generated by deadreckon; refusing to write into it",
                hint="choose a new or empty folder with -o",
            )
    elif root.exists():
        old_files = read_manifest(root, unfinished_too=True)["files"]
    edited = _edited_files(root, {"files": old_files}, files)
    if edited and not force:
        raise UserError(
            f"{len(edited)} generated file(s) in {root} were edited since: {', '.join(edited[:5])}",
            hint="keep your edits elsewhere, or pass --force to overwrite them",
        )
    targets = {relative: _check_inside(root, relative) for relative in files}
    stale = [relative for relative in old_files if relative not in files]
    for relative in stale:
        _check_inside(root, relative)
    kept = [relative for relative in stale if relative in edited]
    # The claim first: a sealed manifest of every file this run writes or may remove, marked unfinished. Killed at
    # any point after it, the folder is recognisably this run's and the next generate finishes it; killed before
    # it, the folder is as it was (or empty but for the claim's own temporary file).
    claim = manifest_for(loaded, files, root)
    entries = {rel: old_files[rel] for rel in stale if rel not in kept}
    for rel, entry in claim["files"].items():
        old = old_files.get(rel)
        earlier = [old.get("sha256"), *_earlier(old)] if old is not None and rel not in edited else []
        entries[rel] = {**entry, EARLIER: [d for d in earlier if isinstance(d, str)]} if earlier else entry
    claim = seal({**claim, UNFINISHED: True, "files": entries})
    write_atomically(root / MANIFEST, (json.dumps(claim, indent=2, sort_keys=True) + "\n").encode("utf-8"))
    for leftover in _leftovers(root, [*files, *stale, MANIFEST]):
        leftover.unlink()
    for relative, rendered in files.items():
        write_atomically(targets[relative], rendered.content)
    for relative in stale:
        if relative not in kept and os.path.lexists(root / relative):
            (root / relative).unlink()
    manifest = json.dumps(manifest_for(loaded, files, root), indent=2, sort_keys=True) + "\n"
    write_atomically(root / MANIFEST, manifest.encode("utf-8"))
    return GenerateResult(root, files, kept)
