"""`deadreckon pull --port P -o DIR`: the device's logs (/logs/dr*.bin, docs/log-format.md) copied to the computer
over the raw REPL, each checked against a SHA-256 the board computes itself.

- The board lists its logs with their size and SHA-256 (hashlib where the firmware has it; without it only the size
  can be checked, and said so).
- A file arrives in DIR/NAME.part, chunk by chunk (base64 over the REPL), each chunk written and flushed before
  the next is asked for; it becomes DIR/NAME only once its SHA-256 matches the board's.
- After a dropped link or a board reset, the port is opened again and the copy resumes at the end of the .part,
  once the board's hash of that many bytes matches the .part's (else the .part starts over: it is only ours).
- A local DIR/NAME that differs from the board's file is never overwritten: that file is skipped and named at the
  end (exit status 2). One that is the same is left alone.
- `--delete` removes a log from the board only after its local copy was verified by SHA-256 (never on a board that
  cannot hash).
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from codegen.deploy.ports import close_quietly, open_port
from codegen.deploy.upload import RawRepl, ReplError
from codegen.deploy.watchdog import hold_watchdog
from codegen.errors import UserError

Progress = Callable[[str], None]

CHUNK = 3072  # file bytes per REPL command (4 KiB of base64): small enough for a board's heap
ATTEMPTS = 8  # link drops or resets survived per pull before giving up
RETRY_PAUSE_S = 0.5
LOG_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")  # what the board may name a log (no folders, no "..")
NO_HASH = "?"

_HELPERS = """
import os, sys, binascii
try:
    import hashlib
except ImportError:
    hashlib = None
def _dr_hash(p, n):
    if hashlib is None:
        return '?'
    h = hashlib.sha256()
    b = bytearray(1024)
    f = open(p, 'rb')
    while n > 0:
        k = f.readinto(b)
        if not k:
            break
        k = min(k, n)
        h.update(memoryview(b)[:k])
        n -= k
    f.close()
    return binascii.hexlify(h.digest()).decode()
def _dr_list(d):
    try:
        names = sorted(os.listdir(d))
    except OSError:
        print('NOFOLDER')
        return
    for n in names:
        p = d + '/' + n
        st = os.stat(p)
        if st[0] & 0x4000 == 0:
            print('F', n, st[6], _dr_hash(p, st[6]))
_dr_f = None
def _dr_read(p, o, n):
    global _dr_f
    if _dr_f is None or _dr_f[0] != p:
        if _dr_f is not None:
            _dr_f[1].close()
        _dr_f = (p, open(p, 'rb'))
    _dr_f[1].seek(o)
    print(binascii.b2a_base64(_dr_f[1].read(n)).decode().strip())
def _dr_remove(p):
    global _dr_f
    if _dr_f is not None:
        _dr_f[1].close()
        _dr_f = None
    os.remove(p)
