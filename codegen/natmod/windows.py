"""Windows of IMU samples (and GPS fixes) through dr_native or dr_fallback on an emulated board, the host's side of
codegen/natmod/device_driver.py: steps in (exact int16/int32/float32 arrays), float32 results and instruction counts
out.

A step is ("C", samples (n, 6) int16) a calibration, ("P", samples (n, 6) int16, dt_us (n,) int32) a window, or
("G", ve, vn, de, dn) a GPS fix (m/s, m).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codegen.natmod.qemu_arm import CLOCK_NS, CLOCK_SOURCE, Session

DRIVER = Path(__file__).with_name("device_driver.py")
OUT_FLOATS = 6


@dataclass
class Answer:
    instructions: float  # executed by the call (virtual clock at one instruction per ns), clock reads excluded
    out: np.ndarray  # float32[6]; after a calibration out[0] is its verdict
    state: np.ndarray  # float32, the first `state_floats` of the state buffer


def start(session: Session, module: str, algorithm: str, state_floats: int) -> None:
    """Import `module` (already in the session's /mem) and the driver; `algorithm` is "seed" or "fused"."""
    session.put_file("drdrive.py", DRIVER.read_bytes())
    session.exec(CLOCK_SOURCE[session.board])
    session.exec(f"import {module}\nimport drdrive\n_run = drdrive.Runner({module}, {algorithm!r}, clock, "
                 f"{state_floats})\nimport gc\n_memfs.files.clear()\ngc.collect()")  # the imported files' bytes


def step(session: Session, item: tuple) -> Answer:
    kind = item[0]
    if kind == "C":
        session.send_array("_s", "h", np.asarray(item[1], dtype="<i2").tobytes())
        line = session.exec("_run.calibrate(_s)", timeout=600)
    elif kind == "P":
        session.send_array("_s", "h", np.asarray(item[1], dtype="<i2").tobytes())
        session.send_array("_d", "i", np.asarray(item[2], dtype="<i4").tobytes())
        line = session.exec("_run.window(_s, _d)", timeout=600)
    elif kind == "G":
        session.send_array("_g", "f", np.asarray(item[1:5], dtype="<f4").tobytes())
        line = session.exec("_run.fix(_g)", timeout=600)
    else:
        raise ValueError(f"unknown step {kind!r}")
    tag, counts, data = line.split()
    if tag != "R":
        raise ValueError(f"unexpected driver output {line[:80]!r}")
    values = np.frombuffer(bytes.fromhex(data), dtype="<f4")
    return Answer(int(counts) * CLOCK_NS[session.board], values[:OUT_FLOATS].copy(), values[OUT_FLOATS:].copy())


def run(session: Session, module: str, algorithm: str, steps: list, state_floats: int) -> list[Answer]:
    start(session, module, algorithm, state_floats)
    return [step(session, item) for item in steps]
