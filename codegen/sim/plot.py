"""Plots of one run: truth vs each method's estimate in the plane for one outage (the whole run, and zoomed on the
outage), and the error against the time since GPS loss (median over all outage starts, 90th percentile shaded)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from codegen.sim.methods import registered_methods
from codegen.sim.run import RunData, outage_starts

ZOOM_MARGIN = 1.6  # the zoomed panel spans this many times the truth's extent during the outage
ZOOM_MIN_HALF_M = 5.0  # m added to the zoomed panel's half width (a standing outage is not a point)


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

    fig, (plane, zoom, curve) = plt.subplots(1, 3, figsize=(18, 5.8))
    whole = run.truth.at(np.arange(0.0, run.duration, 0.5))
    fixes = run.gps.enu[run.gps.valid & (run.gps.t < starts[shown])]
    for ax in (plane, zoom):
        ax.plot(whole[:, 0], whole[:, 1], color="0.8", lw=1, label="truth (whole run)")
        ax.plot(truth[shown, :, 0], truth[shown, :, 1], color="k", lw=2.5, label="truth during the outage")
        ax.plot(truth[shown, -1, 0], truth[shown, -1, 1], "o", ms=6, color="k")
        ax.plot(fixes[:, 0], fixes[:, 1], ".", color="0.5", ms=2, label="GPS fixes before the loss")
    for name, fn in methods.items():
        est = fn(run, starts, times)
        err = np.where(ok, np.linalg.norm(est - truth, axis=-1), np.nan)
        (line,) = curve.plot(since, np.nanmedian(err, axis=0), lw=2, label=name)
        curve.fill_between(since, np.nanpercentile(err, 10, axis=0), np.nanpercentile(err, 90, axis=0),
                           color=line.get_color(), alpha=0.15)
        for ax in (plane, zoom):
            ax.plot(est[shown, :, 0], est[shown, :, 1], lw=1.5, color=line.get_color(), label=name)
            ax.plot(est[shown, -1, 0], est[shown, -1, 1], "o", ms=5, color=line.get_color())  # where it ends
    # the outage is a dot on a long track: the middle panel shows the truth during it with room around it (an
    # estimate that runs further off leaves the panel; the left one shows it)
    low, high = truth[shown].min(axis=0), truth[shown].max(axis=0)
    middle = 0.5 * (low + high)
    half = 0.5 * float(np.max(high - low)) * ZOOM_MARGIN + ZOOM_MIN_HALF_M
    zoom.set_xlim(middle[0] - half, middle[0] + half)
    zoom.set_ylim(middle[1] - half, middle[1] + half)
    zoom.set_aspect("equal", adjustable="box")
    zoom.set_title(f"zoomed on the outage ({2 * half:.0f} m across)")
    for ax in (plane, zoom):
        ax.set_xlabel("East (m)")
        ax.set_ylabel("North (m)")
    plane.set_aspect("equal", adjustable="datalim")
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
