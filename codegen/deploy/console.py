"""The app's console lines (templates/micropython/app.py.j2 and the modules it drives), decoded into what a person
watching the device wants to know: mode, fix, satellites, position, speed, drops, heap, kernel, warnings.

docs/console.md documents every line. Decoding is pure: `ConsoleStatus.feed(line)` takes one line (without its
line ending) and returns the `Event` it was, or None for a line that changes nothing; `status_line()` and
`event_text()` render for a terminal, in colour when asked. `deadreckon monitor` (codegen/deploy/monitor.py) reads
the port and calls these.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Optional

# levels an event is shown with
INFO, NOTE, WARNING, ERROR = "info", "note", "warning", "error"
COLOURS = {NOTE: "\x1b[36m", WARNING: "\x1b[33m", ERROR: "\x1b[31;1m"}
RESET_COLOUR = "\x1b[0m"
WARNINGS_KEPT = 8  # as many as the app keeps (app.py.j2 _WARNINGS_KEPT)

_WIN = re.compile(r"^WIN (?P<index>\d+) mode=(?P<mode>\w+) n=(?P<count>\d+) e=(?P<e>\S+) n=(?P<n>\S+) u=(?P<u>\S+) "
                  r"ve=(?P<ve>\S+) vn=(?P<vn>\S+) vu=(?P<vu>\S+) lat=(?P<lat>-?\d+) lon=(?P<lon>-?\d+) "
                  r"us=(?P<us>\d+) ticks_ms=(?P<ticks_ms>\d+)$")
_PAIR = re.compile(r"(\w+)=(\S+)")
_MODE = re.compile(r"^MODE (\w+) -> (\w+)$")
# what a board prints when it starts again (ESP32 ROM, MicroPython's soft reset, RP2040/CircuitPython banners)
_RESTARTS = ("rst:0x", "ets ", "MPY: soft reboot", "soft reboot", "Auto-reload", "code.py output:")


@dataclass
class Event:
    kind: str  # the line's first word: WIN, DIAG, MODE, WARN, DEADRECKON, CAL, TEST, FATAL, RESET, ...
    level: str
    text: str  # the line as the device printed it


@dataclass
class ConsoleStatus:
    """What the console said so far. Position in 1e-7 degrees (as the app prints it), offsets in metres ENU from
    the last fix, speeds in m/s."""

    board: Optional[str] = None
    kernel: Optional[str] = None  # native | python
    imu: Optional[str] = None
    display: Optional[str] = None
    mode: Optional[str] = None  # GPS | IMU | TEST
    calibrating: bool = False
    test_mode: bool = False
    fixes: int = 0
    sats: Optional[int] = None
    gps_speed: Optional[float] = None
    lat_e7: Optional[int] = None
    lon_e7: Optional[int] = None
    enu: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the kernel's, East North Up
    windows: int = 0
    rate_hz: Optional[float] = None
    dropped: int = 0
    heap_free: Optional[int] = None
    log_blocks: Optional[int] = None
    bad_checksum: int = 0
    starts: int = 0  # DEADRECKON banners seen: the app (re)started
    restarts: int = 0  # reset messages from the board (ROM, soft reboot)
    warnings: list[str] = field(default_factory=list)
    fatal: Optional[str] = None
    in_traceback: bool = False

    @property
    def has_fix(self) -> bool:
        return self.mode == "GPS" and self.fixes > 0

    @property
    def speed(self) -> Optional[float]:
        """The speed the device's screen shows: the GPS's in GPS mode, the dead-reckoned one otherwise."""
        if self.mode == "GPS":
            return self.gps_speed
        if self.windows == 0:
            return None
        return math.hypot(self.velocity[0], self.velocity[1])

    def _warn(self, text: str) -> None:
        self.warnings.append(text)
        del self.warnings[:-WARNINGS_KEPT]

    def feed(self, line: str) -> Optional[Event]:
        """Take one console line; return what it was, or None when it is not one of the app's."""
        line = line.rstrip("\r\n")
        head = line.split(" ", 1)[0]
        rest = line[len(head) + 1:]
        if self.in_traceback:
            if line.startswith(("Traceback", "  ")):
                return Event("TRACEBACK", ERROR, line)
            self.in_traceback = False
            if line and not line.startswith(("DEADRECKON", "WIN", "DIAG", "MODE", "WARN")):
                self.fatal = line  # the exception's last line: "OSError: [Errno 5] EIO"
                return Event("TRACEBACK", ERROR, line)
        if head == "WIN":
            m = _WIN.match(line)
            if not m:
                return Event("GARBLED", NOTE, line)
            self.windows = int(m["index"])
            self.mode = m["mode"]
            self.enu = (float(m["e"]), float(m["n"]), float(m["u"]))
            self.velocity = (float(m["ve"]), float(m["vn"]), float(m["vu"]))
            if int(m["lat"]) or int(m["lon"]):
                self.lat_e7, self.lon_e7 = int(m["lat"]), int(m["lon"])
            return Event("WIN", INFO, line)
        if head == "DIAG":
            values = dict(_PAIR.findall(rest))
            try:
                self.rate_hz = float(values["rate"].rstrip("Hz"))
                self.dropped = int(values["dropped"])
                self.mode = values.get("mode", self.mode)
                self.fixes = int(values["fixes"])
                self.heap_free = int(values["heap_free"])
                self.log_blocks = int(values["log_blocks"])
                self.bad_checksum = int(values.get("bad_checksum", 0))
                if "sats" in values:
                    self.sats = int(values["sats"])
                if "gps_speed" in values:
                    self.gps_speed = float(values["gps_speed"])
            except (KeyError, ValueError):
                return Event("GARBLED", NOTE, line)
            return Event("DIAG", INFO, line)
        if head == "MODE":
            m = _MODE.match(line)
            if not m:
                return Event("GARBLED", NOTE, line)
            self.mode = m[2]
            return Event("MODE", NOTE, line)
        if head == "WARN":
            self._warn(rest)
            return Event("WARN", WARNING, line)
        if head == "DEADRECKON":
            values = dict(_PAIR.findall(rest))
            self.board, self.kernel = values.get("board"), values.get("kernel")
            self.imu, self.display = values.get("imu"), values.get("display")
            self.starts += 1
            self.mode, self.fixes, self.windows, self.fatal = "GPS", 0, 0, None
            self.calibrating = True  # the app calibrates at start (a "CAL start" line follows)
            level = WARNING if self.kernel == "python" else NOTE
            return Event("DEADRECKON", level, line)
        if head == "CAL":
            self.calibrating = rest.startswith(("start", "moved"))
            return Event("CAL", WARNING if rest.startswith("moved") else NOTE, line)
        if head == "TEST":
            self.test_mode = rest == "on"
            return Event("TEST", NOTE, line)
        if head == "FATAL":
            self.fatal = "FATAL"
            self.in_traceback = True
            return Event("FATAL", ERROR, line)
        if line.startswith("Traceback"):
            self.in_traceback = True
            return Event("TRACEBACK", ERROR, line)
        if head in ("IMU", "DISPLAY", "LOG") and rest.startswith(("missing", "lost", "disabled")):
            return Event(head, WARNING, line)
        if line == "no watchdog on this port":
            return Event("WATCHDOG", WARNING, line)
        if line.startswith(_RESTARTS):
            self.restarts += 1
            return Event("RESET", NOTE, line)
        return None

    def status_line(self, width: int = 80) -> str:
        """One line: mode and fix, kernel, satellites, speed, position, offset, drops, heap (cut to `width`)."""
        if self.starts == 0 and self.mode is None:
            return "waiting for the app (DEADRECKON line)"[:width]
        mode = self.mode or "?"
        if self.calibrating:
            mode = "CAL " + mode
        if self.test_mode:
            mode += " test"
        parts = [mode + (" fix" if self.has_fix else " no fix")]
        if self.kernel:
            parts.append(self.kernel)
        if self.fatal:
            parts.append("FATAL")
        if self.sats is not None:
            parts.append(f"sats {self.sats}")
        speed = self.speed
        if speed is not None:
            parts.append(f"{speed:.2f} m/s")
        if self.lat_e7 is not None and self.lon_e7 is not None:
            parts.append(f"{abs(self.lat_e7) / 1e7:.5f}{'N' if self.lat_e7 >= 0 else 'S'} "
                         f"{abs(self.lon_e7) / 1e7:.5f}{'E' if self.lon_e7 >= 0 else 'W'}")
        if self.mode in ("IMU", "TEST"):
            parts.append(f"E{self.enu[0]:+.1f} N{self.enu[1]:+.1f} m")
        parts.append(f"drop {self.dropped}")
        if self.heap_free is not None:
            parts.append(f"heap {self.heap_free // 1024}K")
        text = "  ".join(parts)
        return text if len(text) <= width else text[: max(0, width - 1)] + "…"


def event_text(event: Event, colour: bool) -> str:
    """The line as printed, coloured by its level when `colour`."""
    code = COLOURS.get(event.level) if colour else None
    return f"{code}{event.text}{RESET_COLOUR}" if code else event.text
