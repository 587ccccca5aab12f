"""`deadreckon upload`: raw REPL onto real MicroPython (the WebAssembly port behind tests/peers/repl_bridge.mjs),
first shown faithful with the real mpremote client, then driven by our uploader."""

from __future__ import annotations

import subprocess
import sys

import pytest

from codegen.deploy.build import build
from codegen.deploy.upload import RawRepl, open_port, upload
from codegen.errors import UserError
from conftest import require
from peers.repl_peer import ReplPeer, missing_reason
from peers.trees import default_board, make_tree


def quiet(_line: str) -> None:
    pass


@pytest.fixture
def peer(tmp_path):
    reason = missing_reason()
    require(reason is None, reason or "")
    with ReplPeer(tmp_path / "board") as p:
        yield p


@pytest.fixture
def built(tmp_path):
    tree = make_tree(tmp_path / "out")
    return tree, build(tree, board=default_board(), progress=quiet, image=False)


def mpremote(peer: ReplPeer, *args: str) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "mpremote", "connect", peer.url, *args], capture_output=True,
                            text=True, timeout=60)
    peer.wait_idle()
    return result


def test_mpremote_works_against_the_peer(peer, tmp_path):
    require(subprocess.run([sys.executable, "-c", "import mpremote"]).returncode == 0, "mpremote is not installed")
    (peer.root / "hello.py").write_text("GREETING = 'hi from the board'\n")
    peer.stop()
    with ReplPeer(peer.root) as board:  # files present at start are on the board's filesystem
        source = tmp_path / "x.py"
        source.write_text("X = 41\n")
        ran = mpremote(board, "fs", "ls", "+", "fs", "mkdir", "lib", "+", "fs", "cp", str(source), ":lib/x.py",
                       "+", "exec", "import hello; from lib import x; print(hello.GREETING, x.X + 1)")
        assert ran.returncode == 0, ran.stderr
        # 42 proves exec ran after cp; the lines' order in a pipe depends on mpremote's buffering (PYTHONUNBUFFERED)
        assert "hello.py" in ran.stdout and "hi from the board 42" in ran.stdout.splitlines()
        assert board.files()["lib/x.py"] == b"X = 41\n"
        missing = mpremote(board, "fs", "cat", "nope.py")
        assert missing.returncode != 0 and "No such file or directory" in missing.stderr  # errno mapped


def test_upload_sends_only_what_differs(peer, built):
    tree, result = built
    first = upload(tree, peer.url, progress=quiet)
    peer.wait_idle()
    assert sorted(first.sent) == sorted(result.files) and not first.raw_paste
    assert peer.files() == {rel: (result.app_dir / rel).read_bytes() for rel in result.files}

    # the uploaded .mpy modules run on MicroPython (ours compiled for 1.24, the peer runs 1.27)
    handle = open_port(peer.url)
    try:
        repl = RawRepl(handle)
        repl.enter()
        assert repl.exec("import app; app.run()").strip() == b"deadreckon 42"
    finally:
        handle.close()
    peer.wait_idle()

    second = upload(tree, peer.url, progress=quiet)
    peer.wait_idle()
    assert second.sent == [] and sorted(second.unchanged) == sorted(result.files)

    (result.app_dir / "lib" / "util.mpy").write_bytes(b"changed")
    third = upload(tree, peer.url, progress=quiet)
    peer.wait_idle()
    assert third.sent == ["lib/util.mpy"]
    assert peer.files()["lib/util.mpy"] == b"changed"

    forced = upload(tree, peer.url, force=True, progress=quiet)
    peer.wait_idle()
    assert sorted(forced.sent) == sorted(result.files)


def test_a_stale_py_that_would_shadow_the_new_mpy_is_removed(peer, built):
    tree, result = built
    (peer.root / "app.py").write_text("raise RuntimeError('old source')\n")
    peer.stop()
    with ReplPeer(peer.root) as board:
        outcome = upload(tree, board.url, progress=quiet)
        board.wait_idle()
        assert outcome.removed == ["app.py"]
        assert "app.py" not in board.files() and "app.mpy" in board.files()


