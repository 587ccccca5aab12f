"""An RFC 2217 (telnet COM port control) server on loopback in front of a serial port, for `rfc2217://` ports, as
ser2net would offer a board's USB serial port. pyserial's PortManager does the protocol; this moves the bytes."""

from __future__ import annotations

import socket
import threading

import serial
import serial.rfc2217


class _Connection:
    def __init__(self, sock: socket.socket):
        self.sock = sock

    def write(self, data: bytes) -> None:
        self.sock.sendall(data)


class Rfc2217Server:
    def __init__(self, device: str):
        self.device = serial.serial_for_url(device, timeout=0.05)  # a pyserial URL, e.g. the REPL peer's
        self.server = socket.socket()
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(1)
        self.port = self.server.getsockname()[1]
        self.url = f"rfc2217://127.0.0.1:{self.port}"
        self._stop = False
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self._stop:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            manager = serial.rfc2217.PortManager(self.device, _Connection(conn))
            done = threading.Event()

            def device_to_network() -> None:
                while not done.is_set():
                    data = self.device.read(max(1, self.device.in_waiting))
                    if data:
                        try:
                            conn.sendall(b"".join(manager.escape(data)))
                        except OSError:
                            return

            pump = threading.Thread(target=device_to_network, daemon=True)
            pump.start()
            try:
                while True:
                    data = conn.recv(4096)
                    if not data:
                        break
                    self.device.write(b"".join(manager.filter(data)))
            except OSError:
                pass
            finally:
                done.set()
                pump.join(timeout=1)
                conn.close()

    def close(self) -> None:
        self._stop = True
        self.server.close()
        self.device.close()

    def __enter__(self) -> "Rfc2217Server":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
