"""Port detection by USB VID:PID (codegen/deploy/ports.py), on pyserial's own ListPortInfo records."""

from __future__ import annotations

import pytest
from serial.tools.list_ports_common import ListPortInfo

from codegen.deploy.ports import choose_port, list_serial_ports
from codegen.errors import UserError


def port(device, vid=None, pid=None, description="n/a"):
    info = ListPortInfo(device, skip_link_detection=True)
    info.vid, info.pid, info.description = vid, pid, description
    return info


BRIDGES = [("/dev/ttyUSB0", 0x10C4, 0xEA60), ("/dev/ttyACM0", 0x1A86, 0x55D4), ("/dev/ttyUSB1", 0x1A86, 0x7523),
           ("/dev/ttyACM1", 0x2E8A, 0x0005), ("/dev/ttyACM2", 0x303A, 0x1001)]


@pytest.mark.parametrize("device,vid,pid", BRIDGES)
def test_the_one_board_is_found_by_its_usb_id(device, vid, pid):
    others = [port("/dev/ttyS0"), port("/dev/ttyUSB9", 0x0BDA, 0x8153, "Realtek ethernet")]
    assert choose_port(None, others + [port(device, vid, pid)]) == device


def test_a_given_port_is_used_as_it_is():
    assert choose_port("socket://127.0.0.1:2000", []) == "socket://127.0.0.1:2000"


def test_several_boards_are_listed():
    with pytest.raises(UserError) as failure:
        choose_port(None, [port(d, v, p) for d, v, p in BRIDGES[:2]] + [port("/dev/ttyS0")])
    message = failure.value.message
    assert message.startswith("2 boards are plugged in")
    assert "/dev/ttyUSB0 (10c4:ea60, CP210x" in message and "/dev/ttyACM0 (1a86:55d4, CH9102" in message
    assert "ttyS0" not in message and "--port /dev/ttyACM0" in failure.value.hint


def test_no_board_lists_the_other_ports():
    with pytest.raises(UserError) as failure:
        choose_port(None, [port("/dev/ttyS0"), port("/dev/ttyUSB3", 0x0BDA, 0x8153, "Realtek ethernet")])
    assert failure.value.message.startswith("no board found")
    assert "/dev/ttyUSB3 (0bda:8153, Realtek ethernet)" in failure.value.message
    assert "--port" in failure.value.hint
    with pytest.raises(UserError, match="no board found: no USB serial port with a known bridge .*\\)$"):
        choose_port(None, [])


def test_known_bridges_sort_first():
    found = list_serial_ports([port("/dev/ttyS0"), port("/dev/ttyUSB0", 0x10C4, 0xEA60)])
    assert [p.device for p in found] == ["/dev/ttyUSB0", "/dev/ttyS0"]


def test_upload_without_a_port_looks_for_the_board(tmp_path, capsys, monkeypatch):
    from codegen.cli import main

    monkeypatch.setattr("serial.tools.list_ports.comports", lambda: [port("/dev/ttyS0")])
    assert main(["upload", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no board found") and "/dev/ttyS0" in err and "Traceback" not in err
