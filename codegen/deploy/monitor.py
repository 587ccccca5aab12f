"""`deadreckon monitor` (alias `logs`): the board's console, decoded into a live status (codegen/deploy/console.py)
or, with `--raw`, the bytes as they come.

The port is opened without touching DTR/RTS (which would reset an ESP32 or hold it in its bootloader). When the
port goes away (a board with native USB re-enumerates on every reset, a TCP bridge drops), the monitor says so and
opens it again as soon as it is back; Ctrl-] (or Ctrl-C) ends it. Lines the decoder does not know are printed as
they are, so nothing the board says is hidden.
"""

from __future__ import annotations

import os
import select
import sys
import time
from typing import Callable, Optional, TextIO

from codegen.deploy.console import ConsoleStatus, event_text
from codegen.deploy.ports import close_quietly, open_port
from codegen.errors import UserError

QUIT_KEY = 0x1D  # Ctrl-]
RECONNECT_EVERY_S = 0.5
QUIET_KINDS = ("WIN", "DIAG")  # shown in the status line, not printed one by one (WIN comes every window)
MAX_LINE_BYTES = 4096  # a line longer than this is printed in pieces (a board printing binary, a wrong baud rate)


class _Keys:
    """Ctrl-] from a terminal (cbreak mode, so the key arrives alone; Ctrl-C still interrupts), or nothing."""

    def __init__(self, stream: Optional[TextIO]):
        self.fd = None
        self.saved = None
        if stream is None:
            return
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):
            return
        if not os.isatty(fd):
            return
        import termios
        import tty

        self.fd = fd
        self.saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)

    def quit_pressed(self) -> bool:
        if self.fd is None:
            return False
        ready, _, _ = select.select([self.fd], [], [], 0)
        return bool(ready) and QUIT_KEY in os.read(self.fd, 64)

    def restore(self) -> None:
        if self.fd is not None and self.saved is not None:
            import termios

            termios.tcsetattr(self.fd, termios.TCSADRAIN, self.saved)


class _Printer:
    """Event lines scroll; on a terminal the status line stays at the bottom, redrawn in place."""

    def __init__(self, out: TextIO, colour: bool, live: bool):
        self.out = out
        self.colour = colour
        self.live = live
        self.shown = ""

    def line(self, text: str) -> None:
        if self.live and self.shown:
            self.out.write("\r\x1b[K")
        self.out.write(text + "\n")
        if self.live and self.shown:
            self.out.write(self.shown)
        self.out.flush()

    def status(self, text: str) -> None:
        if self.live:
            self.shown = text
            self.out.write("\r\x1b[K" + text)
            self.out.flush()
        elif text != self.shown:
            self.shown = text
            self.line("status: " + text)

    def close(self) -> None:
        if self.live and self.shown:
            self.out.write("\n")
            self.out.flush()


def monitor(port: str, raw: bool = False, out: TextIO = sys.stdout, keys: Optional[TextIO] = sys.stdin,
            colour: Optional[bool] = None, until: Optional[Callable[[ConsoleStatus], bool]] = None,
            timeout: Optional[float] = None, reconnect: bool = True, wait_s: float = 0.0) -> ConsoleStatus:
    """Show the console of the board on `port` until Ctrl-], `until(status)` is true, or `timeout` seconds passed;
    return what was decoded. A lost port is reopened (unless reconnect=False: then a UserError). `wait_s`: how long
    a port that is not there yet is waited for (a board with native USB comes back a moment after a flash)."""
    import serial

    live = bool(getattr(out, "isatty", lambda: False)())
    colour = live and not os.environ.get("NO_COLOR") if colour is None else colour
    printer = _Printer(out, colour, live and not raw)
    status = ConsoleStatus()
    started = time.monotonic()
    key_reader = _Keys(keys)
    pending = b""
    handle = _open_waiting(port, wait_s)
    printer.line(f"monitoring {port} (quit: Ctrl-])")

    def take(line: bytes) -> None:
        text = line.decode("utf-8", "replace").rstrip("\r")
        event = status.feed(text)
        if event is None:
            printer.line(text)
        elif event.kind not in QUIET_KINDS:
            printer.line(event_text(event, colour))
        if event is not None and (printer.live or event.kind == "DIAG"):
            printer.status(status.status_line(_width()))

    try:
        while True:
            if key_reader.quit_pressed():
                break
            if until is not None and until(status):
                break
            if timeout is not None and time.monotonic() - started > timeout:
                break
            try:
                chunk = handle.read(max(1, min(handle.in_waiting, 4096)))
            except (serial.SerialException, OSError) as exc:
                close_quietly(handle)
                if not reconnect:
                    raise UserError(f"the connection to the board on {port} was lost: {exc}",
                                    hint="check the cable; `deadreckon monitor` reconnects on its own") from None
                if pending:
                    take(pending)
                    pending = b""
                printer.line(f"-- {port} went away ({exc}); waiting for it to come back")
                handle = _reopen(port, key_reader, until, status, started, timeout)
                if handle is None:
                    break
                printer.line(f"-- {port} is back")
                continue
            if not chunk:
                continue
            if raw:
                stream = getattr(out, "buffer", None)
                if stream is not None:
                    stream.write(chunk)
                else:
                    out.write(chunk.decode("utf-8", "replace"))
                out.flush()
            pending += chunk
            while b"\n" in pending or len(pending) > MAX_LINE_BYTES:
                line, sep, rest = pending.partition(b"\n")
                if not sep:
                    line, rest = pending[:MAX_LINE_BYTES], pending[MAX_LINE_BYTES:]
                pending = rest
                if raw:
                    status.feed(line.decode("utf-8", "replace"))
                else:
                    take(line)
    finally:
        key_reader.restore()
        close_quietly(handle)
        printer.close()
    return status


def _reopen(port, key_reader, until, status, started, timeout):
    """The port opened again once it is back; None when the user quit or the time is up meanwhile."""
    while True:
        if key_reader.quit_pressed() or (until is not None and until(status)):
            return None
        if timeout is not None and time.monotonic() - started > timeout:
            return None
        try:
            return open_port(port)
        except UserError:
            time.sleep(RECONNECT_EVERY_S)


def _open_waiting(port: str, wait_s: float):
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return open_port(port)
        except UserError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(RECONNECT_EVERY_S)


def _width() -> int:
    try:
        return os.get_terminal_size().columns
    except OSError:
        return 80
