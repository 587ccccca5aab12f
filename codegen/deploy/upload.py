"""`deadreckon upload OUT --port PORT`: the built app onto a board already running MicroPython, by raw REPL.

The raw REPL (MicroPython docs, "raw mode and raw-paste mode"): Ctrl-C stops the running program, Ctrl-A enters
raw mode ("raw REPL; CTRL-B to exit" then ">"), the host sends code and Ctrl-D, the board answers "OK", the
program's stdout, \\x04, its stderr (a traceback), \\x04 and ">" again. Raw-paste mode (\\x05A\\x01, answered
"R\\x01" + a 16-bit window size) adds flow control: the host sends a window of bytes and waits for \\x01 before
the next; it is used where the board offers it, and standard raw mode (written in small, paced chunks) otherwise.

Only files whose SHA-256 differs from the board's copy are sent, each to a temporary name and renamed into place,
so an interrupted upload never leaves half a module. A `.py` on the board that would shadow a new `.mpy` of the
same module (MicroPython imports `.py` first) is removed, and the other way round. A soft reset ends the upload,
which starts the app. Ports may be device paths or pyserial URLs (`socket://host:port`, `rfc2217://host:port`).

A port is not trusted to behave: every read has a deadline and a size bound (a device that talks continuously, a
GPS module say, is told apart from a silent one), every write a timeout, and a port that closes or drops ends the
upload with a UserError, never a traceback.
"""

from __future__ import annotations

import base64
import hashlib
import re
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from codegen.deploy.ports import PORT_TIMEOUT_S, WRITE_TIMEOUT_S, close_quietly, open_port
from codegen.deploy.watchdog import hold_watchdog
from codegen.errors import UserError

Progress = Callable[[str], None]

RAW_BANNER = b"raw REPL; CTRL-B to exit\r\n"
CHUNK = 2048  # file bytes per REPL command (base64 makes it ~2.7 kB of code), small for a board's heap
PACED_WRITE = 256  # bytes per write in standard raw mode, with a pause, so a board's UART buffer keeps up
PACE_SECONDS = 0.01
KEEP_AS_SOURCE = ("main.py", "boot.py")
# Every wait has an end. A board that keeps talking extends a wait for an answer, but never past twice its timeout;
# a reply is at most 1 MiB (our commands print a few KB); a write the port does not take within WRITE_TIMEOUT_S
# (codegen.deploy.ports) is a dead port; the quiet wait before entering the raw REPL and the discarding of old input
# stop after a second.
TALKING_GRACE_FACTOR = 2.0
MAX_REPLY_BYTES = 1024 * 1024
QUIET_LIMIT_S = 1.0
CHATTER_BYTES = 2048  # more than this arriving while we try to enter the raw REPL: the device talks on its own


class ReplError(Exception):
    """The board answered, but not as a raw REPL should (or raised an exception running our code)."""


@dataclass
class UploadResult:
    sent: list[str] = field(default_factory=list)
    unchanged: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    raw_paste: bool = False
    seconds: float = 0.0


