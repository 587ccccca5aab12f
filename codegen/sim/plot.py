"""Plots of one run: truth vs each method's estimate in the plane for one outage, and the error against the time
since GPS loss (median over all outage starts, 90th percentile shaded)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from codegen.sim.methods import registered_methods
from codegen.sim.run import RunData, outage_starts


def plot_run(run: RunData, outage_s: float, path: Path, methods=None, step: float = 5.0) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = registered_methods() if methods is None else methods
    starts = outage_starts(run, outage_s, step)
    since = np.arange(0.0, outage_s + 1e-9, 0.5)
    times = starts[:, None] + since[None, :]
    truth = run.truth.at(times)[..., :2]
    ok = run.trusted(times)
    shown = len(starts) // 2

    fig, (plane, curve) = plt.subplots(1, 2, figsize=(13, 5.5))
    whole = run.truth.at(np.arange(0.0, run.duration, 0.5))
    plane.plot(whole[:, 0], whole[:, 1], color="0.8", lw=1, label="truth (whole run)")
    plane.plot(truth[shown, :, 0], truth[shown, :, 1], color="k", lw=2.5, label="truth during the outage")
    plane.plot(truth[shown, -1, 0], truth[shown, -1, 1], "o", ms=6, color="k")
    fixes = run.gps.enu[run.gps.valid & (run.gps.t < starts[shown])]
    plane.plot(fixes[:, 0], fixes[:, 1], ".", color="0.5", ms=2, label="GPS fixes before the loss")
    for name, fn in methods.items():
        est = fn(run, starts, times)
        err = np.where(ok, np.linalg.norm(est - truth, axis=-1), np.nan)
        (line,) = curve.plot(since, np.nanmedian(err, axis=0), lw=2, label=name)
        curve.fill_between(since, np.nanpercentile(err, 10, axis=0), np.nanpercentile(err, 90, axis=0),
                           color=line.get_color(), alpha=0.15)
        plane.plot(est[shown, :, 0], est[shown, :, 1], lw=1.5, color=line.get_color(), label=name)
        plane.plot(est[shown, -1, 0], est[shown, -1, 1], "o", ms=5, color=line.get_color())  # where it ends
    plane.set_aspect("equal", adjustable="datalim")
    plane.set_xlabel("East (m)")
    plane.set_ylabel("North (m)")
    plane.set_title(f"{run.scenario}, seed {run.seed}: outage at {starts[shown]:.1f} s for {outage_s:g} s")
    plane.legend(fontsize=8)
    curve.set_xlabel("time since GPS loss (s)")
    curve.set_ylabel("horizontal error (m)")
    curve.set_yscale("symlog", linthresh=1.0)
    curve.set_title(f"median over {len(starts)} outages (band: 10th-90th percentile)")
    curve.grid(True, which="both", alpha=0.3)
    curve.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
