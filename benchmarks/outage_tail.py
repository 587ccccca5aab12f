"""What a fused outage's error is made of, and what its tail is made of.

    python3 benchmarks/outage_tail.py                        # car, tuning seeds 100-119, 30 s (about 2 minutes)
    python3 benchmarks/outage_tail.py --scenario bike --horizon 60 --seeds 10
    python3 benchmarks/outage_tail.py --set nhc_fold_scale=0   # a fused parameter changed (repeatable)
    python3 benchmarks/outage_tail.py --scenario replay-car --horizon 30 --seeds 4   # the real car, degradations 100-103

Runs the fused reference through every outage of the accuracy benchmark (an outage every 5 s) in steps of 0.5 s
and splits each outage's horizontal error at the horizon into what the device got wrong:
  start       the error of the smoothed fix the outage starts from (the receiver's);
  along       the speed error integrated, integral of (s - s_true) dt: the along-track part (s: the speed
              the position moved by, a vehicle's kept speed);
  across      the travel direction's error integrated, integral of s_true sin(heading error) dt: the cross-track part;
and, per outage, the speed error at the horizon, how far the vehicle turned (truth), when the outage began, and
what calibration folded into the tilt that is still there: the horizontal part of the simulated chip's offsets
(its zero-g offset and its scale and cross-axis errors on gravity, codegen.sim.mpu6050) minus the tilt/offset
filter's estimate, at the outage's start ("fold"), against that filter's own horizontal sigma of it ("kf sigma").
A turn makes the fold a leak along the track. The table compares all outages with the worst tenth (error above the
90th percentile): the medians of those magnitudes. Tuning seeds only (codegen.sim.run.TUNING_SEEDS): this is where
an algorithm is taken apart, not where it is reported. replay-car is the real car (codegen.sim.run.REAL_CAR,
../shared/data/car-comma2k19) under tuning degradations from 100, an outage of the horizon's length every second
as the accuracy benchmark runs it there (10 or 30 s; up to 30); its chip's own offsets are unknown, so its fold is not printed. A second table
splits the errors by the quarter of the run in which the outage began (a calibration that moved shows early).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.kernel import fused as F  # noqa: E402
from codegen.kernel.layout import FUSED  # noqa: E402
from codegen.kernel.reference import STANDARD_GRAVITY, quat_to_matrix  # noqa: E402
from codegen.sim.mpu6050 import MpuErrors, draw_device  # noqa: E402
from codegen.sim.run import (  # noqa: E402
    REAL_CAR,
    SCENARIOS,
    TUNING_SEEDS,
    build_run,
    outage_starts,
    require_recordings,
)

STEP_S = 0.5
OUTAGE_S = 60.0  # the accuracy benchmark's longest horizon: the same outage starts
REAL_CAR_OUTAGE_S = 30.0  # the real car's 60 s hold outages of up to 30 s (benchmarks/accuracy.py: CAR_OUTAGES)
COLUMNS = ("seed", "error", "start", "along", "across", "speed_error", "turn_deg", "began", "fold", "kf_sigma")


def _fold(st, device, axis_map) -> tuple[float, float]:
    """The offsets calibration folded into the tilt that the tilt/offset filter has not taken out, seen
    horizontally (m/s^2), and that filter's own sigma of it."""
    r = quat_to_matrix(np.array([st.qw, st.qx, st.qy, st.qz]))  # body -> kernel frame
    perm = np.zeros((3, 3))  # body = perm @ sensor (the board's axis remap)
    for i, (src, sign) in enumerate(axis_map):
        perm[i, src] = sign
    up_sensor = perm.T @ r.T @ np.array([0.0, 0.0, STANDARD_GRAVITY])
    offset = perm @ (device.accel_offset + (device.accel_matrix - np.eye(3)) @ up_sensor)
    left = r[:2] @ (offset - np.array([st.bax, st.bay, st.baz]))
    pbb = np.array([[getattr(st, F._PIJ[(min(i, j) + 2, max(i, j) + 2)]) for j in range(3)] for i in range(3)])
    return float(np.linalg.norm(left)), math.sqrt(max(float(np.trace(r[:2] @ pbb @ r[:2].T)), 0.0))


def outage_rows(scenario: str, seed: int, horizon: float, changes: dict) -> list[tuple]:
    """One row of COLUMNS per outage of one run; `changes`: fused parameters (FusedConfig names) to change."""
    board = load_board(None).board
    run = build_run(scenario, board, seed=seed)
    real = scenario == REAL_CAR
    device = draw_device(MpuErrors(), np.random.default_rng(seed))  # as codegen.sim.mpu6050.simulate_imu draws it
    t, dt_us, snaps, kcfg, fcfg = F._fused_pass(run, replace(F.FusedConfig.from_board(board), **changes))
    starts = outage_starts(run, horizon, 1.0) if real else outage_starts(run, OUTAGE_S, 5.0)
    rows = []
    for o, j in enumerate(run.gps.last_valid_before(starts)):
        k, snap = snaps[int(j)]
        st = snap.copy()
        fold, kf_sigma = (math.nan, math.nan) if real else _fold(st, device, board.imu.axis_map)
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
            # the speed the position moved by: a vehicle's kept speed (_kept_speed), else the integrated one
            on_foot_or_resting = int(st.flags) & (F.AT_REST | F.WALKING | F.WALKED)
            along += ((st.speed if on_foot_or_resting else F._kept_speed(st, fcfg)) - s_true) * (tb - ta)
            ta = tb
        err = float(np.linalg.norm(base + (st.pe, st.pn) - run.truth.at(np.array([end_t]))[0, :2]))
        course = run.truth.velocity_at(np.linspace(starts[o], end_t, int(horizon * 4) + 1))[:, :2]
        moving = np.linalg.norm(course, axis=1) > 0.5
        heading = np.unwrap(np.arctan2(course[moving, 1], course[moving, 0])) if moving.sum() > 1 else np.zeros(1)
        speed_err = st.speed - float(np.linalg.norm(run.truth.velocity_at(np.array([end_t]))[0, :2]))
        rows.append((seed, err, start_err, along, across, speed_err, math.degrees(float(np.ptp(heading))),
                     float(starts[o]), fold, kf_sigma))
    return [row + (run.duration,) for row in rows]


