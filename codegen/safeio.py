"""Reading and writing files a hostile or mistaken user may have put in the way.

    read_bounded(path, ...)      the bytes of a regular file of at most `limit` bytes; a folder, a FIFO, a device
                                 (/dev/zero) or a larger file is refused from its status, before a byte is read, and
                                 a FIFO is opened without waiting for a writer
    write_atomically(path, ...)  a new file renamed over `path`: never written through a link or into a file that
                                 shares its data with another name (a hard link), never seen half-written
    regular_file_sha256(path)    the SHA-256 of a regular file read in chunks; None for a link, a folder, a FIFO, a
                                 device, or nothing there
"""

from __future__ import annotations

import errno
import hashlib
import os
import stat
import tempfile
from pathlib import Path
from typing import Optional

from codegen.errors import Location, UserError

FILE_MODE = 0o644


def read_bounded(path: Path, name: str, limit: int, what: str, typical: str = "a few KB") -> bytes:
    """The bytes of the regular file at `path` (named `name` in messages), or a UserError."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise UserError(f"no such file: {name}") from None
    except IsADirectoryError:
        raise UserError(f"{name} is a folder, not a {what} file") from None
    except OSError as error:
        raise UserError(f"cannot read {name}: {error.strerror}") from None
    chunks: list[bytes] = []
    try:
        status = os.fstat(descriptor)
        if stat.S_ISDIR(status.st_mode):
            raise UserError(f"{name} is a folder, not a {what} file")
        if not stat.S_ISREG(status.st_mode):
            kind = "a FIFO" if stat.S_ISFIFO(status.st_mode) else (
                "a device" if stat.S_ISCHR(status.st_mode) or stat.S_ISBLK(status.st_mode) else "a socket")
            raise UserError(f"{name} is {kind}, not a regular file", hint=f"a {what} is a file")
        too_large = f"a {what} is {typical} (limit {limit // 1024} KB)"
        if status.st_size > limit:
            raise UserError(f"file is {status.st_size / 1e6:.1f} MB; {too_large}", location=Location(name, 1, 1),
                            hint="is this the right file?")
        os.set_blocking(descriptor, True)
        total = 0
        while total <= limit:  # the file may grow while it is read: never take more than the limit
            chunk = os.read(descriptor, limit + 1 - total)
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as error:
        raise UserError(f"cannot read {name}: {error.strerror}") from None
    finally:
        os.close(descriptor)
    raw = b"".join(chunks)
    if len(raw) > limit:
        raise UserError(f"{name} grew beyond {limit // 1024} KB while it was read; {too_large}",
                        location=Location(name, 1, 1))
    return raw


def write_failed(target: Path, error: OSError) -> UserError:
    """The UserError for a write to `target` the file system refused (full, read-only, gone), naming the file;
    the caller has left `target` as it was (each file is renamed into place whole)."""
    reason = error.strerror or str(error)
    if error.errno == errno.ENOSPC or error.errno == errno.EDQUOT:
        hint = f"free some space on the disk holding {target.parent} and run the same command again"
    elif error.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        hint = f"choose a folder you may write to, or make {target.parent} writable"
    else:
        hint = "check the disk, then run the same command again"
    return UserError(f"writing {target} failed: {reason}; it is as it was before", hint=hint)


def write_atomically(target: Path, content: bytes) -> None:
    """Write `content` to a new temporary file beside `target` (created exclusively, so never through a link),
    then rename it over `target`: a reader sees the old or the new file, never half of one, and a link or a hard
    link at `target` is replaced, not written through. A refused write is a UserError naming `target`."""
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        descriptor, temporary = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    except OSError as error:
        raise write_failed(target, error) from None
    try:
        with os.fdopen(descriptor, "wb") as handle:
            handle.write(content)
        os.chmod(temporary, FILE_MODE)
        os.replace(temporary, target)
    except BaseException as error:
        if os.path.lexists(temporary):
            os.unlink(temporary)
        if isinstance(error, OSError):
            raise write_failed(target, error) from None
        raise


def regular_file_sha256(path: Path) -> Optional[str]:
    """SHA-256 of a regular file read in chunks; None for anything else (a link, a folder, a FIFO, a device) or
    when it cannot be read."""
    try:
        if not stat.S_ISREG(path.lstat().st_mode):
            return None
        digest = hashlib.sha256()
        with open(path, "rb") as handle:
            for chunk in iter(lambda: handle.read(1 << 20), b""):
                digest.update(chunk)
        return digest.hexdigest()
    except OSError:
        return None
