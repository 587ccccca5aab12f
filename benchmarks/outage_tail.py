"""What a fused outage's error is made of, and what its tail is made of (issue 19).

    python3 benchmarks/outage_tail.py                        # car, tuning seeds 100-119, 30 s (about 2 minutes)
    python3 benchmarks/outage_tail.py --scenario bike --horizon 60 --seeds 10

Runs the fused reference through every outage of the accuracy benchmark (an outage every 5 s) in steps of 0.5 s
and splits each outage's horizontal error at the horizon into what the device got wrong:
  start       the error of the smoothed fix the outage starts from (the receiver's);
  along       the speed error integrated, integral of (s - s_true) dt: the along-track part;
  across      the travel direction's error integrated, integral of s_true sin(heading error) dt: the cross-track part;
and, per outage, the speed error at the horizon and how far the vehicle turned (truth). The table compares all
outages with the worst tenth (error above the 90th percentile): the medians of those magnitudes. Tuning seeds
only (codegen.sim.run.TUNING_SEEDS): this is where an algorithm is taken apart, not where it is reported.
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.kernel import fused as F  # noqa: E402
from codegen.sim.run import TUNING_SEEDS, build_run, outage_starts  # noqa: E402

STEP_S = 0.5
OUTAGE_S = 60.0  # the accuracy benchmark's longest horizon: the same outage starts
COLUMNS = ("seed", "error", "start", "along", "across", "speed_error", "turn_deg")


def outage_rows(scenario: str, seed: int, horizon: float) -> list[tuple]:
    """One row of COLUMNS per outage of one run."""
    board = load_board(None).board
    run = build_run(scenario, board, seed=seed)
    t, dt_us, snaps, kcfg, fcfg = F._fused_pass(run)
    starts = outage_starts(run, OUTAGE_S, 5.0)
    rows = []
    for o, j in enumerate(run.gps.last_valid_before(starts)):
        k, snap = snaps[int(j)]
        st = snap.copy()
        st.pe = st.pn = 0.0
        base = run.gps.enu[j, :2] + (st.fix_ae, st.fix_an)
        ta, end_t = float(run.gps.t[j]), float(starts[o] + horizon)
        start_err = float(np.linalg.norm(base - run.truth.at(np.array([ta]))[0, :2]))
        along = across = 0.0
        while ta < end_t - 1e-9:
            tb = min(ta + STEP_S, end_t)
            end = min(int(np.searchsorted(t, tb, side="right") - 1), len(dt_us))
            if end > k:
                F.process(st, run.counts[k:end], dt_us[k:end], kcfg, fcfg)
                k = end
            v = run.truth.velocity_at(np.array([0.5 * (ta + tb)]))[0, :2]
            s_true = float(np.linalg.norm(v))
            if s_true > 0.5:
                ue = st.cos_t * st.ux - st.sin_t * st.uy  # the travel direction, true ENU
                un = st.sin_t * st.ux + st.cos_t * st.uy
                across += (v[0] * un - v[1] * ue) * (tb - ta)  # s_true sin(heading error)
            along += (st.speed - s_true) * (tb - ta)
            ta = tb
        err = float(np.linalg.norm(base + (st.pe, st.pn) - run.truth.at(np.array([end_t]))[0, :2]))
        course = run.truth.velocity_at(np.linspace(starts[o], end_t, int(horizon * 4) + 1))[:, :2]
        moving = np.linalg.norm(course, axis=1) > 0.5
        heading = np.unwrap(np.arctan2(course[moving, 1], course[moving, 0])) if moving.sum() > 1 else np.zeros(1)
        speed_err = st.speed - float(np.linalg.norm(run.truth.velocity_at(np.array([end_t]))[0, :2]))
        rows.append((seed, err, start_err, along, across, speed_err, math.degrees(float(np.ptp(heading)))))
    return rows


def report(data: np.ndarray, horizon: float) -> str:
    c = {name: data[:, i] for i, name in enumerate(COLUMNS)}
    p90 = np.percentile(c["error"], 90)
    tail = c["error"] > p90
    groups = (("all outages", np.ones(len(data), dtype=bool)), ("the worst tenth", tail))
    lines = [f"{len(data)} outages; error at {horizon:g} s: median {np.median(c['error']):.1f} m, p90 {p90:.1f} m "
             f"({p90 / np.median(c['error']):.2f} x the median)", "",
             f"{'median of |x|':18s} {'error':>7s} {'start':>7s} {'along':>7s} {'across':>7s} {'speed err':>10s}"
             f" {'turned':>7s}", f"{'':18s} {'m':>7s} {'m':>7s} {'m':>7s} {'m':>7s} {'m/s':>10s} {'deg':>7s}"]
    for label, m in groups:
        lines.append(f"{label:18s}" + "".join(f" {np.median(np.abs(c[n][m])):{w}.1f}" for n, w in
                                              (("error", 7), ("start", 7), ("along", 7), ("across", 7),
                                               ("speed_error", 10), ("turn_deg", 7))))
    turned = c["turn_deg"] > 45.0
    lines += ["", f"outages that turned more than 45 deg: {turned.mean():.0%} of all, {turned[tail].mean():.0%} of the "
              f"worst tenth; the along-track part is the larger in {(np.abs(c['along']) > np.abs(c['across']))[tail].mean():.0%}"
              " of the worst tenth"]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="car", choices=("car", "bike", "walk", "walk-pocket", "walk-backpack"))
    parser.add_argument("--seeds", type=int, default=20, help="tuning seeds from 100 (default 20)")
    parser.add_argument("--horizon", type=float, default=30.0, help="seconds into the outage (at most 60)")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args(argv)
    if not 0.0 < args.horizon <= OUTAGE_S:
        parser.error(f"--horizon takes 0 < s <= {OUTAGE_S:g}, not {args.horizon:g}")
    seeds = list(TUNING_SEEDS)[: args.seeds]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        parts = list(pool.map(outage_rows, [args.scenario] * len(seeds), seeds, [args.horizon] * len(seeds)))
    print(f"{args.scenario}, TUNING seeds {seeds[0]}-{seeds[-1]}, the fused reference (float64)\n")
    print(report(np.array([r for part in parts for r in part], dtype=float), args.horizon))
    return 0


if __name__ == "__main__":
    sys.exit(main())
