"""`deadreckon flash`: the real esptool against the emulated ESP32 ROM loader (tests/peers/esp_rom.py)."""

from __future__ import annotations

import time

import pytest

from codegen.deploy.build import build
from codegen.deploy.flash import flash, plan_regions
from codegen.deploy.fsimage import mount_image, read_tree
from codegen.errors import UserError
from conftest import require
from peers.esp_rom import RomLoaderPeer
from peers.trees import MICROPYTHON_4MIB, default_board, make_tree, merged_firmware


def _have_esptool() -> bool:
    try:
        import esptool  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    require(_have_esptool(), "esptool is not installed (pip install esptool)")
    root = tmp_path_factory.mktemp("flash")
    tree = make_tree(root / "out")
    result = build(tree, board=default_board(), progress=lambda _: None)
    firmware = root / "micropython.bin"
    firmware.write_bytes(merged_firmware())
    return tree, result, firmware


@pytest.fixture
def peer():
    with RomLoaderPeer() as p:
        yield p


def quiet(_line: str) -> None:
    pass


def assert_flashed(peer: RomLoaderPeer, result, firmware, board=None) -> None:
    board = board or default_board()
    fw = firmware.read_bytes()
    start = board.micropython.partitions.bootloader
    assert peer.flash[start : start + len(fw)] == fw
    fs = board.micropython.filesystem
    image = result.image.read_bytes()
    assert peer.flash[fs.offset : fs.offset + fs.size] == image
    mounted = read_tree(mount_image(bytes(peer.flash[fs.offset : fs.offset + fs.size]), block_size=fs.block_size))
    assert mounted == {rel: (result.app_dir / rel).read_bytes() for rel in result.files}


def test_flash_over_the_rom_loader(built, peer, tmp_path):
    """The ROM path alone (--no-stub --no-compress): 0x400-byte blocks, 4-word FLASH_BEGIN, hex MD5 verification.
    A 256 KiB filesystem (and a firmware whose partition table says so) keeps it quick (the full 2 MiB image this
    way: tests/peers/bench_flash.py)."""
    board = default_board(**{"micropython.filesystem.size": 0x40000})
    firmware = tmp_path / "small-vfs.bin"
    firmware.write_bytes(merged_firmware(rows=MICROPYTHON_4MIB[:-1] + (("vfs", 0x01, 0x81, 0x200000, 0x40000),)))
    tree = make_tree(tmp_path / "out")
    result = build(tree, board=board, progress=quiet)
    started = time.monotonic()
    outcome = flash(tree, peer.url, firmware=firmware, board=board, stub=False, compress=False, progress=quiet)
    print(f"ROM path: 256 KiB image + {firmware.stat().st_size} byte firmware in {time.monotonic() - started:.1f} s")
    assert_flashed(peer, result, firmware, board)
    assert peer.stats.stub_runs == 0
    assert peer.stats.commands.get(0x03, 0) >= 256 + 252  # every 0x400 block went over the wire, uncompressed
    assert peer.stats.commands.get(0x13) == 2  # one MD5 verification per region
    assert peer.stats.commands.get(0x04, 0) == 0  # no FLASH_END: it would leave the ROM loader
    assert [r.offset for r in outcome.regions] == [0x1000, 0x200000]


def test_flash_over_the_rom_loader_compressed(built, peer):
    """What `deadreckon flash --no-stub` does: the ESP32 ROM inflates FLASH_DEFL blocks itself."""
    tree, result, firmware = built
    started = time.monotonic()
    flash(tree, peer.url, firmware=firmware, board=default_board(), stub=False, progress=quiet)
    print(f"ROM path, compressed: {time.monotonic() - started:.1f} s")
    assert_flashed(peer, result, firmware)
    assert peer.stats.stub_runs == 0 and peer.stats.commands.get(0x11, 0) > 0


def test_flash_with_the_stub(built, peer, tmp_path):
    tree, result, firmware = built
    started = time.monotonic()
    flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    print(f"stub path: {time.monotonic() - started:.1f} s")
    assert_flashed(peer, result, firmware)
    assert peer.stats.stub_runs == 1
    assert peer.stats.commands.get(0x11, 0) > 0  # compressed writes

    # and the stub's READ_FLASH, through esptool's own command line: the image's first 8 KiB come back
    import subprocess
    import sys

    back = tmp_path / "back.bin"
    read = subprocess.run([sys.executable, "-m", "esptool", "--chip", "esp32", "--port", peer.url, "--before",
                           "no-reset", "read-flash", "0x200000", "0x2000", str(back)], capture_output=True, text=True)
    assert read.returncode == 0, read.stdout + read.stderr
    assert back.read_bytes() == result.image.read_bytes()[:0x2000]


