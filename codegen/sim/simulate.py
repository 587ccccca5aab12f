"""What `deadreckon simulate` does, as a library call the tests use too."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from codegen.errors import UserError
from codegen.sim import neo6m
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


def horizons_for(outage_s: float) -> tuple[float, ...]:
    """The standard horizons shorter than the outage, then the outage length itself."""
    return tuple(h for h in STANDARD_HORIZONS if h < outage_s) + (float(outage_s),)


@dataclass
class SimulateReport:
    result: Result
    table: str
    plot: Path | None


def simulate(board, scenario: str = "walk", outage_s: float = 30.0, seed: int = 0, quality: str = "open-sky",
             step: float = 5.0, plot: Path | None = None, methods: list[str] | None = None,
             stream=sys.stdout) -> SimulateReport:
    """Simulate `scenario` on `board` (reference pipeline), measure every method over outages of `outage_s`
    seconds starting every `step` s, print the table to `stream`, and optionally write the plot."""
    if scenario not in SCENARIOS:
        raise UserError(f"unknown scenario {scenario!r}", hint=f"choose one of {', '.join(SCENARIOS)}")
    if not outage_s > 0:
        raise UserError(f"--outage must be a positive number of seconds, not {outage_s:g}")
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
        run = build_run(scenario, board, seed=seed, quality=quality)
    except FileNotFoundError as error:
        raise UserError(f"the real walk recording is missing: {error.filename}",
                        hint="replay-walk reads ../shared/data/gnss-imu-walk beside the project checkout") from None
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
