"""A pseudo-terminal joined to a loopback TCP peer: a device path (/dev/pts/N) that behaves like a USB serial
port with a board behind it, so the tests cover opening real ttys (exclusive lock, DTR/RTS, paced writes)."""

from __future__ import annotations

import os
import select
import socket
import threading
import tty


class PtyLink:
    def __init__(self, host: str, port: int):
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.address = (host, port)
        self.socket = socket.create_connection(self.address)
        self._stop = False
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        """Copy bytes both ways; when the peer hangs up (the chip reset), connect again, as a USB adapter stays."""
        while not self._stop:
            ready, _, _ = select.select([self.master, self.socket], [], [], 0.1)
            try:
                if self.master in ready:
                    data = os.read(self.master, 4096)
                    if not data:
                        return
                    self.socket.sendall(data)
                if self.socket in ready:
                    data = self.socket.recv(4096)
                    if not data:
                        raise ConnectionResetError()
                    os.write(self.master, data)
            except (ConnectionError, BrokenPipeError):
                self.socket.close()
                try:
                    self.socket = socket.create_connection(self.address)
                except OSError:
                    return
            except OSError:
                return

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=2)
        self.socket.close()
        os.close(self.master)
        os.close(self.slave)

    def __enter__(self) -> "PtyLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