def test_dropped_connection_fails_clearly_then_a_retry_succeeds(built, peer):
    tree, result, firmware = built
    peer.drop_after_blocks = 3
    with pytest.raises(UserError) as failure:
        flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    assert "connection to the board" in failure.value.message and "lost" in failure.value.message
    peer.clear_faults()
    flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    assert_flashed(peer, result, firmware)


def test_corrupted_reply_fails_clearly_then_a_retry_succeeds(built, peer):
    tree, result, firmware = built
    peer.noise_reply = (0x0A, 12)  # the 12th READ_REG reply (chip info) drowns in line noise
    with pytest.raises(UserError, match="arrived corrupted"):
        flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    peer.clear_faults()
    flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    assert_flashed(peer, result, firmware)


def test_wrong_chip_is_refused_before_writing(built, peer):
    tree, result, firmware = built
    peer.chip_magic = 0x000007C6  # what an ESP32-S2 shows
    with pytest.raises(UserError) as failure:
        flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    assert "ESP32-S2" in failure.value.message and "ESP32" in failure.value.message
    assert peer.flash == bytearray(b"\xff" * len(peer.flash))
    peer.chip_magic = 0x12345678  # no chip esptool knows: it would "continue anyway"; we stop it
    with pytest.raises(UserError, match="not an ESP32"):
        flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    assert peer.flash == bytearray(b"\xff" * len(peer.flash))
    peer.clear_faults()
    flash(tree, peer.url, firmware=firmware, board=default_board(), progress=quiet)
    assert_flashed(peer, result, firmware)


def test_flash_smaller_than_the_layout(built):
    tree, result, firmware = built
    with RomLoaderPeer(flash_size=2 * 1024 * 1024) as small:
        small.flash[0x1000 : 0x1000 + firmware.stat().st_size] = firmware.read_bytes()  # MicroPython is on it
        with pytest.raises(UserError, match="less flash"):
            flash(tree, small.url, board=default_board(), progress=quiet)


def test_firmware_for_another_chip(built, peer, tmp_path):
    tree, result, _ = built
    s3 = tmp_path / "s3.bin"
    s3.write_bytes(merged_firmware(chip_id=9, app_bytes=0x1000))
    with pytest.raises(UserError, match="not built for an ESP32"):
        flash(tree, peer.url, firmware=s3, board=default_board(), progress=quiet)


def test_layout_checks_before_touching_the_board(built, tmp_path):
    tree, result, firmware = built
    board = default_board()
    with pytest.raises(UserError, match="larger than the vfs partition"):
        plan_regions(default_board(**{"micropython.filesystem.size": 0x100000}), result.image)
    with pytest.raises(UserError, match="layout ends at"):
        plan_regions(default_board(flash_size="2MB"), result.image)
    with pytest.raises(UserError, match="not an ESP firmware image"):
        text = tmp_path / "fw.uf2"
        text.write_bytes(b"UF2\n" * 100)
        plan_regions(board, result.image, text)
    with pytest.raises(UserError, match="no partition table at 0x8000"):
        huge = tmp_path / "huge.bin"
        huge.write_bytes(b"\xe9" + b"\0" * 0x200000)  # an app-only image, as a build's micropython.bin is
        plan_regions(board, result.image, huge)
    with pytest.raises(UserError, match="runs 48 bytes past its own app partition"):
        huge.write_bytes(merged_firmware(app_bytes=0x1F0000))  # 0x1F0000 of segment + 48 bytes of headers
        plan_regions(board, result.image, huge)


def test_no_such_port(built):
    tree, _, _ = built
    with pytest.raises(UserError, match="no such port /dev/ttyDEADRECKON0"):
        flash(tree, "/dev/ttyDEADRECKON0", board=default_board(), progress=quiet)


