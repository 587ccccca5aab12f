"""Run one script of the fused algorithm on any implementation: the float64 reference, the C kernel through cffi, or
the generated fallback on the unix-port `micropython` (tests/mp_fused_driver.py), so a physical test is written once
and holds each implementation to physics on its own.

A script: an optional starting state (a FusedState, written over fused_init's) or calibration samples, optional
parameters (a FusedConfig; default the board's), and steps:
    ("p", samples (m, 6) int16, dt_us (m,))   process the samples
    ("g", ve, vn, de, dn)                      a fix: position_update, then gps_update
    ("v", ve, vn)                              gps_update alone
    ("x", ve, vn, de, dn)                      position_update alone
`run` returns a Trace: the state after the start, and after each step the `out` vector and the whole state vector
(in the order of codegen.kernel.fused.STATE_FIELDS; float32 for the C and the fallback), and every Kalman filter's
covariance after every one of its steps (start, predict, update), observed inside the implementation; `run` checks
each of those symmetric and positive semi-definite (`assert_covariances_usable`) before it returns, so every script
run through here, on every implementation, is also a test of the filters' consistency.
"""

from __future__ import annotations

import json
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from codegen.board.loader import default_board
from codegen.kernel import fused as F
from codegen.kernel.layout import COVARIANCE_FILTERS, FILTER_STEPS
from codegen.kernel.reference import KernelConfig

IMPLEMENTATIONS = ("reference", "c", "fallback")
BOARD = default_board()
KCFG = KernelConfig.from_board(BOARD)
FCFG = F.FusedConfig.from_board(BOARD)
DRIVER = Path(__file__).resolve().parent / "mp_fused_driver.py"


@dataclass
class Trace:
    moved: Optional[bool]
    start: np.ndarray
    outs: list = field(default_factory=list)
    states: list = field(default_factory=list)
    covariances: list = field(default_factory=list)  # (filter, step, full matrix) after every filter step

    def at(self, step: int, name: str) -> float:
        """The value `name` (a STATE_FIELDS name) after step `step` (-1: the last)."""
        return float(self.states[step][F.IDX[name]])

    def series(self, name: str) -> np.ndarray:
        return np.array([s[F.IDX[name]] for s in self.states])


# each filter's covariance as STATE_FIELDS indices of its upper triangle, and where each entry goes
FILTER_ENTRIES = {which: (list(pij), [F.IDX[name] for name in pij.values()])
                  for which, pij in F.FILTER_COVARIANCES.items()}


def covariance_from(which: int, values) -> np.ndarray:
    """Filter `which`'s covariance as a full matrix from its upper triangle's values (FILTER_ENTRIES' order)."""
    cells, _ = FILTER_ENTRIES[which]
    n = max(j for _, j in cells) + 1
    p = np.zeros((n, n))
    for (i, j), v in zip(cells, values):
        p[i, j] = p[j, i] = v
    return p


def assert_covariance_usable(p: np.ndarray, eps: float, where: str = "") -> None:
    """Symmetric (by construction: an upper triangle stored) and positive semi-definite within rounding: every
    value finite, every variance >= 0, the smallest eigenvalue >= -n * 64 eps max|P| (a filter with a state it
    cannot see, as the offset along gravity, has an eigenvalue 0 that rounding may take just below)."""
    assert np.all(np.isfinite(p)), f"{where}: not finite\n{p}"
    np.testing.assert_array_equal(p, p.T)
    assert np.all(np.diag(p) >= 0.0), f"{where}: a negative variance\n{p}"
    scale = float(np.abs(p).max())
    low = float(np.linalg.eigvalsh(p).min())
    assert low >= -len(p) * 64 * eps * scale, f"{where}: eigenvalue {low} (max |P| {scale})\n{p}"


def assert_covariances_usable(trace: Trace, impl: str) -> None:
    eps = 2.0**-52 if impl == "reference" else 2.0**-24
    for k, (which, step, p) in enumerate(trace.covariances):
        assert_covariance_usable(p, eps, f"{impl}: filter {COVARIANCE_FILTERS[which]} after step "
                                 f"{FILTER_STEPS[step]} (observation {k})")


def _reference(steps, params, start, calib) -> Trace:
    st = start.copy() if start is not None else F.FusedState()
    moved = bool(F.calibrate(st, calib, KCFG)) if calib is not None else None
    trace = Trace(moved, st.vector())
    previous = F.observe_covariances(lambda s, which, step: trace.covariances.append(
        (which, step, F.covariance_matrix(s, which))))
    try:
        _reference_steps(st, steps, params, trace)
    finally:
        F.observe_covariances(previous)
    return trace


