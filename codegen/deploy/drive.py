"""`deadreckon upload OUT --drive PATH`: the built CircuitPython app onto a board's CIRCUITPY drive, mounted by the
computer as a USB drive.

What it checks first (nothing is written before): PATH is a folder holding CircuitPython's boot_out.txt (written
by the firmware at every start: its release and board_id), the board_id is the one the tree was generated for, the
drive is writable (after the app's boot.py took it, it is read-only to the computer until the board starts with
the button held: the message says how), and there is room for what changes.

How it writes (each file on its own, whole or not at all): only files whose SHA-256 differs from the drive's
copy; each into a hidden temporary file beside its target (`.NAME.deadreckon-part`), flushed and fsync'ed, then
renamed over the target, and the folder fsync'ed. A drive pulled out, full or failing mid-way leaves every file
either as it was or as it is now, never half of one; the partial temporary file, if any, is removed then or by the
next upload. lib/ goes first and code.py last, because CircuitPython restarts code.py whenever the drive changes:
until the last file is in, the old code.py keeps running (or restarts into modules that are already new).

Files an earlier upload wrote and the tree no longer has are removed, and only those, and only while unchanged
since. The drive's word is never enough: anyone can write a file onto a USB drive. A file is removed only when
both records name it with the SHA-256 it still has: the drive's (`.deadreckon-upload.json`) and the tree's own
(OUT/build/UPLOADED.json: the app's file list this tree last uploaded), each sealed as generate's MANIFEST.json is;
and only when its path stays on the drive without passing through a link. Everything else on the drive (the logs,
the user's own files, settings.toml, a file that happens to have the hash a record names) is never touched.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Callable

from codegen.board.circuitpython import MIN_CIRCUITPYTHON
from codegen.errors import UserError
from codegen.safeio import read_bounded, regular_file_sha256, write_atomically

Progress = Callable[[str], None]

BOOT_OUT = "boot_out.txt"
RECORD = ".deadreckon-upload.json"
RECORD_GENERATOR = "deadreckon upload"
PART_SUFFIX = ".deadreckon-part"
MAX_BOOT_OUT_BYTES = 64 * 1024
MAX_RECORD_BYTES = 1024 * 1024
LAST = ("boot.py", "code.py")  # written after everything they import, code.py last


@dataclass
class DriveResult:
    sent: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    board_id: str = ""
    version: str = ""
    seconds: float = 0.0


@dataclass(frozen=True)
class BootOut:
    """What CircuitPython's boot_out.txt says about the board."""

    version: str  # "10.2.1"
    board_id: str  # "raspberry_pi_pico"


def read_boot_out(drive: Path) -> BootOut:
    """The release and board_id in DRIVE/boot_out.txt; a UserError when the folder is not a CIRCUITPY drive."""
    path = drive / BOOT_OUT
    if not os.path.lexists(path):
        raise UserError(
            f"{drive} has no {BOOT_OUT}: it is not a CircuitPython board's CIRCUITPY drive",
            hint="give the folder the board's drive is mounted at (Linux: /media/$USER/CIRCUITPY or "
                 "/run/media/$USER/CIRCUITPY; macOS: /Volumes/CIRCUITPY; Windows: the drive letter); CircuitPython "
                 "writes boot_out.txt there each time it starts",
        )
    try:
        text = read_bounded(path, str(path), MAX_BOOT_OUT_BYTES, what="boot_out.txt").decode("utf-8", "replace")
    except UserError as problem:
        raise UserError(f"{path}: {problem.message}", hint="is this a CIRCUITPY drive?") from None
    version = board_id = ""
    for line in text.splitlines():
        words = line.split()
        if line.startswith("Adafruit CircuitPython ") and len(words) > 2:
            version = words[2]
        elif line.startswith("Board ID:"):
            board_id = line[len("Board ID:"):].strip()
    if not version or not board_id:
        raise UserError(f"{path} does not say which CircuitPython and board this is (no release or no Board ID "
                        "line)", hint="reset the board so that CircuitPython writes it again")
    return BootOut(version, board_id)


def _release(version: str) -> tuple[int, ...]:
    numbers = []
    for part in version.split("."):
        digits = "".join(ch for ch in part if ch.isdigit())
        if not digits:
            break
        numbers.append(int(digits))
    return tuple(numbers)


def _order(paths: list[str]) -> list[str]:
    """lib/ and everything else first, then boot.py, then code.py."""
    return sorted(paths, key=lambda rel: (LAST.index(rel) + 1 if rel in LAST else 0, rel))


def _fsync_folder(folder: Path) -> None:
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # a folder that cannot be opened (Windows): the rename is what the drive keeps
    try:
        os.fsync(descriptor)
    except OSError:
        pass  # FAT through some drivers refuses fsync on a folder: the file's own fsync came first
    finally:
        os.close(descriptor)