class RawRepl:
    """A raw-REPL session on an open pyserial port. Every read has a deadline and a size bound."""

    def __init__(self, serial, use_raw_paste: bool = True, paced: bool = True):
        self.serial = serial
        self.paced = paced  # a TCP link has its own flow control; a UART into a small buffer does not
        self.use_raw_paste = use_raw_paste
        self.raw_paste_used = False
        self.received = 0  # bytes read from the port so far
        self._buffer = b""
        # pyserial's socket:// reports in_waiting as 0 or 1; setting its timeout costs nothing (on a tty it would)
        self._socket_port = type(serial).__module__.endswith("protocol_socket")

    def _fill(self) -> bool:
        """Move what the port has (waiting up to its short timeout for one byte) into the buffer."""
        waiting = self.serial.in_waiting
        chunk = self.serial.read(max(1, min(waiting, 4096)))
        if chunk and waiting <= 1 and self._socket_port:  # a socket:// port says only "something": take the rest
            self.serial.timeout = 0
            try:
                chunk += self.serial.read(4096)
            finally:
                self.serial.timeout = PORT_TIMEOUT_S
        self._buffer += chunk
        self.received += len(chunk)
        if len(self._buffer) > MAX_REPLY_BYTES:
            raise ReplError(f"the board sent more than {MAX_REPLY_BYTES // 1024} KiB without the end of a reply "
                            "(is something printing continuously?)")
        return bool(chunk)

    def _take(self, count: int) -> bytes:
        data, self._buffer = self._buffer[:count], self._buffer[count:]
        return data

    def read_until(self, ending: bytes, timeout: float) -> bytes:
        """Everything up to and including the first `ending`; the rest stays buffered. A board still talking
        extends the wait, to at most TALKING_GRACE_FACTOR times `timeout`."""
        started = time.monotonic()
        deadline = started + timeout
        limit = started + TALKING_GRACE_FACTOR * timeout
        searched = 0
        while True:
            found = self._buffer.find(ending, searched)
            if found >= 0:
                return self._take(found + len(ending))
            searched = max(0, len(self._buffer) - len(ending) + 1)
            now = time.monotonic()
            if self._fill():
                deadline = min(limit, max(deadline, time.monotonic() + min(timeout, 1.0)))  # still talking
            elif now > deadline:
                raise ReplError(f"timed out waiting for {ending!r}; got {self._buffer[-80:]!r}")
            if now > limit:
                raise ReplError(f"the board kept talking for {now - started:.0f} s without sending {ending!r}; "
                                f"last: {self._buffer[-80:]!r}")

    def read_exact(self, count: int, timeout: float) -> bytes:
        deadline = time.monotonic() + timeout
        while len(self._buffer) < count:
            if not self._fill() and time.monotonic() > deadline:
                raise ReplError(f"timed out reading {count} bytes from the board; got {self._buffer!r}")
        return self._take(count)

    def waiting(self) -> bool:
        return bool(self._buffer) or self.serial.in_waiting > 0

    def drain(self, quiet: float = 0.1, limit: float = QUIET_LIMIT_S) -> bytes:
        """Read whatever the board prints until it has been quiet for `quiet` seconds, or `limit` seconds passed."""
        started = last = time.monotonic()
        while time.monotonic() - last < quiet and time.monotonic() - started < limit:
            if self._fill():
                last = time.monotonic()
        return self._take(len(self._buffer))

    def discard_input(self, limit: float = QUIET_LIMIT_S) -> None:
        """Forget what arrived so far (pyserial's reset_input_buffer never returns while a socket keeps talking)."""
        self._buffer = b""
        started = time.monotonic()
        while time.monotonic() - started < limit and self.serial.in_waiting:
            self.received += len(self.serial.read(4096))

    def enter(self) -> None:
        """Stop the running program and enter raw mode."""
        started, before = time.monotonic(), self.received
        for attempt in range(3):
            try:
                self.serial.write(b"\r\x03\x03")  # interrupt main.py (twice: one may land inside a handler)
                self.drain(0.1 + 0.2 * attempt)
                self.discard_input()
                self.serial.write(b"\r\x01")
                self.read_until(RAW_BANNER + b">", timeout=2.0)
                return
            except ReplError:
                self._buffer = b""
                continue
        heard = self.received - before
        if heard > CHATTER_BYTES:
            raise ReplError(f"the device talks continuously ({heard} bytes in {time.monotonic() - started:.1f} s) "
                            "but never answered as MicroPython's raw REPL: is it a GPS module, or a program that "
                            "ignores Ctrl-C?")
        raise ReplError("the board did not enter the raw REPL (is MicroPython running on it?)")

    def _send_raw_paste(self, code: bytes) -> bool:
        """Send `code` in raw-paste mode; False if the board refuses (then nothing was consumed)."""
        self.serial.write(b"\x05A\x01")
        answer = self.read_exact(2, timeout=2.0)
        if answer == b"R\x00":
            self.use_raw_paste = False
            return False
        if answer != b"R\x01":
            # a board older than raw-paste took the bytes as raw input; its Ctrl-A re-entered raw mode
            self.use_raw_paste = False
            if not (answer + self.drain(0.3)).endswith(RAW_BANNER + b">"):
                raise ReplError(f"the board answered {answer!r} to the raw-paste request")
            return False
        window = struct.unpack("<H", self.read_exact(2, timeout=2.0))[0]
        remaining = window
        index = 0
        while index < len(code):
            while remaining == 0 or self.waiting():
                byte = self.read_exact(1, timeout=5.0)
                if byte == b"\x01":
                    remaining += window
                elif byte == b"\x04":  # the board ended the paste early (a compile error is coming)
                    self.serial.write(b"\x04")
                    return True
                else:
                    raise ReplError(f"unexpected {byte!r} from the board during raw paste")
            piece = code[index : index + remaining]
            self.serial.write(piece)
            index += len(piece)
            remaining -= len(piece)
        self.serial.write(b"\x04")
        self.read_until(b"\x04", timeout=5.0)  # compiled: execution output follows
        self.raw_paste_used = True
        return True

    def exec(self, code: str | bytes, timeout: float = 10.0) -> bytes:
        """Run `code` on the board; return its stdout; raise ReplError with the board's traceback on error."""
        code = code.encode() if isinstance(code, str) else code
        if not (self.use_raw_paste and self._send_raw_paste(code)):
            code += b"\x04"
            for index in range(0, len(code), PACED_WRITE):
                self.serial.write(code[index : index + PACED_WRITE])
                if self.paced and len(code) > PACED_WRITE:
                    time.sleep(PACE_SECONDS)
            answer = self.read_exact(2, timeout=timeout)
            if answer != b"OK":
                raise ReplError(f"the board did not accept the code: {answer + self.drain(0.2)!r}")
        out = self.read_until(b"\x04", timeout)[:-1]
        err = self.read_until(b"\x04", timeout)[:-1]
        self.read_until(b">", timeout)
        if err:
            raise ReplError(err.decode("utf-8", "replace").strip())
        return out

    def soft_reset(self) -> bytes:
        """Leave raw mode and soft-reset, which runs boot.py and main.py."""
        self.serial.write(b"\x02")
        self.drain(0.1)
        self.serial.write(b"\x04")
        try:
            return self.read_until(b"soft reboot\r\n", timeout=3.0)
        except ReplError:
            return b""


