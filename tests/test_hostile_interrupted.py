"""`deadreckon generate` killed (SIGKILL: no handler runs) at every kind of point of its work, then run again: the
second run finishes the folder, byte for byte the tree an uninterrupted run writes, with no temporary file left;
a `build` of the unfinished folder is refused, naming the interruption.

The kill points are the file system calls generate makes (making a folder, creating a temporary file, setting its
mode, renaming it into place, removing a file): the k-th such call kills the process, for k spread over the whole
run. Each run is a fork of this process calling the CLI's `main` (the imports already done, so a run costs a
fraction of a second); the kill is the kernel's, as a power cut or an OOM kill would be.
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
from pathlib import Path

import pytest

import codegen.deploy.build  # noqa: F401  (imported once here, not in every forked run)
import codegen.deploy.capacity  # noqa: F401
import codegen.generate  # noqa: F401
from codegen.board.loader import load_board
from codegen.cli import build_parser, main
from hostilekit import snapshot, user_files

KILLABLE = (("os", "replace"), ("os", "unlink"), ("os", "mkdir"), ("os", "chmod"), ("tempfile", "mkstemp"))
MODULES = {"os": os, "tempfile": tempfile}


def _in_fork(argv: list[str], cwd: Path, kill_at: int | None = None) -> tuple[int | None, int]:
    """Run `deadreckon ARGV` in a child; with `kill_at`, the child SIGKILLs itself at its kill_at-th file system
    call. Returns (exit status or None when killed, file system calls made)."""
    reader, writer = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        os.close(reader)
        calls = [0]

        def counted(original):
            def call(*args, **kwargs):
                calls[0] += 1
                if calls[0] == kill_at:
                    os.kill(os.getpid(), signal.SIGKILL)
                return original(*args, **kwargs)
            return call

        status = 70
        try:
            os.chdir(cwd)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            for module, name in KILLABLE:
                setattr(MODULES[module], name, counted(getattr(MODULES[module], name)))
            status = main(argv)
        finally:
            os.write(writer, str(calls[0]).encode())
            os._exit(status if isinstance(status, int) else 70)
    os.close(writer)
    with os.fdopen(reader) as pipe:
        made = pipe.read()
    _, wait_status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(wait_status):
        assert os.WTERMSIG(wait_status) == signal.SIGKILL
        return None, 0
    return os.WEXITSTATUS(wait_status), int(made or 0)


BOARDS = ("ttgo-tbeam-v1.1", "pico-gy521")


@pytest.fixture
def reference(tmp_path):
    """Uninterrupted trees of the two boards (generated beside the folder the test kills generate in, so the
    manifest's board path reads the same), and how many file system calls a run makes."""
    home = tmp_path / "home"
    home.mkdir()
    codegen.generate.render_tree(load_board(BOARDS[0]))  # what every run imports: jinja2, the templates' modules,
    build_parser()  # every command's modules
    trees, calls = {}, {}
    for board in BOARDS:
        status, calls[board] = _in_fork(["generate", board, "-o", f"reference-{board}"], home)
        assert status == 0
        trees[board] = snapshot(home / f"reference-{board}")
    return home, trees, calls


def _points(total: int, count: int) -> list[int]:
    """`count` kill points spread over 1..total, the first and last three always among them."""
    spread = {1 + round(i * (total - 1) / (count - 1)) for i in range(count)}
    return sorted(spread | {1, 2, 3, total - 2, total - 1, total})


def _check_finished(home: Path, out: Path, expected: dict, board: str) -> None:
    status, _ = _in_fork(["generate", board, "-o", out.name], home)
    assert status == 0, f"the run after the kill exited {status}"
    assert snapshot(out) == expected


@pytest.mark.parametrize("count", [20])
def test_a_new_folder_killed_anywhere_is_finished_by_the_next_run(reference, count):
    home, trees, calls = reference
    user_files(home)
    around = snapshot(home)
    out = home / "out"
    points = _points(calls["ttgo-tbeam-v1.1"], count)
    assert len(points) >= 20
    for point in points:
        if out.exists():
            shutil.rmtree(out)
        status, _ = _in_fork(["generate", "ttgo-tbeam-v1.1", "-o", out.name], home, kill_at=point)
        assert status is None, f"kill point {point} was never reached"
        if (out / "MANIFEST.json").exists() and '"unfinished": true' in (out / "MANIFEST.json").read_text():
            assert _in_fork(["build", out.name], home)[0] == 2, f"build ran on an unfinished tree (point {point})"
        _check_finished(home, out, trees["ttgo-tbeam-v1.1"], "ttgo-tbeam-v1.1")
        assert {k: v for k, v in snapshot(home).items() if not k.startswith(out.name)} == around


def test_a_regenerate_killed_anywhere_is_finished_by_the_next_run(reference):
    """The folder holds one board's tree; generating another board's over it is killed, then run again."""
    home, trees, calls = reference
    out = home / "out"
    for point in _points(calls["pico-gy521"], 12):
        if out.exists():
            shutil.rmtree(out)
        assert _in_fork(["generate", "ttgo-tbeam-v1.1", "-o", out.name], home)[0] == 0
        status, _ = _in_fork(["generate", "pico-gy521", "-o", out.name], home, kill_at=point)
        assert status is None, f"kill point {point} was never reached"
        _check_finished(home, out, trees["pico-gy521"], "pico-gy521")
