"""The board's watchdog against the host's transfers: the raw-REPL peer with a watchdog (repl_bridge.mjs
--watchdog-ms), whose app stops feeding it at the first Ctrl-C; `upload`, `pull` and `run` interrupt it at
different moments of the watchdog's period and take several timeouts long, and the board is never reset. Without
the host's timer the same upload is cut by a reset: the peer's watchdog bites."""

from __future__ import annotations

import os
import time

import pytest

from codegen.cli import main
from codegen.deploy import watchdog as host_watchdog
from codegen.deploy.build import build
from codegen.deploy.pull import pull
from codegen.deploy.upload import upload
from codegen.errors import UserError
from conftest import require
from peers.flaky_link import FlakyLink
from peers.repl_peer import ReplPeer, missing_reason
from peers.trees import default_board, make_tree

TIMEOUT_MS = 400  # the peer's watchdog: short, so a transfer of a few seconds is many timeouts long
SLOW_S = 0.03  # each reply of the board waits this long on the link, so a transfer of n commands takes at least
# n * SLOW_S (upload: 32 chunks and 10 more commands; pull: 48 chunks and 4 more), whatever the machine's speed


def quiet(_line: str) -> None:
    pass


def board_root(tmp_path, watchdog_ms=TIMEOUT_MS, logs=()):
    """A board the app runs on: its main.py and board_config (with the watchdog's timeout), and logs."""
    root = tmp_path / "board"
    (root / "logs").mkdir(parents=True)
    (root / "main.py").write_text("import app\napp.main()\n")
    (root / "board_config.py").write_text(f"WATCHDOG_MS = {watchdog_ms}\n")
    for name, data in logs:
        (root / "logs" / name).write_bytes(data)
    return root


@pytest.fixture
def peer_ok():
    reason = missing_reason()
    require(reason is None, reason or "")


@pytest.fixture
def built(tmp_path):
    tree = make_tree(tmp_path / "out")
    result = build(tree, board=default_board(), progress=quiet, image=False)
    (result.app_dir / "data.bin").write_bytes(os.urandom(64 * 1024))  # a transfer of several seconds
    return tree, result


@pytest.mark.parametrize("delay_s", [0.0, 0.15, 0.35])
def test_upload_lives_through_the_watchdog(peer_ok, tmp_path, built, delay_s):
    tree, result = built
    with ReplPeer(board_root(tmp_path), watchdog_ms=TIMEOUT_MS) as board:
        time.sleep(delay_s)  # the Ctrl-C lands at another moment of the app's run
        with FlakyLink(board.port, delay_s=SLOW_S) as link:
            started = time.monotonic()
            upload(tree, link.url, progress=quiet)
            took = time.monotonic() - started
        board.wait_idle()
        assert board.watchdog_resets() == 0
        files = board.files()
    print(f"upload: {took:.2f} s against a {TIMEOUT_MS} ms watchdog")
    assert took > 3 * TIMEOUT_MS / 1000, f"the upload took only {took:.1f} s: no proof"
    assert all(files[rel] == (result.app_dir / rel).read_bytes() for rel in result.files)
    assert files["data.bin"] == (result.app_dir / "data.bin").read_bytes()


def test_without_the_hosts_timer_the_watchdog_cuts_the_upload(peer_ok, tmp_path, built, monkeypatch):
    tree, _ = built
    monkeypatch.setattr(host_watchdog, "HOLD_SCRIPT", "print('none')")
    with ReplPeer(board_root(tmp_path), watchdog_ms=TIMEOUT_MS) as board:
        # through the slow link the upload outlasts the watchdog by design, as in the tests above: on a quiet
        # machine a direct upload can finish inside one timeout, and then nothing is cut
        with FlakyLink(board.port, delay_s=SLOW_S) as link, pytest.raises(UserError):
            upload(tree, link.url, progress=quiet)
        assert board.watchdog_resets() >= 1


@pytest.mark.parametrize("delay_s", [0.1, 0.3])
def test_pull_lives_through_the_watchdog(peer_ok, tmp_path, delay_s):
    logs = [(f"dr0000{i}.bin", os.urandom(4096 * 9)) for i in range(1, 5)]
    with ReplPeer(board_root(tmp_path, logs=logs), watchdog_ms=TIMEOUT_MS) as board:
        time.sleep(delay_s)
        with FlakyLink(board.port, delay_s=SLOW_S) as link:
            started = time.monotonic()
            result = pull(link.url, tmp_path / "pulled", progress=quiet)
            took = time.monotonic() - started
        assert board.watchdog_resets() == 0
    print(f"pull: {took:.2f} s against a {TIMEOUT_MS} ms watchdog")
    assert took > 3 * TIMEOUT_MS / 1000, f"the pull took only {took:.1f} s: no proof"
    assert result.reconnects == 0 and sorted(result.copied) == [name for name, _ in logs]
    assert all((tmp_path / "pulled" / name).read_bytes() == data for name, data in logs)


def test_run_lives_through_the_boards_own_watchdog(peer_ok, tmp_path, capsys):
    """`run` onto a board running an earlier build of its app, whose watchdog is the board's watchdog_s (1 s here,
    the shortest a board YAML allows): from the probe's Ctrl-C to the soft reset into the new app, several
    timeouts pass."""
    yaml = tmp_path / "board.yaml"
    yaml.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-short-watchdog\nmicropython:\n  watchdog_s: 1\n")
    out = tmp_path / "out"
    assert main(["generate", str(yaml), "-o", str(out)]) == 0
    assert main(["build", str(out)]) == 0  # built before, so the time below is the board's part of `run`
    capsys.readouterr()
    with ReplPeer(board_root(tmp_path, watchdog_ms=1000), watchdog_ms=1000) as board:
        time.sleep(0.3)
        with FlakyLink(board.port, delay_s=SLOW_S) as link:  # 11 files, at least 4 commands each
            assert main(["run", str(yaml), "-o", str(out), "--port", link.url, "--no-monitor", "--force"]) == 0
            printed = capsys.readouterr().out
        board.wait_idle()
        assert board.watchdog_resets() == 0
        files = board.files()
    app = out / "build" / "app"
    assert all(files[p.relative_to(app).as_posix()] == p.read_bytes() for p in app.rglob("*") if p.is_file())
    upload_s = float(printed.split("uploaded")[-1].split(" in ")[1].split(" s")[0])
    assert upload_s > 1.2, f"the upload took only {upload_s} s against a 1 s watchdog"