HASH_SCRIPT = """
import os
try:
    import hashlib
except ImportError:
    hashlib = None
def _h(p):
    try:
        f = open(p, 'rb')
    except OSError:
        return '-'
    if hashlib is None:
        f.close()
        return '?'
    h = hashlib.sha256()
    b = bytearray(512)
    while True:
        n = f.readinto(b)
        if not n:
            break
        h.update(memoryview(b)[:n])
    f.close()
    return ''.join('%02x' % x for x in h.digest())
for _p in {paths!r}:
    print(_p, _h('/' + _p))
"""


def device_hashes(repl: RawRepl, paths: list[str]) -> dict[str, str]:
    """SHA-256 hex of each path on the board: '-' where absent, '?' where the board has no hashlib."""
    out = repl.exec(HASH_SCRIPT.format(paths=list(paths)), timeout=30.0).decode("utf-8", "replace")
    found = {}
    for line in out.splitlines():
        name, _, digest = line.strip().rpartition(" ")
        if name and (digest in ("-", "?") or re.fullmatch(r"[0-9a-f]{64}", digest)):
            found[name] = digest  # anything else (noise, another program's output) proves nothing: sent again
    return found


def ensure_dirs(repl: RawRepl, paths: list[str]) -> None:
    folders = sorted({"/".join(p.split("/")[:i]) for p in paths for i in range(1, p.count("/") + 1)},
                     key=lambda d: (d.count("/"), d))
    if not folders:
        return
    repl.exec(
        "import os\n"
        f"for _d in {folders!r}:\n"
        "    try:\n"
        "        os.mkdir('/' + _d)\n"
        "    except OSError:\n"
        "        pass\n"
    )


def send_file(repl: RawRepl, rel: str, data: bytes) -> None:
    """Write `data` to /rel on the board through a temporary file renamed into place."""
    target = "/" + rel
    part = target + ".part"
    repl.exec(f"import os, binascii\n_f = open({part!r}, 'wb')\n_w = _f.write\n_a = binascii.a2b_base64")
    try:
        for index in range(0, len(data), CHUNK):
            encoded = base64.b64encode(data[index : index + CHUNK])  # bytes: some ports take no str here
            repl.exec(f"_w(_a({encoded!r}))")
    finally:
        repl.exec("_f.close()")
    repl.exec(
        "try:\n"
        f"    os.remove({target!r})\n"
        "except OSError:\n"
        "    pass\n"
        f"os.rename({part!r}, {target!r})\n"
    )


def remove_files(repl: RawRepl, paths: list[str]) -> None:
    if paths:
        repl.exec(
            "import os\n"
            f"for _p in {paths!r}:\n"
            "    try:\n"
            "        os.remove('/' + _p)\n"
            "    except OSError:\n"
            "        pass\n"
        )


def shadows(rel: str) -> Optional[str]:
    """The other form of a module (`x.py` for `x.mpy` and back) that must not stay beside it."""
    if rel.endswith(".mpy"):
        return rel[:-4] + ".py"
    if rel.endswith(".py") and rel not in KEEP_AS_SOURCE:
        return rel[:-3] + ".mpy"
    return None


def local_files(app_dir: Path) -> dict[str, bytes]:
    return {
        p.relative_to(app_dir).as_posix(): p.read_bytes()
        for p in sorted(app_dir.rglob("*"))
        if p.is_file() and not p.name.endswith(".part")
    }


