"""Python handle on the Node REPL bridge (repl_bridge.mjs): a MicroPython board on a loopback TCP port."""

from __future__ import annotations

import queue
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Optional

HERE = Path(__file__).resolve().parent
PACKAGE = HERE / "node_modules" / "@micropython" / "micropython-webassembly-pyscript" / "micropython.mjs"


def missing_reason() -> Optional[str]:
    """Why the peer cannot run here, or None."""
    if shutil.which("node") is None:
        return "node is not installed (Debian package nodejs)"
    if not PACKAGE.is_file():
        return "tests/peers/node_modules is missing (scripts/setup.sh runs `npm install` in tests/peers)"
    return None


class ReplPeer:
    """Start with a folder as the board's filesystem; `url` for clients; files mirror back into `root`."""

    def __init__(self, root: Path, raw_paste: bool = False, watchdog_ms: int = 0):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        command = ["node", str(HERE / "repl_bridge.mjs"), "--root", str(self.root)]
        if raw_paste:
            command.append("--raw-paste")
        if watchdog_ms:
            command += ["--watchdog-ms", str(watchdog_ms)]  # the board's watchdog (repl_bridge.mjs)
        self.process = subprocess.Popen(command, cwd=HERE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
        self.lines: "queue.Queue[str]" = queue.Queue()
        self.printed: list[str] = []  # everything the bridge said, e.g. "WATCHDOG RESET"
        threading.Thread(target=self._read, daemon=True).start()
        line = self._next(timeout=20.0, prefix="LISTENING")
        self.port = int(line.split()[1])
        self.url = f"socket://127.0.0.1:{self.port}"

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.printed.append(line.strip())
            self.lines.put(line.strip())

    def _next(self, timeout: float, prefix: str) -> str:
        deadline = time.monotonic() + timeout
        seen = []
        while True:
            try:
                line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise TimeoutError(f"REPL peer did not print {prefix!r}; printed {seen!r}")
            if line.startswith(prefix):
                return line
            seen.append(line)

    def wait_idle(self, timeout: float = 10.0) -> None:
        """Wait until the last client has gone and the bridge has mirrored its filesystem into `root`."""
        self._next(timeout, "IDLE")

    def watchdog_resets(self) -> int:
        return self.printed.count("WATCHDOG RESET")

    def files(self) -> dict[str, bytes]:
        return {p.relative_to(self.root).as_posix(): p.read_bytes() for p in sorted(self.root.rglob("*"))
                if p.is_file()}

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.process.kill()

    def __enter__(self) -> "ReplPeer":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
