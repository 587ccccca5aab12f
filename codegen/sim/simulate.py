"""What `deadreckon simulate` does, as a library call the tests use too."""

from __future__ import annotations

import math
import os
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

from codegen.errors import UserError
from codegen.sim import neo6m, replay
from codegen.sim.methods import registered_methods
from codegen.sim.run import (
    SCENARIOS,
    Result,
    build_run,
    evaluate,
    format_table,
    progress,
)

STANDARD_HORIZONS = (10.0, 30.0, 60.0)
# The options' ranges: an outage or a step longer than an hour outlasts every scenario; a step under a second
# starts more outages than there are GPS fixes (the fixes come at 1 Hz) and only multiplies the run time; the
# scenario and sensor generators take a seed of 32 bits.
MAX_OUTAGE_S = 3600.0
MIN_STEP_S = 1.0
MAX_STEP_S = 3600.0
MAX_SEED = 2**32 - 1
PLOT_SUFFIX = ".png"


def check_options(outage_s: float = 30.0, seed: int = 0, step: float = 5.0, plot: Path | None = None) -> None:
    """A UserError naming the option when --outage, --seed, --step or --plot is out of its range, before any
    simulation runs (so nothing is written and no time is spent on a run that cannot finish)."""
    if not (math.isfinite(outage_s) and 0 < outage_s <= MAX_OUTAGE_S):
        raise UserError(f"--outage {outage_s:g}: an outage is a positive number of seconds, at most "
                        f"{MAX_OUTAGE_S:g}", hint="the default, 30, is a typical tunnel or urban canyon")
    if not (math.isfinite(step) and MIN_STEP_S <= step <= MAX_STEP_S):
        raise UserError(f"--step {step:g}: the time between outage starts is between {MIN_STEP_S:g} and "
                        f"{MAX_STEP_S:g} seconds", hint="the default, 5, measures about a hundred outages per run")
    if not 0 <= seed <= MAX_SEED:
        raise UserError(f"--seed {seed}: a seed is a whole number from 0 to {MAX_SEED} (32 bits)",
                        hint="any number in that range gives its own repeatable run; 0 is the default")
    if plot is not None:
        check_plot_path(Path(plot))


def check_plot_path(plot: Path) -> None:
    """--plot names a new or existing regular .png file in an existing folder (never a folder, a device or a link)."""
    if plot.suffix.lower() != PLOT_SUFFIX:
        raise UserError(f"--plot {plot}: the plot is a PNG image, so its name ends in {PLOT_SUFFIX}",
                        hint=f"e.g. --plot {plot.with_suffix(PLOT_SUFFIX).name if plot.name else 'walk.png'}")
    if os.path.lexists(plot) and not stat.S_ISREG(os.lstat(plot).st_mode):
        raise UserError(f"--plot {plot}: exists and is not a regular file (a folder, a link or a device)",
                        hint="name a new file, or a PNG of yours to replace")
    folder = plot.parent
    if not folder.is_dir():
        raise UserError(f"--plot {plot}: the folder {folder} does not exist", hint="create it first, or name "
                        "a file in an existing folder")


def horizons_for(outage_s: float) -> tuple[float, ...]:
    """The standard horizons shorter than the outage, then the outage length itself."""
    return tuple(h for h in STANDARD_HORIZONS if h < outage_s) + (float(outage_s),)


def recorded_walk_dir(data: Path | None) -> Path:
    """The folder replay-walk reads, checked: `data` (the --data option) or, without it, the recording beside a
    source checkout. A missing folder or file is a UserError naming it and the option."""
    folder = Path(data) if data is not None else replay.default_walk_dir()
    hint = (f"--data DIR names the recorded walk's folder, which holds {replay.IMU_FILE} and {replay.POS_FILE} "
            "(rtklibexplorer/GNSS_IMU data/walk_0827; a checkout has it in ../shared/data/gnss-imu-walk)")
    for name in (replay.IMU_FILE, replay.POS_FILE):
        if (folder / name).is_file():
            continue
        if data is None:
            raise UserError(f"replay-walk needs the recorded walk: none was given (--data) and {folder / name}, "
                            "where a source checkout keeps it, is missing", hint=hint)
        what = "is not a folder" if not folder.is_dir() else f"has no {name}"
        raise UserError(f"replay-walk: {folder} {what} (--data)", hint=hint)
    return folder


@dataclass
class SimulateReport:
    result: Result
    table: str
    plot: Path | None


def simulate(board, scenario: str = "walk", outage_s: float = 30.0, seed: int = 0, quality: str = "open-sky",
             step: float = 5.0, plot: Path | None = None, methods: list[str] | None = None,
             stream=None, data: Path | None = None) -> SimulateReport:
    """Simulate `scenario` on `board` (reference pipeline), measure every method over outages of `outage_s`
    seconds starting every `step` s, print the table to `stream`, and optionally write the plot. `data`: the
    folder of the recorded walk that replay-walk reads (default: ../shared/data/gnss-imu-walk beside a checkout)."""
    stream = sys.stdout if stream is None else stream  # looked up per call: a caller may have replaced sys.stdout
    if scenario not in SCENARIOS:
        raise UserError(f"unknown scenario {scenario!r}", hint=f"choose one of {', '.join(SCENARIOS)}")
    check_options(outage_s, seed, step, plot)
    if data is not None and scenario != "replay-walk":
        raise UserError(f"--data is the recorded walk's folder; the {scenario} scenario is simulated and reads none",
                        hint="use --data with --scenario replay-walk, or leave it out")
    walk_dir = recorded_walk_dir(data) if scenario == "replay-walk" else None
    if quality not in neo6m.QUALITY:
        raise UserError(f"unknown GPS quality {quality!r}", hint=f"choose one of {', '.join(neo6m.QUALITY)}")
    available = registered_methods()
    if methods:
        unknown = [m for m in methods if m not in available]
        if unknown:
            raise UserError(f"unknown method {unknown[0]!r}", hint=f"registered: {', '.join(available)}")
        available = {m: available[m] for m in methods}
    progress(0, 3, f"simulating {scenario}")
    try:
        run = build_run(scenario, board, seed=seed, quality=quality, walk_dir=walk_dir)
    except ValueError as error:  # e.g. a GPS rate the NEO-6M cannot deliver
        raise UserError(str(error), hint="check the board's gps: and imu: settings") from None
    progress(1, 3, "measuring outages")
    try:
        result = evaluate(run, horizons_for(outage_s), available, step=step)
    except ValueError as error:
        raise UserError(str(error), hint="choose a shorter --outage") from None
    table = format_table([result])
    progress(2, 3, "plotting" if plot else "done")
    written = None
    if plot is not None:
        from codegen.sim.plot import plot_run

        written = plot_run(run, outage_s, Path(plot), available, step=step)
    progress(3, 3, "done")
    print(table, file=stream)
    if written is not None:
        print(f"plot: {written}", file=stream)
    return SimulateReport(result, table, written)
