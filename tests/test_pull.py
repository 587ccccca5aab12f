"""`deadreckon pull`: logs off a board running MicroPython (the raw-REPL peer, tests/peers/repl_bridge.mjs), each
checked by a SHA-256 the board computes; through a link that drops and a board that resets mid-copy."""

from __future__ import annotations

import os

import pytest

from codegen.deploy.pull import pull
from codegen.errors import UserError
from conftest import require
from peers.flaky_link import FlakyLink
from peers.repl_peer import ReplPeer, missing_reason


def quiet(_line: str) -> None:
    pass


LOGS = {"dr00001.bin": os.urandom(4096 * 5), "dr00002.bin": os.urandom(4096 * 2 + 100), "dr00003.bin": b""}


@pytest.fixture
def board(tmp_path):
    reason = missing_reason()
    require(reason is None, reason or "")
    root = tmp_path / "board"
    (root / "logs").mkdir(parents=True)
    for name, data in LOGS.items():
        (root / "logs" / name).write_bytes(data)
    (root / "main.py").write_text("print('app')\n")
    with ReplPeer(root) as peer:
        yield peer


def local(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def test_pull_copies_each_log_verified(board, tmp_path):
    out = tmp_path / "pulled"
    first = pull(board.url, out, progress=quiet)
    assert sorted(first.copied) == sorted(LOGS) and not first.unverified and first.reconnects == 0
    assert local(out) == LOGS  # no .part left behind
    again = pull(board.url, out, progress=quiet)
    assert again.copied == [] and sorted(again.unchanged) == sorted(LOGS)
    board.wait_idle()
    on_board = {k: v for k, v in board.files().items() if k.startswith("logs/")}
    assert on_board == {f"logs/{k}": v for k, v in LOGS.items()}


def test_a_differing_local_file_is_never_overwritten(board, tmp_path):
    out = tmp_path / "pulled"
    out.mkdir()
    (out / "dr00002.bin").write_bytes(b"my own notes")
    with pytest.raises(UserError) as failure:
        pull(board.url, out, delete=True, progress=quiet)
    assert "dr00002.bin" in failure.value.message and "nothing was overwritten or deleted" in failure.value.hint
    assert (out / "dr00002.bin").read_bytes() == b"my own notes"
    assert (out / "dr00001.bin").read_bytes() == LOGS["dr00001.bin"]  # the others came
    board.wait_idle()
    assert "logs/dr00002.bin" in board.files()  # not deleted: its copy is not the board's
    assert "logs/dr00001.bin" not in board.files() and "logs/dr00003.bin" not in board.files()


def test_delete_only_after_verification(board, tmp_path):
    out = tmp_path / "pulled"
    result = pull(board.url, out, delete=True, progress=quiet)
    assert sorted(result.deleted) == sorted(LOGS)
    board.wait_idle()
    assert not any(k.startswith("logs/dr") for k in board.files()) and "main.py" in board.files()
    assert local(out) == LOGS


def test_pull_resumes_after_drops_and_resets(board, tmp_path):
    out = tmp_path / "pulled"
    lines = []
    with FlakyLink(board.port, cuts=[4000, 21000], resets=[12000]) as link:
        result = pull(link.url, out, progress=lines.append)
    assert [kind for _, kind in link.done] == ["cut", "reset", "cut"], link.done
    assert result.reconnects == 3 and local(out) == LOGS
    assert any(line.strip().startswith("resuming dr00001.bin") for line in lines), lines
    # resumed, not started over: what crossed the link is the logs once plus at most a chunk per drop
    assert result.bytes_read <= sum(map(len, LOGS.values())) + 3 * 3072


def test_a_stale_part_of_another_file_starts_over(board, tmp_path):
    out = tmp_path / "pulled"
    out.mkdir()
    (out / "dr00001.bin.part").write_bytes(b"x" * 5000)  # a copy of an older dr00001.bin, since deleted
    result = pull(board.url, out, progress=quiet)
    assert local(out) == LOGS and "dr00001.bin" in result.copied


def test_pull_cli(board, tmp_path, capsys):
    from codegen.cli import main

    out = tmp_path / "pulled"
    assert main(["pull", "--port", board.url, "-o", str(out)]) == 0
    assert "pulled 3 log(s)" in capsys.readouterr().out
    assert main(["pull", "--port", "socket://127.0.0.1:9", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: nothing answers at socket://127.0.0.1:9") and "Traceback" not in err
