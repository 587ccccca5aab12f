"""The hostile-input suite's helpers (tests/test_hostile_*.py): the CLI run as a user runs it, in a subprocess
with a time bound, and the files around the output folder hashed before and after.

Every hostile case must end with exit status 2, an `error:` message and no traceback, within its time bound, and
leave everything outside the output folder as it was (`snapshot` records type, content hash, mode and link target of
every entry; FIFOs and devices are recorded, never opened; files over 16 MiB by size and modification time).
"""

from __future__ import annotations

import hashlib
import os
import stat
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Time bounds of one CLI run (a cold start of the CLI is about 2 s; the machine is shared by parallel jobs).
QUICK_BOUND_S = 30.0  # reading, validating, generating, refusing before any port is opened
PORT_BOUND_S = 90.0  # a conversation with a port that misbehaves (the longest wait is a 30 s REPL reply, x2)
LARGE_FILE_BYTES = 16 * 1024 * 1024  # larger files are compared by size, modification time and mode, not read


@dataclass
class Outcome:
    returncode: int
    stdout: str
    stderr: str
    seconds: float


def run_cli(*args: str, cwd: Path, timeout: float = QUICK_BOUND_S, env: dict | None = None) -> Outcome:
    """`deadreckon ARGS` in `cwd`; a run longer than `timeout` is killed and fails the test."""
    environment = dict(os.environ, PYTHONPATH=str(ROOT), **(env or {}))
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "codegen", *args], capture_output=True, text=True, cwd=cwd,
                            env=environment, timeout=timeout, stdin=subprocess.DEVNULL)
    return Outcome(result.returncode, result.stdout, result.stderr, time.monotonic() - started)


def assert_refused(outcome: Outcome, *phrases: str, bound: float = QUICK_BOUND_S) -> None:
    """Exit 2, a located-or-plain `error:` naming the problem (every phrase), no traceback, within `bound`."""
    shown = (f"exit {outcome.returncode} after {outcome.seconds:.1f} s\nstdout: {outcome.stdout}\n"
             f"stderr: {outcome.stderr}")
    assert outcome.returncode == 2, shown
    assert "Traceback" not in outcome.stdout + outcome.stderr, shown
    assert "error:" in outcome.stderr, shown
    for phrase in phrases:
        assert phrase in outcome.stderr, f"{phrase!r} not in the message\n{shown}"
    assert outcome.seconds < bound, shown


def snapshot(folder: Path, skip: tuple[Path, ...] = ()) -> dict[str, tuple]:
    """Every entry under `folder` (not following links, not entering `skip`): its kind and, for files, the
    SHA-256 and mode, for links the target."""
    found: dict[str, tuple] = {}
    skipped = {os.path.abspath(p) for p in skip}
    for top, folders, names in os.walk(folder, followlinks=False):
        folders[:] = [f for f in folders if os.path.abspath(os.path.join(top, f)) not in skipped]
        for name in folders + names:
            path = os.path.join(top, name)
            if os.path.abspath(path) in skipped:
                continue
            status = os.lstat(path)
            relative = os.path.relpath(path, folder)
            if stat.S_ISLNK(status.st_mode):
                found[relative] = ("link", os.readlink(path))
            elif stat.S_ISREG(status.st_mode) and status.st_size > LARGE_FILE_BYTES:  # (a sparse gigabyte)
                found[relative] = ("large file", status.st_size, status.st_mtime_ns, stat.S_IMODE(status.st_mode))
            elif stat.S_ISREG(status.st_mode):
                found[relative] = ("file", hashlib.sha256(Path(path).read_bytes()).hexdigest(),
                                   stat.S_IMODE(status.st_mode))
            elif stat.S_ISDIR(status.st_mode):
                found[relative] = ("dir", stat.S_IMODE(status.st_mode))
            else:
                found[relative] = ("special", stat.S_IFMT(status.st_mode))
    return found


def user_files(home: Path) -> None:
    """A few files of the user's beside the work (documents, a link, a nested folder) that must survive."""
    (home / "notes.txt").write_text("my notes\n")
    (home / "projects").mkdir()
    (home / "projects" / "main.py").write_text("print('my own app')\n")
    (home / "projects" / "data.bin").write_bytes(bytes(range(256)))
    (home / "link-to-notes").symlink_to("notes.txt")