def _part_name(target: Path) -> Path:
    return target.parent / f".{target.name}{PART_SUFFIX}"


def write_whole(target: Path, data: bytes) -> None:
    """`data` into `target` on the drive, whole or not at all: a hidden temporary file beside it, fsync'ed, renamed
    over it. On failure the temporary file is removed if the drive still lets us, and the OSError goes up."""
    part = _part_name(target)
    try:
        descriptor = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            view = memoryview(data)
            while view:
                written = os.write(descriptor, view)
                view = view[written:]
            os.fsync(descriptor)
        finally:
            os.close(descriptor)
        os.replace(part, target)
    except OSError:
        try:
            os.unlink(part)
        except OSError:
            pass
        raise
    _fsync_folder(target.parent)


def _check_inside(drive: Path, rel: str) -> Path:
    """drive/rel, refusing links and files where folders go (nothing is written outside the drive)."""
    current = drive
    for part in PurePosixPath(rel).parts[:-1]:
        current = current / part
        if current.is_symlink() or (current.exists() and not current.is_dir()):
            raise UserError(f"{current} is {'a link' if current.is_symlink() else 'a file'} where the app puts a "
                            "folder", hint="move it off the drive and upload again")
    target = drive / rel
    if target.is_symlink() or (target.exists() and not target.is_file()):
        raise UserError(f"{target} is not a regular file where the app puts one", hint="move it off the drive")
    return target


def read_upload_record(path: Path) -> dict[str, str]:
    """{path on the drive: SHA-256} of a sealed upload record at `path` (a regular file, not a link); {} for
    anything else: no record, a link, unreadable, not JSON, not deadreckon's, a seal that does not match."""
    from codegen.generate import is_sealed

    try:
        if not stat.S_ISREG(path.lstat().st_mode):
            return {}
        record = json.loads(read_bounded(path, str(path), MAX_RECORD_BYTES, what="upload record").decode())
    except (OSError, UserError, ValueError, RecursionError):
        return {}
    if not is_sealed(record) or record.get("generator") != RECORD_GENERATOR:
        return {}
    files = record.get("files")
    if not isinstance(files, dict):
        return {}
    return {rel: digest for rel, digest in files.items() if _drive_relative(rel) and isinstance(digest, str)}


def upload_record(files: dict[str, str]) -> bytes:
    """The sealed record of an upload of `files` ({path: SHA-256})."""
    from codegen.generate import seal

    return (json.dumps(seal({"generator": RECORD_GENERATOR, "files": files}), indent=1, sort_keys=True)
            + "\n").encode()


def _drive_relative(rel: object) -> bool:
    """Whether `rel` is a path as the app's files are named: relative, '/'-separated, no '.', '..' or empty part."""
    if not isinstance(rel, str) or not rel or "\\" in rel or "\0" in rel or rel.startswith("/"):
        return False
    return all(part not in ("", ".", "..") for part in rel.split("/"))


def _removable(drive: Path, rel: str, digest: str) -> bool:
    """Whether drive/rel is a regular file with SHA-256 `digest` reached through real folders only (no link on the
    way, nothing outside the drive)."""
    current = drive
    for part in PurePosixPath(rel).parts[:-1]:
        current = current / part
        try:
            if not stat.S_ISDIR(current.lstat().st_mode):
                return False
        except OSError:
            return False
    return regular_file_sha256(drive / rel) == digest  # None for a link, a folder, a device or nothing


def _drive_failed(drive: Path, rel: str, problem: OSError, done: list[str]) -> UserError:
    reason = os.strerror(problem.errno) if problem.errno else str(problem)
    so_far = f"{len(done)} file(s) were written whole before it" if done else "nothing was changed before it"
    if problem.errno == errno.EROFS or problem.errno == errno.EACCES:
        return UserError(
            f"the CIRCUITPY drive at {drive} is read-only ({reason}) while writing {rel}; {so_far}",
            hint="the app's boot.py gives the drive to the app: hold the button its boot.py names while the board "
                 "starts (or use CircuitPython's safe mode) and upload again",
        )
    if problem.errno == errno.ENOSPC:
        return UserError(f"the CIRCUITPY drive at {drive} is full while writing {rel}; {so_far}, {rel} is as it was",
                         hint="delete old logs from the drive and upload again")
    return UserError(
        f"writing {rel} to {drive} failed ({reason}): the drive may have gone away; {so_far}, and {rel} is as it "
        "was (each file is renamed into place whole)",
        hint="plug the board in again and run the same command: it sends only what differs",
    )