def _reference_steps(st, steps, params, trace) -> None:
    for step in steps:
        out = np.zeros(6)
        if step[0] == "p":
            out, _ = F.process(st, step[1], step[2], KCFG, params)
        elif step[0] == "g":
            F.position_update(st, *step[1:5], params)
            F.gps_update(st, step[1], step[2], params)
        elif step[0] == "v":
            F.gps_update(st, step[1], step[2], params)
        else:
            F.position_update(st, *step[1:5], params)
        trace.outs.append(np.asarray(out, dtype=float))
        trace.states.append(st.vector())


def _c(steps, params, start, calib) -> Trace:
    from codegen.kernel.hostfused import load_fused

    session = load_fused().session(params)
    if start is not None:
        session.set_state_vector(start.vector())
    moved = session.calibrate(calib) if calib is not None else None
    trace = Trace(moved, session.state_vector())
    session.observe(lambda which, step, state: trace.covariances.append(
        (which, step, covariance_from(which, state[FILTER_ENTRIES[which][1]]))))
    for step in steps:
        out = np.zeros(6)
        if step[0] == "p":
            out = session.process(step[1], step[2])
        elif step[0] == "g":
            session.position(*step[1:5])
            session.gps(step[1], step[2])
        elif step[0] == "v":
            session.gps(step[1], step[2])
        else:
            session.position(*step[1:5])
        trace.outs.append(np.asarray(out, dtype=float))
        trace.states.append(session.state_vector())
    session.observe(None)
    return trace


def _fallback(steps, params, start, calib, work: Path) -> Trace:
    from conftest import require_tool
    from kernelkit import write_fallback

    micropython = require_tool("micropython")
    write_fallback(work)
    payload = {
        "state_len": F.STATE_LEN,
        "params": [float(getattr(params, name)) for name in F.FusedConfig.__dataclass_fields__],
        "calib": None if calib is None else np.asarray(calib).ravel().tolist(),
        "steps": [[s[0], np.asarray(s[1]).ravel().tolist(), np.asarray(s[2]).ravel().tolist()] if s[0] == "p"
                  else [s[0]] + [float(x) for x in s[1:]] for s in steps],
        "observe": [FILTER_ENTRIES[which][1] for which in sorted(FILTER_ENTRIES)],
    }
    if start is not None:
        payload["state"] = start.vector().tolist()
    (work / "fused_script.json").write_text(json.dumps(payload))
    env = dict(os.environ, MICROPYPATH=f"{work}:.frozen")
    done = subprocess.run([micropython, "-X", "heapsize=64M", str(DRIVER), "dr_fallback",
                           str(work / "fused_script.json")], capture_output=True, text=True, env=env, timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    answer = json.loads(done.stdout.strip().splitlines()[-1])
    trace = Trace(None if answer["moved"] is None else bool(answer["moved"]), np.array(answer["start"]))
    for out, state in answer["steps"]:
        trace.outs.append(np.array(out))
        trace.states.append(np.array(state))
    trace.covariances = [(which, step, covariance_from(which, values)) for which, step, values in answer["observed"]]
    return trace


def run(impl: str, steps, work: Path, params=None, start: Optional[F.FusedState] = None, calib=None,
        check_covariances: bool = True) -> Trace:
    """The script on implementation `impl` ("reference", "c" or "fallback"); `work`: a folder for the fallback.
    check_covariances=False: the caller checks trace.covariances itself (a test of a covariance gone wrong)."""
    params = FCFG if params is None else params
    steps = [(s[0], np.asarray(s[1], dtype=np.int16).reshape(-1, 6), np.asarray(s[2], dtype=np.int32))
             if s[0] == "p" else s for s in steps]
    calib = None if calib is None else np.asarray(calib, dtype=np.int16).reshape(-1, 6)
    if impl == "reference":
        trace = _reference(steps, params, start, calib)
    elif impl == "c":
        trace = _c(steps, params, start, calib)
    elif impl == "fallback":
        trace = _fallback(steps, params, start, calib, Path(work))
    else:
        raise ValueError(impl)
    if check_covariances:
        assert_covariances_usable(trace, impl)
    return trace


def chunks(samples, dt_us, size):
    """("p", ...) steps of `size` samples each."""
    return [("p", samples[k:k + size], dt_us[k:k + size]) for k in range(0, len(samples), size)]
