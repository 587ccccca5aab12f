"""`deadreckon run`: from the board YAML to the app on a board: uploaded to one running MicroPython (the raw-REPL
peer), flashed with its firmware onto an ESP32 (the ROM-loader emulator), refused with the fix on a silent one."""

from __future__ import annotations

import socket
import threading

from codegen.cli import main
from codegen.deploy.fsimage import mount_image, read_tree
from conftest import require
from peers.repl_peer import ReplPeer, missing_reason


def app_files(out):
    app = out / "build" / "app"
    return {p.relative_to(app).as_posix(): p.read_bytes() for p in app.rglob("*") if p.is_file()}


def test_run_uploads_to_a_board_running_micropython(tmp_path, capsys):
    reason = missing_reason()
    require(reason is None, reason or "")
    out = tmp_path / "out"
    with ReplPeer(tmp_path / "board") as peer:
        assert main(["run", "-o", str(out), "--port", peer.url, "--no-monitor"]) == 0
        peer.wait_idle()
        assert peer.files() == app_files(out)
    printed = capsys.readouterr().out
    assert "generated" in printed and "looking for MicroPython on" in printed and "uploaded" in printed


def test_run_flashes_firmware_and_app(tmp_path, capsys):
    from peers.esp_rom import RomLoaderPeer
    from peers.trees import default_board, merged_firmware

    firmware = tmp_path / "ESP32_GENERIC.bin"
    firmware.write_bytes(merged_firmware())
    out = tmp_path / "out"
    with RomLoaderPeer() as peer:
        assert main(["run", "-o", str(out), "--port", peer.url, "--firmware", str(firmware), "--no-monitor"]) == 0
        board = default_board()
        fs = board.micropython.filesystem
        start = board.micropython.partitions.bootloader
        assert peer.flash[start:start + firmware.stat().st_size] == firmware.read_bytes()
        on_board = read_tree(mount_image(bytes(peer.flash[fs.offset:fs.offset + fs.size]), block_size=fs.block_size))
    assert on_board == app_files(out)


def test_run_on_a_board_without_micropython_says_which_firmware(tmp_path, capsys):
    server = socket.create_server(("127.0.0.1", 0))  # a port that never answers (a blank board's bridge)
    held = []
    threading.Thread(target=lambda: held.append(server.accept()), daemon=True).start()
    try:
        code = main(["run", "-o", str(tmp_path / "out"), "--port",
                     f"socket://127.0.0.1:{server.getsockname()[1]}", "--no-monitor"])
    finally:
        server.close()
    err = capsys.readouterr().err
    assert code == 2 and "does not answer as MicroPython" in err and "Traceback" not in err
    assert "--firmware ESP32_GENERIC-v" in err