def test_flash_cli_error_path(built, peer, capsys, monkeypatch):
    from codegen import cli

    tree, result, firmware = built
    monkeypatch.setattr("codegen.deploy.build._manifest_board", lambda out: default_board())
    peer.chip_magic = 0x000007C6
    assert cli.main(["flash", str(tree), "--port", peer.url]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: the chip on socket://") and "hint:" in err and "Traceback" not in err


def test_default_board_generate_build_flash(tmp_path, peer, capsys):
    """The whole path a user takes, through the CLI: generate -> build -> flash --erase --firmware, on the default
    board (a blank board gets MicroPython and the app in one go)."""
    require(_have_esptool(), "esptool is not installed (pip install esptool)")
    from codegen.board.loader import load_board
    from codegen.cli import main

    board = load_board(None).board
    out = tmp_path / "out"
    peer.flash[0x100000:0x100010] = b"\0" * 16  # something the layout does not cover
    assert main(["generate", "-o", str(out)]) == 0
    assert main(["build", str(out)]) == 0  # the board comes from OUT/MANIFEST.json
    firmware = tmp_path / "ESP32_GENERIC.bin"
    firmware.write_bytes(merged_firmware(app_bytes=0x1000))
    assert main(["flash", str(out), "--port", peer.url, "--erase"]) == 2  # would leave no firmware
    assert "--erase without --firmware" in capsys.readouterr().err
    assert main(["flash", str(out), "--port", peer.url, "--erase", "--firmware", str(firmware)]) == 0
    assert "flashed and verified 2 region(s)" in capsys.readouterr().out
    assert peer.flash[0x100000:0x100010] == b"\xff" * 16
    app_dir = out / "build" / "app"
    files = {p.relative_to(app_dir).as_posix(): p.read_bytes() for p in app_dir.rglob("*") if p.is_file()}
    assert "main.py" in files and any(name.endswith(".mpy") for name in files)
    fs = board.micropython.filesystem
    region = bytes(peer.flash[fs.offset : fs.offset + fs.size])
    assert region == (out / "build" / "fs.img").read_bytes()
    assert read_tree(mount_image(region, block_size=fs.block_size)) == files


def test_flash_through_a_tty_device_path_and_a_busy_one(built, peer):
    """A /dev/pts/N in front of the emulated chip, as a USB serial adapter would be (esptool's DTR/RTS reset)."""
    import serial

    from peers.pty_link import PtyLink

    tree, result, firmware = built
    with PtyLink("127.0.0.1", peer.port) as link:
        holder = serial.Serial(link.path, exclusive=True)  # a serial monitor left open
        try:
            with pytest.raises(UserError, match=f"port {link.path} is busy"):
                flash(tree, link.path, board=default_board(), progress=quiet)
        finally:
            holder.close()
        flash(tree, link.path, firmware=firmware, board=default_board(), progress=quiet)
    assert_flashed(peer, result, firmware)


def test_board_yaml_naming_another_chip():
    from codegen.deploy.flash import classify

    said = "A fatal error occurred: This chip is ESP32, not ESP32-S3. Wrong chip argument?"
    error = classify(said, "/dev/ttyUSB0", default_board(chip="esp32s3"), [])
    assert error.message == "the chip on /dev/ttyUSB0 is ESP32, but ttgo-tbeam-v1.1 has an ESP32-S3"


def test_falls_back_to_115200_when_the_line_cannot_go_faster(built, peer, tmp_path, monkeypatch):
    from peers.pty_link import PtyLink

    config = tmp_path / "esptool.cfg"
    config.write_text("[esptool]\ntimeout = 0.5\n")  # esptool waits this long for the silent chip
    monkeypatch.setenv("ESPTOOL_CFGFILE", str(config))

    tree, result, firmware = built
    peer.drop_on_baud_change = True  # the chip goes silent when asked for 460800 baud
    lines = []
    with PtyLink("127.0.0.1", peer.port) as link:
        outcome = flash(tree, link.path, firmware=firmware, board=default_board(), progress=lines.append)
    assert outcome.baud == 115200 and outcome.attempts[0].startswith("460800: exit 2")
    assert any("trying 115200" in line for line in lines)
    assert_flashed(peer, result, firmware)


@pytest.mark.parametrize("stub", [True, False], ids=["stub", "rom"])
def test_filesystem_only_flash_reads_the_boards_partition_table_first(built, peer, stub):
    """Without --firmware the image joins the MicroPython already on the board: its partition table is read
    (the stub's READ_FLASH, or the ROM's 64-byte READ_FLASH_SLOW) and checked before anything is written."""
    tree, result, firmware = built
    peer.flash[0x1000 : 0x1000 + firmware.stat().st_size] = firmware.read_bytes()
    flash(tree, peer.url, board=default_board(), stub=stub, progress=quiet)
    read = peer.stats.commands.get(0xD2 if stub else 0x0E, 0)
    assert read == (1 if stub else 0xC00 // 64)
    fs = default_board().micropython.filesystem
    assert peer.flash[fs.offset : fs.offset + fs.size] == result.image.read_bytes()
    assert peer.flash[0x1000 : 0x1000 + firmware.stat().st_size] == firmware.read_bytes()