def upload_folder(app_dir: Path, port: str, force: bool = False, use_raw_paste: bool = True,
                  reset: bool = True, progress: Progress = print) -> UploadResult:
    """Make the board's filesystem root hold every file of `app_dir`; send only what differs."""
    started = time.monotonic()
    files = local_files(app_dir)
    if not files:
        raise UserError(f"{app_dir} is empty: nothing to upload", hint="run `deadreckon build OUT` first")
    import serial

    result = UploadResult()
    handle = open_port(port)
    try:
        repl = RawRepl(handle, use_raw_paste=use_raw_paste, paced=not port.startswith("socket://"))
        try:
            repl.enter()
            hold_watchdog(repl)  # the app's watchdog fed from a timer while the files go over
            others = sorted({s for s in map(shadows, files) if s and s not in files})
            on_board = device_hashes(repl, sorted(files) + others)
            stale = [p for p in others if on_board.get(p, "-") != "-"]
            remove_files(repl, stale)
            result.removed = stale
            for rel in stale:
                progress(f"  removed {rel} (it would shadow the new {shadows(rel)})")
            ensure_dirs(repl, sorted(files))
            for rel, data in files.items():
                digest = hashlib.sha256(data).hexdigest()
                if not force and on_board.get(rel) == digest:
                    result.unchanged.append(rel)
                    progress(f"  unchanged {rel}")
                    continue
                send_file(repl, rel, data)
                result.sent.append(rel)
                progress(f"  sent      {rel} ({len(data)} bytes)")
            if result.sent:
                check = device_hashes(repl, result.sent)
                expected = {rel: hashlib.sha256(files[rel]).hexdigest() for rel in result.sent}
                bad = [rel for rel in result.sent if check.get(rel) not in (expected[rel], "?")]
                if bad:
                    raise UserError(f"the board's copy of {', '.join(bad)} differs from what was sent to {port}",
                                    hint="run the upload again; check the board's filesystem has room (os.statvfs('/'))")
            result.raw_paste = repl.raw_paste_used
            if reset:
                repl.soft_reset()
        except ReplError as exc:
            text = str(exc)
            if "ENOSPC" in text or "28]" in text:
                raise UserError(f"the filesystem of the board on {port} is full", hint="remove files from the board, "
                                "or flash a fresh filesystem image with `deadreckon flash`")
            if "EROFS" in text or "30]" in text:  # CircuitPython: the drive is the computer's until boot.py takes it
                raise UserError("the board's filesystem is read-only to programs: a CircuitPython board gives its "
                                "CIRCUITPY drive to the computer unless boot.py remounts it",
                                hint="copy the app over USB: deadreckon upload OUT --drive PATH; after the next "
                                     "reset its boot.py takes the drive and the serial route works too")
            raise UserError(f"upload to {port} failed: {text.splitlines()[-1] if text else 'no answer'}",
                            hint="is MicroPython running on the board (not its bootloader, not another program "
                                 "holding the port)? Try again after pressing RESET")
        except serial.SerialTimeoutException:
            raise UserError(f"the board on {port} stopped taking data (a write waited {WRITE_TIMEOUT_S:.0f} s)",
                            hint="check the cable and press RESET; the upload starts over and sends only what "
                                 "differs") from None
        except (serial.SerialException, OSError) as exc:
            raise UserError(f"the connection to the board on {port} was lost: {exc}",
                            hint="check the cable and run the same command again; files arrive whole or not at "
                                 "all (each is renamed into place)") from None
    finally:
        close_quietly(handle)
    result.seconds = time.monotonic() - started
    progress(f"uploaded {len(result.sent)} file(s), {len(result.unchanged)} unchanged, in {result.seconds:.1f} s"
             f"{' (raw-paste)' if result.raw_paste else ''}")
    return result


def upload(out: Path, port: str, force: bool = False, use_raw_paste: bool = True,
           progress: Progress = print) -> UploadResult:
    """Upload OUT/build/app (from `deadreckon build OUT`) to the board on `port`."""
    from codegen.deploy.build import BUILD_DIR
    from codegen.deploy.buildrecord import check_build_current

    app_dir = Path(out) / BUILD_DIR / "app"
    if not app_dir.is_dir():
        raise UserError(f"{app_dir} does not exist", hint=f"run `deadreckon build {out}` first")
    check_build_current(Path(out))
    progress(f"uploading {app_dir} to {port}")
    return upload_folder(app_dir, port, force=force, use_raw_paste=use_raw_paste, progress=progress)
