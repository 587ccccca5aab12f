"""Accuracy benchmark: how far does the device get without GPS? (issue 6)

    python3 benchmarks/accuracy.py                     # full table: scenarios x outage horizons x methods
    python3 benchmarks/accuracy.py --seeds 1 --jobs 1  # quicker
    python3 benchmarks/accuracy.py --gps rtk           # perfect fixes: the IMU's own drift only

For every scenario (simulated static / push / walk / car, and the real walk replayed at MPU-6050 quality) and every
seed, outages start every few seconds after calibration; each registered method (codegen.sim.methods: seed,
const-velocity, hold-last-fix, and any plug-in such as the fused algorithm) estimates the position 10, 30 and 60 s
into each outage. The table gives the horizontal error against truth, median and 90th percentile in metres, pooled
over seeds and starts; "0 s" is the error of the last fix (every method starts there). A second table gives the
drift: the error of the displacement since the last fix, which removes the NEO-6M's own error (a floor of ~2.5 m
that no dead reckoning can remove, close to issue 8's 3 m goal at 10 s). The push scenario adds the
seed's error E = |p_e - p| / |p_e| per push. A second table splits the seed method's error on the walk by MPU-6050
error source (one at a time), to show what a better algorithm has to fight.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.sim.methods import registered_methods  # noqa: E402
from codegen.sim.mpu6050 import MpuErrors  # noqa: E402
from codegen.sim.run import SCENARIOS, build_run, evaluate, format_table  # noqa: E402

HORIZONS = (10.0, 30.0, 60.0)
GOALS = {10.0: 3.0, 30.0: 25.0, 60.0: 100.0}  # issue 8: median horizontal error, m
STEP = {"replay-walk": 2.0}  # s between outage starts (the real walk is short)


def _job(args):
    scenario, seed, quality, board_path, errors, methods = args
    board = load_board(board_path).board
    run = build_run(scenario, board, seed=seed, quality=quality, errors=errors)
    available = registered_methods()
    chosen = {m: available[m] for m in methods} if methods else available
    return evaluate(run, HORIZONS, chosen, step=STEP.get(scenario, 5.0))


def _run_all(jobs, workers):
    if workers <= 1:
        return [_job(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(_job, jobs))


def _pool(results):
    merged = {}
    for res in results:
        merged[res.scenario] = merged[res.scenario].merge(res) if res.scenario in merged else res
    return list(merged.values())


def goal_lines(pooled) -> list[str]:
    """Per scenario: which methods reach issue 8's goals (medians, and below const-velocity at every horizon),
    on the absolute error and on the drift since the last fix."""
    lines = []
    for res in pooled:
        if res.scenario in ("static", "push"):
            continue
        for name in res.errors:
            if name in ("const-velocity", "hold-last-fix"):
                continue
            verdicts = []
            for label, table in (("absolute", res.errors), ("drift", res.drift)):
                med = np.nanmedian(table[name][:, 1:], axis=0)
                meets = all(m <= GOALS[h] for m, h in zip(med, res.horizons) if h in GOALS)
                cv = table.get("const-velocity")
                beats = cv is None or bool(np.all(med < np.nanmedian(cv[:, 1:], axis=0)))
                verdicts.append(f"{label}: {'meets' if meets and beats else 'misses'}"
                                + ("" if beats else " (not below const-velocity)"))
            lines.append(f"  {res.scenario:12s} {name:15s} " + "; ".join(verdicts))
    return lines


def error_budget(board_path, seeds, workers) -> str:
    """The seed method on the walk with one MPU-6050 error source at a time (open-sky GPS)."""
    full = MpuErrors()
    ideal = MpuErrors.ideal()
    sources = {
        "ideal sensor": ideal,
        "white noise": replace(ideal, accel_noise_ug_rthz=full.accel_noise_ug_rthz,
                               gyro_noise_dps_rthz=full.gyro_noise_dps_rthz),
        "accel offset": replace(ideal, accel_offset_mg=full.accel_offset_mg),
        "gyro offset": replace(ideal, gyro_offset_dps=full.gyro_offset_dps),
        "scale+cross": replace(ideal, sensitivity_pct=full.sensitivity_pct, cross_axis_pct=full.cross_axis_pct),
        "bias drift": replace(ideal, gyro_drift_dps=full.gyro_drift_dps, accel_drift_mg=full.accel_drift_mg),
        "dlpf+jitter": replace(ideal, dlpf=True, jitter_us=full.jitter_us),
        "all (datasheet)": full,
    }
    jobs = [("walk", s, "open-sky", board_path, e, ["seed"]) for e in sources.values() for s in range(seeds)]
    results = _run_all(jobs, workers)
    head = f"{'seed method, walk':22s}" + "".join(f" {f'{h:g} s med':>10s}" for h in HORIZONS)
    lines = [head, "-" * len(head)]
    for i, label in enumerate(sources):
        chunk = results[i * seeds : (i + 1) * seeds]
        err = np.vstack([r.errors["seed"] for r in chunk])
        lines.append(f"{label:22s}" + "".join(f" {np.nanmedian(err[:, j]):10.1f}" for j in range(1, len(HORIZONS) + 1)))
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("board", nargs="?", default=None, help="board YAML (default: the bundled T-Beam v1.1)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per simulated scenario (default 3)")
    parser.add_argument("--replay-seeds", type=int, default=5, help="degradations of the real walk (default 5)")
    parser.add_argument("--gps", default="open-sky", choices=("open-sky", "poor", "rtk"))
    parser.add_argument("--scenario", action="append", choices=SCENARIOS, help="only these (repeatable)")
    parser.add_argument("--method", action="append", help="only these methods (repeatable)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--no-budget", action="store_true", help="skip the seed method's error-budget table")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    scenarios = args.scenario or list(SCENARIOS)
    jobs = []
    for scenario in scenarios:
        count = args.replay_seeds if scenario == "replay-walk" else args.seeds
        jobs += [(scenario, seed, args.gps, args.board, None, args.method) for seed in range(count)]
    pooled = _pool(_run_all(jobs, args.jobs))
    board = load_board(args.board).board
    print(f"deadreckon accuracy benchmark: board {board.name}, algorithm window {board.algorithm.window}, "
          f"block {board.algorithm.block}, deadband {board.algorithm.deadband_g} g; GPS {args.gps} NEO-6M at "
          f"{board.gps.rate_hz:g} Hz; IMU MPU-6050 datasheet errors at {board.imu.sample_rate_hz:g} Hz")
    print(f"seeds: {args.seeds} per simulated scenario, {args.replay_seeds} for replay-walk; "
          "horizontal error (m) against truth, pooled over seeds and outage starts\n")
    print(format_table(pooled))
    print("\ndrift: error of the displacement since the last fix (the fix's own error taken out), m\n")
    print(format_table(pooled, drift=True))
    print("\ngoals of issue 8 (median <= 3 / 25 / 100 m at 10 / 30 / 60 s, below const-velocity):")
    for line in goal_lines(pooled):
        print(line)
    if not args.no_budget and (not args.method or "seed" in args.method):
        print()
        print(error_budget(args.board, args.seeds, args.jobs))
    print(f"\n({time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
