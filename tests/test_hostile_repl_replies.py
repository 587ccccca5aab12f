"""`upload --port` and `flash --port` against replies no MicroPython board gives: a raw REPL whose output is bytes
0x80-0xFF (another program's binary, a wrong baud rate once in raw mode), a board whose filesystem is full, and
pyserial's loopback `loop://`, which echoes what is sent. Each through the CLI: exit 2, an `error:` naming the
port with a hint, no traceback, within the bound, nothing changed around the tree."""

from __future__ import annotations

import socket

import pytest

from hostilekit import PORT_BOUND_S, assert_refused, run_cli, snapshot, user_files
from peers.bad_ports import BadPort

HIGH_BYTES = bytes(range(0x80, 0x100))
ENOSPC = (b"Traceback (most recent call last):\r\n  File \"<stdin>\", line 2, in <module>\r\n"
          b"OSError: [Errno 28] ENOSPC\r\n")


class ReplyPort(BadPort):
    """A raw REPL that answers every command with `output` (after OK), or with `error` for a command that opens a
    file for writing."""

    def __init__(self, output: bytes = b"", error: bytes | None = None):
        super().__init__("liar")
        self.behaviour = "replies"
        self.output, self.error = output, error

    def _replies(self, conn: socket.socket) -> None:
        for code in self._commands(conn):
            if self.error is not None and b"'wb'" in code:
                conn.sendall(b"OK\x04" + self.error + b"\x04>")
            else:
                conn.sendall(b"OK" + self.output + b"\x04\x04>")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    home = tmp_path_factory.mktemp("replies") / "home"
    home.mkdir()
    user_files(home)
    assert run_cli("generate", "-o", "out", cwd=home, timeout=120).returncode == 0
    assert run_cli("build", "out", cwd=home, timeout=300).returncode == 0
    return home


@pytest.mark.parametrize("port_kwargs,phrases", [
    ({"output": HIGH_BYTES}, ["the board's copy of", "differs from what was sent to socket://127.0.0.1:"]),
    ({"output": HIGH_BYTES * 40 + b"\r\n" + HIGH_BYTES}, ["differs from what was sent to socket:"]),
    ({"error": ENOSPC}, ["the filesystem of the board on socket://127.0.0.1:", "is full",
                         "hint: remove files from the board"]),
], ids=["bytes-0x80-0xff", "long-binary-lines", "filesystem-full"])
def test_upload_to_a_repl_with_impossible_replies(built, port_kwargs, phrases):
    before = snapshot(built)
    with ReplyPort(**port_kwargs) as port:
        outcome = run_cli("upload", "out", "--port", port.url, cwd=built, timeout=PORT_BOUND_S)
    assert_refused(outcome, *phrases, "hint: ", bound=PORT_BOUND_S)
    assert snapshot(built) == before


@pytest.mark.parametrize("command", ["upload", "flash"])
def test_the_loopback_url_is_no_board(built, command):
    before = snapshot(built)
    outcome = run_cli(command, "out", "--port", "loop://", cwd=built)
    assert_refused(outcome, "--port loop:// is pyserial's loopback", "hint: give the board's port")
    assert "last_error" not in outcome.stderr and "self." not in outcome.stderr
    assert snapshot(built) == before