def test_upload_in_raw_paste_mode(tmp_path, built):
    reason = missing_reason()
    require(reason is None, reason or "")
    tree, result = built
    blob = bytes(range(256)) * 40  # 10 kB of every byte value, several chunks
    (result.app_dir / "data.bin").write_bytes(blob)
    with ReplPeer(tmp_path / "board", raw_paste=True) as board:
        outcome = upload(tree, board.url, progress=quiet)
        board.wait_idle()
        assert outcome.raw_paste
        assert board.files()["data.bin"] == blob
        assert board.files() == {p.relative_to(result.app_dir).as_posix(): p.read_bytes()
                                 for p in result.app_dir.rglob("*") if p.is_file()}


def test_upload_needs_a_build(tmp_path):
    tree = make_tree(tmp_path / "out")
    with pytest.raises(UserError) as failure:
        upload(tree, "socket://127.0.0.1:9", progress=quiet)
    assert "build/app does not exist" in failure.value.message and "deadreckon build" in failure.value.hint


def test_upload_errors_name_the_port(built):
    tree, _ = built
    with pytest.raises(UserError, match="no such port /dev/ttyDEADRECKON0"):
        upload(tree, "/dev/ttyDEADRECKON0", progress=quiet)
    with pytest.raises(UserError, match="nothing answers at socket://127.0.0.1:9"):
        upload(tree, "socket://127.0.0.1:9", progress=quiet)


def test_upload_cli_error_path(built, capsys):
    from codegen.cli import main

    tree, result = built
    assert main(["upload", str(tree), "--port", "socket://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: nothing answers") and "Traceback" not in err


def test_default_board_generate_build_upload(peer, tmp_path, capsys):
    """The whole path a user takes, through the CLI: generate -> build -> upload, on the default board."""
    from codegen.cli import main

    out = tmp_path / "out"
    assert main(["generate", "-o", str(out)]) == 0
    assert main(["build", str(out)]) == 0
    assert main(["upload", str(out), "--port", peer.url]) == 0
    peer.wait_idle()
    app_dir = out / "build" / "app"
    files = {p.relative_to(app_dir).as_posix(): p.read_bytes() for p in app_dir.rglob("*") if p.is_file()}
    assert "main.py" in files and peer.files() == files
    assert f"uploaded {len(files)} file(s), 0 unchanged" in capsys.readouterr().out


def test_upload_through_a_tty_device_path(peer, built):
    """A /dev/pts/N in front of the board, as a USB serial adapter would be: paced standard raw mode."""
    import serial

    from peers.pty_link import PtyLink

    tree, result = built
    with PtyLink("127.0.0.1", peer.port) as link:
        holder = serial.Serial(link.path, exclusive=True)  # a serial monitor left open
        with pytest.raises(UserError, match=f"port {link.path} is busy"):
            upload(tree, link.path, progress=quiet)
        holder.close()
        outcome = upload(tree, link.path, progress=quiet)
    peer.wait_idle()
    assert sorted(outcome.sent) == sorted(result.files)
    assert peer.files() == {rel: (result.app_dir / rel).read_bytes() for rel in result.files}


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # pyserial's rfc2217 threads use setDaemon()
def test_upload_to_an_rfc2217_url(peer, built):
    """`rfc2217://host:port`, a serial port shared over the network (ser2net and the like)."""
    from peers.rfc2217_server import Rfc2217Server

    tree, result = built
    with Rfc2217Server(peer.url) as server:
        outcome = upload(tree, server.url, progress=quiet)
    peer.wait_idle()
    assert sorted(outcome.sent) == sorted(result.files)
    assert peer.files() == {rel: (result.app_dir / rel).read_bytes() for rel in result.files}
