"""A TCP link in front of the REPL peer that fails on purpose: after given numbers of bytes from the board it cuts
the client's connection (a cable pulled, a USB bridge gone) and, for a reset, first soft-resets the board (what a
watchdog or a brown-out does to a transfer). The link to the peer stays up; the client reconnects to `url`. With
`delay_s`, every piece the board sends waits that long first: a slow link, so a transfer takes at least its number
of replies times `delay_s`, however fast the machine running the test."""

from __future__ import annotations

import socket
import threading


class FlakyLink:
    def __init__(self, peer_port: int, cuts: list[int] = (), resets: list[int] = (), delay_s: float = 0.0):
        self.delay_s = delay_s
        self.upstream = socket.create_connection(("127.0.0.1", peer_port))
        self.upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.events = sorted([(n, "cut") for n in cuts] + [(n, "reset") for n in resets])
        self.done: list[tuple[int, str]] = []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.client = None
        self.lock = threading.Lock()
        self.from_board = 0  # bytes the board sent through the link
        self.stopped = False
        threading.Thread(target=self._accept, daemon=True).start()
        threading.Thread(target=self._board_to_client, daemon=True).start()

    def _accept(self):
        while not self.stopped:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self.lock:
                self.client = conn
            threading.Thread(target=self._client_to_board, args=(conn,), daemon=True).start()

    def _client_to_board(self, conn):
        while True:
            try:
                data = conn.recv(4096)
            except OSError:
                return
            if not data:
                return
            with self.lock:
                if conn is not self.client:
                    return
                self.upstream.sendall(data)

    def _board_to_client(self):
        while True:
            try:
                data = self.upstream.recv(4096)
            except OSError:
                return
            if not data:
                return
            if self.delay_s:
                import time

                time.sleep(self.delay_s)
            with self.lock:
                self.from_board += len(data)
                if self.client is not None:
                    try:
                        self.client.sendall(data)
                    except OSError:
                        self.client = None
                if self.events and self.from_board >= self.events[0][0]:
                    at, kind = self.events.pop(0)
                    self.done.append((self.from_board, kind))
                    if kind == "reset":  # leave raw mode, soft reset: the board's RAM state is gone
                        self.upstream.sendall(b"\r\x03\x03\x02\x04")
                    if self.client is not None:
                        self.client.shutdown(socket.SHUT_RDWR)
                        self.client.close()
                        self.client = None

    def close(self):
        self.stopped = True
        self.server.close()
        with self.lock:
            if self.client is not None:
                self.client.close()
        try:
            self.upstream.shutdown(socket.SHUT_RDWR)  # the peer sees its client go (another thread is in recv)
        except OSError:
            pass
        self.upstream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