def upload_to_drive(app_dir: Path, drive: Path, board_id: str, tree_record: Path, force: bool = False,
                    progress: Progress = print) -> DriveResult:
    """Make DRIVE hold every file of APP_DIR (a built CircuitPython app); send only what differs. TREE_RECORD is
    the tree's own sealed record of its last upload (read, then rewritten): with the drive's, what may be removed."""
    started = time.monotonic()
    drive = Path(drive)
    if not drive.exists():
        raise UserError(f"no such folder: {drive}", hint="is the board plugged in and its CIRCUITPY drive mounted?")
    if not drive.is_dir():
        raise UserError(f"{drive} is not a folder: give the folder the CIRCUITPY drive is mounted at")
    boot = read_boot_out(drive)
    if boot.board_id != board_id:
        raise UserError(f"the drive at {drive} is a {boot.board_id} (its boot_out.txt), the app is for a {board_id}",
                        hint="plug in the board the app was generated for, or generate for this one "
                             f"(circuitpython.board: {boot.board_id})")
    if _release(boot.version) < MIN_CIRCUITPYTHON:
        raise UserError(f"the board runs CircuitPython {boot.version}; the app needs "
                        f"{'.'.join(map(str, MIN_CIRCUITPYTHON))} or newer",
                        hint="install a current CircuitPython on the board first")
    files = {p.relative_to(app_dir).as_posix(): p.read_bytes() for p in sorted(app_dir.rglob("*")) if p.is_file()}
    if not files:
        raise UserError(f"{app_dir} is empty: nothing to upload", hint="run `deadreckon build OUT` first")
    result = DriveResult(board_id=boot.board_id, version=boot.version)
    targets = {rel: _check_inside(drive, rel) for rel in files}
    wanted = {rel: hashlib.sha256(data).hexdigest() for rel, data in files.items()}
    on_drive = {rel: regular_file_sha256(target) for rel, target in targets.items()}
    changed = [rel for rel in files if force or on_drive[rel] != wanted[rel]]
    on_drive_record = read_upload_record(drive / RECORD)
    ours = read_upload_record(tree_record)
    stale = [rel for rel, digest in sorted(ours.items()) if rel not in files and on_drive_record.get(rel) == digest
             and _removable(drive, rel, digest)]
    need = sum(len(files[rel]) - (targets[rel].stat().st_size if on_drive[rel] else 0) for rel in changed)
    free = shutil.disk_usage(drive).free
    if need > free:
        raise UserError(f"the app needs {need} more bytes on the drive at {drive}, it has {free} free; nothing was "
                        "written", hint="delete old logs from the drive and upload again")
    for leftover in drive.rglob(f".*{PART_SUFFIX}"):  # an earlier upload that was cut off
        try:
            leftover.unlink()
        except OSError:
            pass
    progress(f"uploading to {drive}: CircuitPython {boot.version} on {boot.board_id}")
    for rel in _order(list(files)):
        if rel not in changed:
            result.unchanged.append(rel)
            progress(f"  unchanged {rel}")
            continue
        try:
            targets[rel].parent.mkdir(parents=True, exist_ok=True)
            write_whole(targets[rel], files[rel])
        except OSError as problem:
            raise _drive_failed(drive, rel, problem, result.sent) from None
        result.sent.append(rel)
        progress(f"  sent      {rel} ({len(files[rel])} bytes)")
    for rel in stale:
        try:
            (drive / rel).unlink()
        except OSError as problem:
            raise _drive_failed(drive, rel, problem, result.sent) from None
        result.removed.append(rel)
        progress(f"  removed   {rel} (no longer part of the app)")
    try:
        write_whole(drive / RECORD, upload_record(wanted))
    except OSError as problem:
        raise _drive_failed(drive, RECORD, problem, result.sent) from None
    write_atomically(tree_record, upload_record(wanted))
    result.seconds = time.monotonic() - started
    progress(f"uploaded {len(result.sent)} file(s), {len(result.unchanged)} unchanged, {len(result.removed)} removed, "
             f"in {result.seconds:.1f} s; CircuitPython restarts code.py by itself")
    return result


def upload_drive(out: Path, drive: Path, force: bool = False, progress: Progress = print) -> DriveResult:
    """Upload OUT/build/app (from `deadreckon build OUT`, a CircuitPython tree) to the CIRCUITPY drive at DRIVE."""
    from codegen.deploy.build import BUILD_DIR, load_tree
    from codegen.deploy.buildrecord import UPLOAD_RECORD, check_build_current

    tree = load_tree(Path(out))
    if tree.board.target != "circuitpython":
        raise UserError(f"{out} is a MicroPython app ({tree.board.name}): MicroPython boards have no CIRCUITPY drive",
                        hint=f"deadreckon upload {out} --port PORT (raw REPL), or deadreckon flash {out} --port PORT")
    app_dir = Path(out) / BUILD_DIR / "app"
    if not app_dir.is_dir():
        raise UserError(f"{app_dir} does not exist", hint=f"run `deadreckon build {out}` first")
    check_build_current(Path(out))
    return upload_to_drive(app_dir, Path(drive), tree.board.circuitpython.board, Path(out) / BUILD_DIR / UPLOAD_RECORD,
                           force=force, progress=progress)
