"""Misbehaving serial ports on loopback TCP (`socket://127.0.0.1:PORT`), for the hostile-input tests.

Each connection gets one behaviour:

    close       accept, then hang up at once (a USB adapter unplugged as the port opens)
    silent      read and drop everything, never answer (a board in a loop that ignores its console)
    chatter     send lines continuously whatever arrives (a GPS module on the port, 115200 baud of NMEA)
    deaf        never read and never answer, with a tiny receive buffer: writes to it block
    garbage     answer every chunk received with random bytes (line noise, a wrong baud rate)

and these speak MicroPython's raw REPL first (Ctrl-A -> banner and ">"; raw-paste refused), then misbehave:

    liar        accept every command with OK and run nothing: no output, no error (the files never arrive)
    drop        answer like a board that ran the code (OK, no output) for `after` commands, then hang up
    babble      accept the first command with OK, then print output forever, never ending it
    stall       accept commands with OK, then never answer again
"""

from __future__ import annotations

import random
import socket
import threading
import time

RAW_BANNER = b"raw REPL; CTRL-B to exit\r\n>"
NMEA = b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n"
BEHAVIOURS = ("close", "silent", "chatter", "deaf", "garbage", "liar", "drop", "babble", "stall")


class BadPort:
    """A TCP server on 127.0.0.1 whose every connection misbehaves as `behaviour`; a context manager."""

    def __init__(self, behaviour: str, after: int = 3):
        if behaviour not in BEHAVIOURS:
            raise ValueError(f"unknown behaviour {behaviour!r}")
        self.behaviour = behaviour
        self.after = after  # commands answered before `drop` hangs up
        self.connections = 0
        self._stop = threading.Event()
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if behaviour == "deaf":  # inherited by accepted sockets: the client's writes fill it quickly
            self._server.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self._server.bind(("127.0.0.1", 0))
        self._server.listen(4)
        self._server.settimeout(0.2)
        self._threads: list[threading.Thread] = []
        self._accepter = threading.Thread(target=self._accept, daemon=True)

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self._server.getsockname()[1]}"

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except (socket.timeout, OSError):
                continue
            self.connections += 1
            thread = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            self._threads.append(thread)
            thread.start()

    def _serve(self, conn: socket.socket) -> None:
        conn.settimeout(0.2)
        try:
            getattr(self, f"_{self.behaviour}")(conn)
        except OSError:
            pass
        finally:
            try:
                conn.close()
            except OSError:
                pass

    # -- plain misbehaviour
    def _close(self, conn: socket.socket) -> None:
        conn.shutdown(socket.SHUT_RDWR)

    def _silent(self, conn: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                if not conn.recv(4096):
                    return
            except socket.timeout:
                continue

    def _chatter(self, conn: socket.socket) -> None:
        conn.setblocking(False)
        while not self._stop.is_set():
            try:
                conn.recv(4096)
            except BlockingIOError:
                pass
            try:
                conn.send(NMEA * 16)
            except BlockingIOError:
                time.sleep(0.001)

    def _deaf(self, conn: socket.socket) -> None:
        self._stop.wait()

    def _garbage(self, conn: socket.socket) -> None:
        noise = random.Random(7)
        while not self._stop.is_set():
            try:
                data = conn.recv(4096)
            except socket.timeout:
                continue
            if not data:
                return
            conn.sendall(bytes(noise.randrange(256) for _ in range(len(data) + 16)))

    # -- a raw REPL that misbehaves after entering
    def _commands(self, conn: socket.socket):
        """Yield each command (code up to Ctrl-D) once the client is in raw mode; answer the rest of the protocol."""
        buffer = b""
        raw = False
        while not self._stop.is_set():
            try:
                data = conn.recv(4096)
            except socket.timeout:
                continue
            if not data:
                return
            buffer += data
            while True:
                if not raw:
                    index = buffer.find(b"\x01")
                    if index < 0:
                        buffer = b""
                        break
                    buffer = buffer[index + 1 :]
                    conn.sendall(RAW_BANNER)
                    raw = True
                    continue
                if buffer.startswith(b"\x05A\x01"):  # raw-paste: refused, as MicroPython before 1.14 did
                    buffer = buffer[3:]
                    conn.sendall(b"R\x00")
                    continue
                if buffer[:1] in (b"\x02", b"\x03", b"\r"):  # leave raw mode / interrupt / stray CR
                    if buffer[:1] == b"\x02":
                        raw = False
                    buffer = buffer[1:]
                    continue
                if buffer[:1] == b"\x01":
                    buffer = buffer[1:]
                    conn.sendall(RAW_BANNER)
                    continue
                end = buffer.find(b"\x04")
                if end < 0:
                    break
                code, buffer = buffer[:end], buffer[end + 1 :]
                yield code

    def _liar(self, conn: socket.socket) -> None:
        for _ in self._commands(conn):
            conn.sendall(b"OK\x04\x04>")

    def _drop(self, conn: socket.socket) -> None:
        for count, _ in enumerate(self._commands(conn), 1):
            if count > self.after:
                conn.shutdown(socket.SHUT_RDWR)
                return
            conn.sendall(b"OK\x04\x04>")

    def _babble(self, conn: socket.socket) -> None:
        for _ in self._commands(conn):
            conn.sendall(b"OK")
            while not self._stop.is_set():
                conn.sendall(b"deadreckon is thinking " * 64 + b"\r\n")
                time.sleep(0.001)
            return

    def _stall(self, conn: socket.socket) -> None:
        for _ in self._commands(conn):
            conn.sendall(b"OK")

    # -- lifetime
    def __enter__(self) -> "BadPort":
        self._accepter.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._accepter.join(timeout=2)
        self._server.close()
        for thread in self._threads:
            thread.join(timeout=2)