"""


@dataclass
class BoardFile:
    name: str
    size: int
    sha256: str  # NO_HASH where the board has no hashlib


@dataclass
class PullResult:
    copied: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    conflicts: list[str] = field(default_factory=list)  # local files that differ, left as they are
    deleted: list[str] = field(default_factory=list)
    unverified: list[str] = field(default_factory=list)  # copied, but the board could not hash them
    reconnects: int = 0
    bytes_read: int = 0
    posted: dict[str, Path] = field(default_factory=dict)


def file_sha256(path: Path, limit: Optional[int] = None) -> str:
    digest = hashlib.sha256()
    left = limit
    with open(path, "rb") as f:
        while left is None or left > 0:
            block = f.read(65536 if left is None else min(65536, left))
            if not block:
                break
            digest.update(block)
            if left is not None:
                left -= len(block)
    return digest.hexdigest()


class _Session:
    """One raw-REPL session on the board: opened (app interrupted, helpers defined) on demand, closed on a drop."""

    def __init__(self, port: str, progress: Progress, use_raw_paste: bool):
        self.port = port
        self.progress = progress
        self.use_raw_paste = use_raw_paste
        self.handle = None
        self.repl: Optional[RawRepl] = None
        self.opened = 0

    def get(self) -> RawRepl:
        if self.repl is None:
            self.handle = open_port(self.port)
            repl = RawRepl(self.handle, use_raw_paste=self.use_raw_paste,
                           paced=not self.port.startswith("socket://"))
            repl.enter()
            hold_watchdog(repl)  # the app's watchdog fed from a timer while the logs come over
            repl.exec(_HELPERS, timeout=10.0)
            self.repl = repl
            self.opened += 1
        return self.repl

    def drop(self) -> None:
        if self.handle is not None:
            close_quietly(self.handle)
        self.handle = None
        self.repl = None

    def run(self, code: str, timeout: float = 30.0) -> str:
        return self.get().exec(code, timeout=timeout).decode("utf-8", "replace")

    def leave(self) -> None:
        """Soft-reset into the app again (the board runs main.py), then close."""
        if self.repl is not None:
            try:
                self.repl.soft_reset()
            except Exception:  # noqa: BLE001 - the copy is done; a board that went away now loses nothing
                pass
        self.drop()


def _list(session: _Session, folder: str) -> list[BoardFile]:
    out = session.run(f"_dr_list({folder!r})", timeout=120.0)
    if out.strip() == "NOFOLDER":
        raise UserError(f"the board has no {folder} folder: no logs yet",
                        hint="the app writes its logs there while it runs (logging.directory in the board YAML)")
    found = []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[0] == "F" and parts[2].isdigit():
            found.append(BoardFile(parts[1], int(parts[2]), parts[3]))
    return found


def pull(port: str, output: Path, folder: str = "/logs", pattern: str = "*.bin", delete: bool = False,
         use_raw_paste: bool = True, progress: Progress = print, attempts: int = ATTEMPTS) -> PullResult:
    """Copy the board's logs in `folder` matching `pattern` into `output` (see the module's docstring)."""
    import fnmatch

    import serial

    output = Path(output)
    if output.exists() and not output.is_dir():
        raise UserError(f"{output} exists and is not a folder", hint="choose a folder with -o")
    output.mkdir(parents=True, exist_ok=True)
    folder = "/" + folder.strip("/")
    result = PullResult()
    session = _Session(port, progress, use_raw_paste)
    failures = 0
    done: set[str] = set()
    try:
        while True:
            try:
                files = [f for f in _list(session, folder) if fnmatch.fnmatch(f.name, pattern)]
                for board_file in files:
                    if board_file.name in done:
                        continue
                    if not LOG_NAME.match(board_file.name) or board_file.name.endswith(".part"):
                        progress(f"  skipped {board_file.name!r}: not a log name")
                        done.add(board_file.name)
                        continue
                    _pull_one(session, folder, board_file, output, result, progress)
                    done.add(board_file.name)
                if delete:
                    _delete_verified(session, folder, files, output, result, progress)
                break
            except (ReplError, UserError, serial.SerialException, OSError) as exc:
                if isinstance(exc, UserError) and (session.opened == 0 or session.repl is not None):
                    raise  # the port cannot be opened at all, or the board's answer is final (no log folder)
                if isinstance(exc, OSError) and not isinstance(exc, serial.SerialException) and exc.filename:
                    raise  # our own disk said no: the CLI names the file
                if session.opened == 0:
                    text = str(exc).splitlines()[-1] if str(exc) else type(exc).__name__
                    raise UserError(f"pull from {port} failed: {text}",
                                    hint="is MicroPython running on the board (not its bootloader, not another "
                                         "program holding the port)? Try again after pressing RESET") from None
                session.drop()
                failures += 1
                if failures > attempts:
                    raise UserError(f"the board on {port} kept dropping the link ({failures} times): {exc}",
                                    hint="check the cable and run the same command again: it resumes where it "
                                         "stopped") from None
                result.reconnects += 1
                progress(f"  link lost ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
                         "reconnecting to resume")
                time.sleep(RETRY_PAUSE_S)
    finally:
        session.leave()
    progress(f"pulled {len(result.copied)} log(s), {len(result.unchanged)} already here"
             + (f", {len(result.deleted)} deleted from the board" if delete else "")
             + (f", {result.reconnects} reconnect(s)" if result.reconnects else ""))
    if result.unverified:
        progress(f"  the board has no hashlib: {', '.join(result.unverified)} checked by size only")
    if result.conflicts:
        raise UserError(
            f"{len(result.conflicts)} log(s) not copied: a different file of the same name is already in {output}: "
            + ", ".join(result.conflicts),
            hint="move those files away (or pull into another folder with -o) and pull again; nothing was "
                 "overwritten" + (" or deleted" if delete else ""))
    return result


def _pull_one(session: _Session, folder: str, board_file: BoardFile, output: Path, result: PullResult,
              progress: Progress) -> None:
    target = output / board_file.name
    part = output / (board_file.name + ".part")
    if target.exists():
        same = (target.stat().st_size == board_file.size and
                (board_file.sha256 == NO_HASH or file_sha256(target) == board_file.sha256))
        if same:
            result.unchanged.append(board_file.name)
            progress(f"  unchanged {board_file.name}")
        else:
            result.conflicts.append(board_file.name)
            progress(f"  KEPT      {target}: it differs from the board's {board_file.name}")
        return
    path = f"{folder}/{board_file.name}"
    offset = part.stat().st_size if part.exists() else 0
    if offset > board_file.size:
        offset = 0
    if offset:
        theirs = session.run(f"print(_dr_hash({path!r}, {offset}))").strip()
        if theirs != NO_HASH and theirs != file_sha256(part, offset):
            offset = 0  # the board's file is not the one this .part began: start over
        elif offset:
            progress(f"  resuming {board_file.name} at {offset} of {board_file.size} bytes")
    with open(part, "r+b" if offset else "wb") as f:
        f.truncate(offset)
        f.seek(offset)
        while offset < board_file.size:
            want = min(CHUNK, board_file.size - offset)
            text = session.run(f"_dr_read({path!r}, {offset}, {want})")
            try:
                data = base64.b64decode(text.strip(), validate=True)
            except ValueError:
                raise ReplError(f"a garbled chunk of {board_file.name} at {offset}") from None
            if len(data) != want:
                raise ReplError(f"{board_file.name}: asked for {want} bytes at {offset}, got {len(data)}")
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
            offset += len(data)
            result.bytes_read += len(data)
    if board_file.sha256 == NO_HASH:
        result.unverified.append(board_file.name)
    elif file_sha256(part) != board_file.sha256:
        part.unlink()
        raise ReplError(f"{board_file.name}: the copy's SHA-256 differs from the board's; copying it again")
    os.replace(part, target)
    result.copied.append(board_file.name)
    progress(f"  copied    {board_file.name} ({board_file.size} bytes)")


def _delete_verified(session: _Session, folder: str, files: list[BoardFile], output: Path, result: PullResult,
                     progress: Progress) -> None:
    """Remove from the board each log whose local copy has the board's SHA-256 (hashed again, on both sides)."""
    verified = []
    for board_file in files:
        target = output / board_file.name
        if board_file.name in result.conflicts or not target.is_file() or board_file.sha256 == NO_HASH:
            continue
        if board_file.name in result.deleted:
            continue
        if file_sha256(target) == board_file.sha256 == session.run(
                f"print(_dr_hash({folder + '/' + board_file.name!r}, {board_file.size + 1}))").strip():
            verified.append(board_file.name)
    for name in verified:
        session.run(f"_dr_remove({folder + '/' + name!r})")
        result.deleted.append(name)
        progress(f"  deleted   {folder}/{name} from the board")
    skipped = [f.name for f in files if f.sha256 == NO_HASH]
    if skipped:
        progress(f"  not deleted (the board cannot hash them, so the copies are unverified): {', '.join(skipped)}")


def post_pulled(output: Path, names: list[str], progress: Progress = print) -> dict[str, Path]:
    """`deadreckon post` on each pulled log, into OUTPUT/NAME-post/; a log post refuses is said, not fatal."""
    from codegen.post import run_post
    from codegen.post.cli import Progress as PostProgress

    done = {}
    for name in names:
        log = output / name
        folder = output / (Path(name).stem + "-post")
        try:
            run_post(log, folder, progress=PostProgress())
        except UserError as exc:
            progress(f"  post {name}: {exc.message}")
            continue
        done[name] = folder
        progress(f"  post {name} -> {folder}")
    return done
