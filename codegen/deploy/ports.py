"""Serial ports: which board is where (USB VID:PID), whether a name can be a port, and opening one without
resetting the board. `flash`, `upload`, `monitor`, `pull` and `run` all take their port from here.

A port is a device path (/dev/ttyUSB0, /dev/ttyACM0, COM3) or a pyserial URL (socket://HOST:PORT,
rfc2217://HOST:PORT). Without `--port`, the USB serial devices are listed (pyserial's list_ports) and those whose
VID:PID is a bridge the bundled boards carry are the candidates: exactly one is used; none or several is an error
that lists what is there.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from typing import Optional

from codegen.errors import UserError

PORT_TIMEOUT_S = 0.05  # one read waits this long for a byte
WRITE_TIMEOUT_S = 10.0  # a write the port does not take within this is a dead port

# USB VID:PID of the serial bridges on the bundled boards (and the chips' own USB); a PID of None is any product
KNOWN_BRIDGES: tuple[tuple[int, Optional[int], str], ...] = (
    (0x10C4, 0xEA60, "CP210x USB-UART (T-Beam v1.x, Heltec, most ESP32 DevKits)"),
    (0x1A86, 0x55D4, "CH9102 USB-UART (T-Beam v1.2, LilyGO boards)"),
    (0x1A86, 0x7523, "CH340 USB-UART"),
    (0x0403, 0x6001, "FTDI FT232 USB-UART"),
    (0x2E8A, 0x0005, "RP2040 running MicroPython"),
    (0x303A, None, "ESP32-S2/S3 native USB"),
)

DIALOUT_HINT = "add yourself to the port's group (`sudo usermod -aG dialout $USER`, then log in again)"
BUSY_HINT = "another program holds it (a serial monitor, mpremote, screen, an IDE): close it and try again"


@dataclass(frozen=True)
class FoundPort:
    device: str
    vid: Optional[int]
    pid: Optional[int]
    description: str
    known: Optional[str]  # the bridge it is, when its VID:PID is one of KNOWN_BRIDGES

    def label(self) -> str:
        ids = f"{self.vid:04x}:{self.pid:04x}" if self.vid is not None and self.pid is not None else "no USB id"
        return f"{self.device} ({ids}, {self.known or self.description or 'unknown device'})"


def is_url(port: str) -> bool:
    return "://" in port


def bridge_name(vid: Optional[int], pid: Optional[int]) -> Optional[str]:
    """The name of the known bridge with this USB VID:PID, or None."""
    for known_vid, known_pid, name in KNOWN_BRIDGES:
        if vid == known_vid and (known_pid is None or pid == known_pid):
            return name
    return None


def list_serial_ports(comports=None) -> list[FoundPort]:
    """Every serial port pyserial sees (or the given list_ports entries), known bridges first, by device name."""
    if comports is None:
        try:
            from serial.tools import list_ports

            comports = list_ports.comports()
        except Exception:  # noqa: BLE001 - no sysfs, no permission: there is nothing to list
            comports = []
    found = [FoundPort(c.device, c.vid, c.pid, c.description if c.description != "n/a" else "",
                       bridge_name(c.vid, c.pid)) for c in comports]
    return sorted(found, key=lambda p: (p.known is None, p.device))


def choose_port(port: Optional[str], comports=None) -> str:
    """`port` when given; else the one serial port whose USB VID:PID is a known bridge. None or several: a
    UserError listing what there is."""
    if port:
        return port
    found = list_serial_ports(comports)
    boards = [p for p in found if p.known]
    if len(boards) == 1:
        return boards[0].device
    if boards:
        raise UserError(f"{len(boards)} boards are plugged in: " + "; ".join(p.label() for p in boards),
                        hint=f"choose one with --port, e.g. --port {boards[0].device}")
    others = "; ".join(p.label() for p in found)
    raise UserError("no board found: no USB serial port with a known bridge (CP210x, CH9102, CH340, FTDI, RP2040, "
                    "ESP32-S3 USB)" + (f"; other serial ports: {others}" if others else ""),
                    hint="plug the board in with a data (not charge-only) cable, or name the port with --port")


def ports_hint() -> str:
    names = [p.label() for p in list_serial_ports()]
    if names:
        return "serial ports here: " + "; ".join(names)
    return "no serial ports found: is the board plugged in with a data (not charge-only) cable?"


def rfc2217_refused(port: str) -> UserError:
    return UserError(f"the server at {port} does not speak RFC 2217 (it did not negotiate the serial options)",
                     hint="a plain TCP serial bridge is socket://HOST:PORT; rfc2217:// needs ser2net in telnet mode "
                          "or esp_rfc2217_server")


def not_a_port(port: str, kind: str = "a device that is not a terminal") -> UserError:
    return UserError(f"{port} is not a serial port: it is {kind}",
                     hint="a board's port is a terminal device (/dev/ttyUSB0, /dev/ttyACM0, COM3) or a URL "
                          "(socket://HOST:PORT)")


def check_port_path(port: str) -> None:
    """A local port must be a terminal device: refuse a regular file, a folder, a FIFO or a device that is not a
    tty (/dev/null, /dev/zero) with a message about ports, before pyserial tries to configure it."""
    try:
        mode = os.stat(port).st_mode
    except OSError:
        return  # missing: the caller says "no such port" with the ports it can see
    if stat.S_ISCHR(mode):
        return  # a character device: pyserial finds out whether it is a terminal (see not_a_port)
    kind = ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else
            "a regular file" if stat.S_ISREG(mode) else "a socket" if stat.S_ISSOCK(mode) else "a block device")
    raise not_a_port(port, kind)


def check_port_url(port: str) -> None:
    """A pyserial URL that pyserial can open (socket://host:port, rfc2217://host:port, ...), or a UserError."""
    if not is_url(port):
        return
    import urllib.parse

    import serial

    scheme = port.split("://", 1)[0]
    if scheme.lower() == "loop":
        raise UserError(f"--port {port} is pyserial's loopback, which answers with what it is sent: no board is "
                        "behind it", hint="give the board's port (/dev/ttyUSB0, /dev/ttyACM0, COM3) or a bridge's URL "
                                          "(socket://HOST:PORT)")
    try:
        serial.serial_for_url(port, do_not_open=True)  # checks the scheme (hwgrep:// also looks for the port)
    except (ValueError, serial.SerialException) as exc:
        if "not known" not in str(exc):
            raise open_failure(port, str(exc)) from None
        raise UserError(f"unknown port URL scheme {scheme + '://'!r} in {port}", hint=URL_HINT) from None
    if scheme.lower() in ("socket", "rfc2217"):
        parts = urllib.parse.urlsplit(port)
        try:
            number = parts.port
        except ValueError:
            number = None
        if not parts.hostname or not number:
            raise UserError(f"bad port URL {port}: it needs a host and a port number 1-65535",
                            hint=f"write it as {scheme}://HOST:PORT, e.g. {scheme}://192.168.4.1:23")


def check_port(port: str) -> None:
    """Fail early, with the fix, when a port URL is malformed, or a local serial device is missing, not ours to
    open, or busy (esptool opens the port itself: this is what it would fail on, said plainly)."""
    if is_url(port):
        check_port_url(port)
        return
    check_port_path(port)
    if not os.path.exists(port):
        raise UserError(f"no such port {port}", hint=ports_hint())
    if not os.access(port, os.R_OK | os.W_OK):
        raise UserError(f"permission denied on {port}", hint=DIALOUT_HINT)
    try:
        import serial

        handle = serial.Serial()
        handle.port = port
        handle.exclusive = True
        handle.dtr = False  # do not reset the board just by looking
        handle.rts = False
        handle.open()
        handle.close()
    except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException, OSError, ValueError
        raise open_failure(port, str(exc)) from None


def open_port(port: str, baud: int = 115200):
    """Open a serial port or pyserial URL without resetting the board; UserError with the fix if it fails."""
    import serial

    if is_url(port):
        check_port_url(port)
    else:
        check_port_path(port)
    try:
        if is_url(port):
            # pyserial's rfc2217 refuses write_timeout; its socket has a 5 s timeout of its own on every send
            write_timeout = None if port.lower().startswith("rfc2217://") else WRITE_TIMEOUT_S
            handle = serial.serial_for_url(port, baudrate=baud, timeout=PORT_TIMEOUT_S, write_timeout=write_timeout,
                                           do_not_open=True)
        else:
            handle = serial.Serial(baudrate=baud, timeout=PORT_TIMEOUT_S, write_timeout=WRITE_TIMEOUT_S)
            handle.port = port
            handle.exclusive = True
        handle.dtr = False  # with auto-reset circuits, DTR/RTS would reset or hold the ESP32 in its bootloader
        handle.rts = False
        handle.open()
        sock = getattr(handle, "_socket", None)  # socket:// ports: no Nagle delay on small writes
        if sock is not None:
            import socket

            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return handle
    except (serial.SerialException, OSError, ValueError) as exc:
        raise open_failure(port, str(exc)) from None


URL_HINT = ("ports are device paths (/dev/ttyUSB0, COM3) or pyserial URLs: socket://HOST:PORT, rfc2217://HOST:PORT; "
            "socket:// takes only ?logging=LEVEL, rfc2217:// also ign_set_control, poll_modem and timeout=SECONDS")


def open_failure(port: str, text: str) -> UserError:
    """What pyserial's message `text` on opening `port` means, said plainly with the fix (its own words stay in the
    message for what this does not know)."""
    lower = text.lower()
    if is_url(port):
        import urllib.parse

        host = urllib.parse.urlsplit(port).hostname or port
        # getaddrinfo's failures: EAI_NONAME (-2), EAI_AGAIN (-3), EAI_NODATA (-5); Windows' WSAHOST_NOT_FOUND
        if any(mark in lower for mark in ("name or service not known", "nodename nor servname", "errno -2]",
                                           "errno -3]", "errno -5]", "errno 11001]", "temporary failure in name")):
            return UserError(f"cannot find the host {host} of {port}: its name does not resolve",
                             hint="check the name, or give the bridge's IP address (socket://192.168.4.1:23)")
        if "unknown option" in lower or "expected a string in the form" in lower or "debug|info" in lower:
            return UserError(f"bad option in the port URL {port}", hint=URL_HINT)
        if "timed out" in lower:
            return UserError(f"no answer from {host} ({port}) in time",
                             hint="is the bridge on this network and switched on?")
    if "no such file" in lower or "could not open port" in lower and "errno 2]" in lower:
        return UserError(f"no such port {port}", hint=ports_hint())
    if "permission denied" in lower or "errno 13]" in lower:
        return UserError(f"permission denied on {port}", hint=DIALOUT_HINT)
    if "busy" in lower or "exclusively lock" in lower:
        return UserError(f"port {port} is busy", hint=BUSY_HINT)
    if "refused" in lower:
        return UserError(f"nothing answers at {port}", hint="is the bridge or telnet server running?")
    if "inappropriate ioctl" in lower:  # termios on /dev/null, /dev/zero and other non-terminals
        return not_a_port(port)
    if "does not seem to support rfc2217" in lower:
        return rfc2217_refused(port)
    return UserError(f"cannot open {port}: {text}",
                     hint="check the cable and that the board is powered; " + ports_hint() if not is_url(port)
                     else URL_HINT)


def close_quietly(handle) -> None:
    """Close a port that may already be gone (a board reset, a cable pulled)."""
    import serial

    try:
        handle.close()
    except (serial.SerialException, OSError):
        pass
