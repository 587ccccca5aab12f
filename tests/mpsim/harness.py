"""Host side of the MicroPython end-to-end tests: generate an app, write a scenario, run it, read the trace.

Runs on CPython only (it lives beside the emulated modules so the pieces of the emulator stay together; MicroPython
never imports it).
"""

from __future__ import annotations

import json
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

MPSIM = Path(__file__).resolve().parent
TICKS_PERIOD = 1 << 30


def generate_app(board: str | Path, out: Path) -> Path:
    """`deadreckon generate BOARD -o OUT` through the library; returns OUT."""
    from codegen.generate import generate
    from codegen.loader import load_board

    generate(load_board(board), out, force=True)
    return out


def board_yaml(tmp: Path, text: str, name: str = "board.yaml") -> Path:
    path = tmp / name
    path.write_text(text)
    return path


@dataclass
class Run:
    returncode: int
    stdout: str
    stderr: str
    trace: list[dict]

    def events(self, kind: str) -> list[dict]:
        return [e for e in self.trace if e["ev"] == kind]

    def screens(self) -> list[dict]:
        return self.events("screen")

    def screen_at(self, t_s: float) -> list[str]:
        """The display text shown at virtual time t_s (the last frame before it)."""
        shown = None
        for e in self.screens():
            if e["t_us"] <= t_s * 1e6:
                shown = e["lines"]
        return shown or []

    def console(self, prefix: str) -> list[str]:
        return [line for line in self.stdout.splitlines() if line.startswith(prefix)]


def run_app(
    micropython: str,
    out: Path,
    scenario: dict,
    work: Path,
    script: str | None = None,
    timeout: float = 600,
    extra_path: list[Path] | None = None,
) -> Run:
    """Run OUT/app/main.py (or `script`) under the unix-port MicroPython with tests/mpsim ahead of the app."""
    work.mkdir(parents=True, exist_ok=True)
    scenario = dict(scenario)
    scenario.setdefault("trace", str(work / "trace.jsonl"))
    scenario_path = work / "scenario.json"
    scenario_path.write_text(json.dumps(scenario))
    paths = [str(MPSIM)] + [str(p) for p in (extra_path or [])] + [str(out / "app")]
    env = dict(os.environ, MICROPYPATH=":".join(paths), MPSIM_SCENARIO=str(scenario_path))
    target = script if script is not None else str(out / "app" / "main.py")
    proc = subprocess.run(
        [micropython, "-X", "heapsize=64M", target], env=env, capture_output=True, text=True, timeout=timeout, cwd=work
    )
    trace_path = Path(scenario["trace"])
    trace = []
    if trace_path.exists():
        trace = [json.loads(line) for line in trace_path.read_text().splitlines() if line.strip()]
    return Run(proc.returncode, proc.stdout, proc.stderr, trace)


def run_script(micropython: str, app_dir: Path, script: str, args: list[str] = (), timeout: float = 600):
    """Run a MicroPython script with the generated app's modules importable (no emulated machine)."""
    env = dict(os.environ, MICROPYPATH=str(app_dir))
    return subprocess.run(
        [micropython, "-X", "heapsize=64M", script, *args], env=env, capture_output=True, text=True, timeout=timeout
    )


def nmea_checksum(body: str) -> str:
    check = 0
    for ch in body.encode():
        check ^= ch
    return f"{check:02X}"


def sentence(body: str) -> str:
    return f"${body}*{nmea_checksum(body)}"


def write_stream(path: Path, chunks: list[tuple[float, str]]) -> Path:
    """NMEA chunks (t in s, text) as the UART model's "t_us<TAB>text" lines (CR LF written as \\r\\n)."""
    with open(path, "w") as f:
        for t, text in chunks:
            f.write(f"{int(round(t * 1e6))}\t{text.replace(chr(13), '').replace(chr(10), chr(92) + 'r' + chr(92) + 'n')}\n")
    return path