def report(data: np.ndarray, horizon: float) -> str:
    c = {name: data[:, i] for i, name in enumerate(COLUMNS)}
    quarter = np.minimum((4.0 * c["began"] / data[:, len(COLUMNS)]).astype(int), 3)
    p90 = np.percentile(c["error"], 90)
    tail = c["error"] > p90
    groups = (("all outages", np.ones(len(data), dtype=bool)), ("the worst tenth", tail))
    lines = [f"{len(data)} outages; error at {horizon:g} s: median {np.median(c['error']):.1f} m, p90 {p90:.1f} m "
             f"({p90 / np.median(c['error']):.2f} x the median)", "",
             f"{'median of |x|':18s} {'error':>7s} {'start':>7s} {'along':>7s} {'across':>7s} {'speed err':>10s}"
             f" {'turned':>7s} {'began':>7s} {'fold':>7s} {'kf sigma':>9s}",
             f"{'':18s} {'m':>7s} {'m':>7s} {'m':>7s} {'m':>7s} {'m/s':>10s} {'deg':>7s} {'s':>7s} {'m/s^2':>7s}"
             f" {'m/s^2':>9s}"]
    for label, m in groups:
        lines.append(f"{label:18s}" + "".join(f" {np.median(np.abs(c[n][m])):{w}.{d}f}" for n, w, d in
                                              (("error", 7, 1), ("start", 7, 1), ("along", 7, 1), ("across", 7, 1),
                                               ("speed_error", 10, 1), ("turn_deg", 7, 1), ("began", 7, 0),
                                               ("fold", 7, 3), ("kf_sigma", 9, 3))))
    turned = c["turn_deg"] > 45.0
    lines += ["", f"outages that turned more than 45 deg: {turned.mean():.0%} of all, {turned[tail].mean():.0%} of the "
              f"worst tenth; the along-track part is the larger in {(np.abs(c['along']) > np.abs(c['across']))[tail].mean():.0%}"
              " of the worst tenth", "",
              f"{'outage began in':18s} {'outages':>7s} {'median':>7s} {'p90':>7s} {'along':>7s} {'across':>7s}"
              f" {'began':>7s}", f"{'':18s} {'':>7s} {'m':>7s} {'m':>7s} {'m':>7s} {'m':>7s} {'s':>7s}"]
    for q, label in enumerate(("the 1st quarter", "the 2nd quarter", "the 3rd quarter", "the 4th quarter")):
        m = quarter == q
        if m.any():
            lines.append(f"{label:18s} {int(m.sum()):7d} {np.median(c['error'][m]):7.1f}"
                         f" {np.percentile(c['error'][m], 90):7.1f} {np.median(np.abs(c['along'][m])):7.1f}"
                         f" {np.median(np.abs(c['across'][m])):7.1f} {np.median(c['began'][m]):7.0f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="car",
                        choices=[s for s in SCENARIOS if s not in ("static", "push", "replay-walk")] + [REAL_CAR])
    parser.add_argument("--seeds", type=int, default=20, help="tuning seeds from 100 (default 20)")
    parser.add_argument("--horizon", type=float, default=30.0, help="seconds into the outage (at most 60)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="a fused parameter in its declared unit (codegen/kernel/layout.py), e.g. nhc_fold_scale=0")
    args = parser.parse_args(argv)
    longest = REAL_CAR_OUTAGE_S if args.scenario == REAL_CAR else OUTAGE_S
    if not 0.0 < args.horizon <= longest:
        parser.error(f"--horizon takes 0 < s <= {longest:g} on {args.scenario}, not {args.horizon:g}")
    require_recordings([args.scenario])
    names = {p.name for p in FUSED.params}
    changes = {}
    for item in args.set:
        name, _, value = item.partition("=")
        if name not in names:
            parser.error(f"--set {item}: no fused parameter {name!r} (they are: {', '.join(sorted(names))})")
        try:
            changes[name] = float(value)
        except ValueError:
            parser.error(f"--set {item}: {value!r} is not a number")
    seeds = list(TUNING_SEEDS)[: args.seeds]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        parts = list(pool.map(outage_rows, [args.scenario] * len(seeds), seeds, [args.horizon] * len(seeds),
                              [changes] * len(seeds)))
    label = ", ".join(f"{k} {v:g}" for k, v in changes.items()) or "the defaults"
    print(f"{args.scenario}, TUNING seeds {seeds[0]}-{seeds[-1]}, the fused reference (float64), {label}\n")
    print(report(np.array([r for part in parts for r in part], dtype=float), args.horizon))
    return 0


if __name__ == "__main__":
    sys.exit(main())
