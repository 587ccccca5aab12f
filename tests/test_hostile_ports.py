"""Hostile ports: `deadreckon upload` and `flash` against ports that close, stay silent, talk continuously, stop
reading, answer with noise, lie, drop mid-transfer or stall, and against port names that are not ports.

The peers: tests/peers/bad_ports.py (misbehaving TCP ports, some speaking the raw REPL first) and the emulated
ESP32 ROM loader with its faults (tests/peers/esp_rom.py). Each case: exit 2, a clear message, no traceback,
within the bound, and the files around the tree unchanged.
"""

from __future__ import annotations

import os
import shutil
import sys
import time

import pytest

from hostilekit import PORT_BOUND_S, QUICK_BOUND_S, assert_refused, run_cli, snapshot, user_files
from peers.bad_ports import BadPort
from peers.esp_rom import RomLoaderPeer
from peers.trees import merged_firmware


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A generated and built default-board tree beside the user's files, and a MicroPython firmware file."""
    try:
        import esptool  # noqa: F401
    except ImportError:
        pytest.fail("esptool is a dependency of deadreckon (pyproject.toml)")
    home = tmp_path_factory.mktemp("ports") / "home"
    home.mkdir()
    user_files(home)
    assert run_cli("generate", "-o", "out", cwd=home, timeout=120).returncode == 0
    assert run_cli("build", "out", cwd=home, timeout=300).returncode == 0
    (home / "ESP32_GENERIC.bin").write_bytes(merged_firmware())
    return home


UPLOAD = [
    ("accepts-then-closes", "close", ["the connection to the board on", "was lost"]),
    ("silent", "silent", ["did not enter the raw REPL"]),
    ("talks-continuously", "chatter", ["talks continuously", "never answered as MicroPython's raw REPL"]),
    ("never-reads", "deaf", ["did not enter the raw REPL"]),
    ("line-noise", "garbage", ["did not enter the raw REPL"]),
    ("lies-ok-stores-nothing", "liar", ["the board's copy of", "differs from what was sent"]),
    ("drops-mid-transfer", "drop", ["was lost"]),
    ("talks-forever-after-ok", "babble", ["without the end of a reply"]),
    ("stalls-after-ok", "stall", ["timed out waiting for"]),
]


@pytest.mark.parametrize("behaviour,phrases", [case[1:] for case in UPLOAD], ids=[case[0] for case in UPLOAD])
def test_upload_to_a_misbehaving_port(built, behaviour, phrases):
    before = snapshot(built)
    with BadPort(behaviour) as port:
        outcome = run_cli("upload", "out", "--port", port.url, cwd=built, timeout=PORT_BOUND_S)
    assert_refused(outcome, *phrases, bound=PORT_BOUND_S)
    assert snapshot(built) == before


FLASH = [
    ("accepts-then-closes", "close", ["the connection to the board on", "lost"]),
    ("silent", "silent", ["no ESP32 bootloader answered"]),
    ("talks-continuously", "chatter", ["arrived corrupted"]),
    ("never-reads", "deaf", ["no ESP32 bootloader answered"]),
    ("line-noise", "garbage", ["arrived corrupted"]),
]


@pytest.mark.parametrize("with_firmware", [True, False], ids=["firmware", "filesystem-only"])
@pytest.mark.parametrize("behaviour,phrases", [case[1:] for case in FLASH], ids=[case[0] for case in FLASH])
def test_flash_to_a_misbehaving_port(built, behaviour, phrases, with_firmware):
    """With --firmware the write run meets the port; without, the run that reads the board's partition table."""
    before = snapshot(built)
    firmware = ["--firmware", "ESP32_GENERIC.bin"] if with_firmware else []
    with BadPort(behaviour) as port:
        outcome = run_cli("flash", "out", "--port", port.url, *firmware, cwd=built, timeout=PORT_BOUND_S)
    assert_refused(outcome, *phrases, bound=PORT_BOUND_S)
    assert snapshot(built) == before


ROM_FAULTS = [
    ("drops-mid-transfer", {"drop_after_blocks": 1}, ["the connection to the board", "was lost while flashing"]),
    ("stalls-mid-transfer", {"stall_after_blocks": 1}, ["the connection to the board", "was lost while flashing"]),
    ("lies-about-what-it-programmed", {"corrupt_program": True}, ["verification failed", "does not hold what was"]),
    ("is-an-esp32-s2", {"chip_magic": 0x000007C6}, ["is ESP32-S2, but ttgo-tbeam-v1.1 has an ESP32"]),
    ("is-no-chip-esptool-knows", {"chip_magic": 0x12345678}, ["is not an ESP32"]),
    ("replies-drowned-in-noise", {"noise_reply": (0x0A, 12)}, ["arrived corrupted"]),
]


@pytest.mark.parametrize("faults,phrases", [case[1:] for case in ROM_FAULTS], ids=[case[0] for case in ROM_FAULTS])
def test_flash_to_a_rom_loader_that_fails(built, tmp_path, faults, phrases):
    """esptool's own waits bound a stalled chip; the configuration file makes them seconds, not minutes (at its
    defaults esptool gives a block 40 s per MiB it inflates to)."""
    config = tmp_path / "esptool.cfg"
    config.write_text("[esptool]\nerase_write_timeout_per_mb = 2\ntimeout = 1\n")
    before = snapshot(built)
    with RomLoaderPeer() as peer:
        for name, value in faults.items():
            setattr(peer, name, value)
        outcome = run_cli("flash", "out", "--port", peer.url, "--firmware", "ESP32_GENERIC.bin", cwd=built,
                          timeout=PORT_BOUND_S, env={"ESPTOOL_CFGFILE": str(config)})
        if "chip_magic" in faults:
            assert peer.flash == bytearray(b"\xff" * len(peer.flash))  # refused before writing a byte
    assert_refused(outcome, *phrases, bound=PORT_BOUND_S)
    assert snapshot(built) == before


def _fifo(home):
    os.mkfifo(home / "fifo.port")
    return "fifo.port"


def _regular_file(home):
    (home / "port.txt").write_text("not a port\n")
    return "port.txt"


PORT_NAMES = [
    ("unknown-url-scheme", lambda home: "foo://board", ["unknown port URL scheme 'foo://'"]),
    ("url-without-port-number", lambda home: "socket://board.local", ["needs a host and a port number"]),
    ("url-port-out-of-range", lambda home: "socket://127.0.0.1:99999", ["needs a host and a port number"]),
    ("nothing-listening", lambda home: "socket://127.0.0.1:9", ["socket://127.0.0.1:9"]),
    ("host-that-does-not-resolve", lambda home: "socket://no-such-board.invalid:23",
     ["cannot find the host no-such-board.invalid", "does not resolve"]),
    ("url-option-pyserial-lacks", lambda home: "socket://127.0.0.1:23?speed=fast", ["bad option in the port URL"]),
    ("rfc2217-option-pyserial-lacks", lambda home: "rfc2217://127.0.0.1:9?bogus", ["bad option in the port URL"]),
    ("dev-null", lambda home: "/dev/null", ["/dev/null is not a serial port", "not a terminal"]),
    ("a-regular-file", _regular_file, ["port.txt is not a serial port: it is a regular file"]),
    ("a-fifo", _fifo, ["fifo.port is not a serial port: it is a FIFO"]),
    ("a-folder", lambda home: ".", [". is not a serial port: it is a folder"]),
    ("no-such-device", lambda home: "/dev/ttyDEADRECKON9", ["no such port /dev/ttyDEADRECKON9"]),
]


@pytest.mark.parametrize("command", ["flash", "upload"])
@pytest.mark.parametrize("port,phrases", [case[1:] for case in PORT_NAMES], ids=[case[0] for case in PORT_NAMES])
def test_a_port_that_is_not_a_port(built, tmp_path, command, port, phrases):
    home = tmp_path / "home"
    shutil.copytree(built, home, symlinks=True)
    name = port(home)
    before = snapshot(home)
    assert_refused(run_cli(command, "out", "--port", name, cwd=home, timeout=QUICK_BOUND_S), *phrases)
    assert snapshot(home) == before


@pytest.mark.parametrize("command", ["flash", "upload"])
def test_an_rfc2217_url_to_a_port_that_does_not_speak_it(built, command):
    before = snapshot(built)
    with BadPort("silent") as port:
        url = port.url.replace("socket://", "rfc2217://")
        outcome = run_cli(command, "out", "--port", url, cwd=built, timeout=PORT_BOUND_S)
    assert_refused(outcome, "does not speak RFC 2217", bound=PORT_BOUND_S)
    assert snapshot(built) == before


# --- the two waits no peer above can reach: a port that stops taking writes, an esptool that goes silent -----


def test_a_port_that_stops_taking_writes(built, monkeypatch):
    """A board whose UART stopped draining: the write times out and the upload ends with a clear error."""
    from codegen.deploy import upload as uploader
    from codegen.errors import UserError

    monkeypatch.setattr(uploader, "WRITE_TIMEOUT_S", 1.0)

    def enter_then_flood(repl):
        repl.serial.write(b"x" * (256 * 1024 * 1024))  # more than any socket buffer holds

    monkeypatch.setattr(uploader.RawRepl, "enter", enter_then_flood)
    with BadPort("deaf") as port:
        started = time.monotonic()
        with pytest.raises(UserError, match="stopped taking data"):
            uploader.upload_folder(built / "out" / "build" / "app", port.url, progress=lambda _: None)
    assert time.monotonic() - started < QUICK_BOUND_S


def test_esptool_going_silent_is_stopped(tmp_path):
    """esptool that prints nothing for the silence limit is killed, and its stall becomes a clear error."""
    from codegen.board.loader import default_board
    from codegen.deploy.flash import classify, run_esptool

    command = [sys.executable, "-c", "import time; print('esptool v5', flush=True); time.sleep(120)"]
    started = time.monotonic()
    status, output = run_esptool(command, lambda _: None, "ESP32", silence_s=1.0)
    assert time.monotonic() - started < 10 and status != 0
    error = classify(output, "/dev/ttyUSB0", default_board(), [])
    assert error is not None and "stopped answering" in error.message and "printed nothing for 1 s" in error.message


def test_esptool_tracebacks_are_not_shown(tmp_path):
    """A Python traceback esptool prints stays out of what the user sees (it is kept for the diagnosis)."""
    from codegen.deploy.flash import run_esptool

    script = "import sys; print('esptool v5'); raise ValueError('invalid URL, protocol foo not known')"
    shown: list[str] = []
    status, output = run_esptool([sys.executable, "-c", script], shown.append, "ESP32", silence_s=30.0)
    assert status != 0 and "Traceback" in output and "ValueError" in output
    assert shown == ["  esptool v5"]
