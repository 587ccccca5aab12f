"""Accuracy benchmark: how far does the device get without GPS?

    python3 benchmarks/accuracy.py                      # every scenario, the 30 reported seeds (over an hour)
    python3 benchmarks/accuracy.py --scenario car       # one scenario
    python3 benchmarks/accuracy.py --scenario replay-car    # the real car only (seconds)
    python3 benchmarks/accuracy.py --seeds 5 --jobs 2   # quicker, wider intervals
    python3 benchmarks/accuracy.py --tuning             # the tuning seeds instead: tune there, report here
    python3 benchmarks/accuracy.py --gps rtk            # perfect fixes: the IMU's own drift only

For every scenario (simulated static / push, walkers carrying the device in a hand, a pocket or a backpack, a
walker who stands holding it, a cyclist, a vibrating car with the device mounted any way up, a car in town, and the
real walk replayed at MPU-6050 quality) and every seed, outages start every few seconds after calibration; each
registered method (codegen.sim.methods: seed, fused, const-velocity, hold-last-fix), and fused with its platform
forced (fused-vehicle, fused-pedestrian; "fused" is the board's own fused_platform, auto on the bundled boards),
estimates the position 10, 30 and 60 s into each outage. The first table gives the horizontal error against truth,
median, 90th percentile and mean in metres, each with a 95 % bootstrap interval that resamples whole runs (one
seed's outages share a road, a device and a fix error, so they are not independent), and the worst outage.

The real car, car-comma2k19 (codegen.sim.comma: 60 s on a highway; its own IMU read at the board's rate and
degraded to an MPU-6050, its u-blox fixes at 1 Hz, the pose as truth), has 10 s outages and 30 s ones (measured at
10 and 30 s), one starting every second, over degradation seeds from the same ranges; docs/simulator.md says how
it is made. Its tuning degradations were used to choose the speed/bias filter's noises: its rows are in-sample
and marked.

Seeds: the reported figures come from codegen.sim.run.REPORT_SEEDS (0-29); algorithms are tuned on TUNING_SEEDS
(100-199) only; both ranges are printed. The replayed real walk is one recording, used for tuning: its rows are
in-sample and marked. The second table gives the drift (the error of the displacement since the last fix, which
removes the NEO-6M's own error), then the real car's tables, then whether each method meets the goals (the first:
median <= 3 / 25 / 100 m at 10 / 30 / 60 s, below const-velocity; vehicles: also p90 <= 3 x median and below every
baseline; the vehicle goal: median <= 3 / 10 / 40 m, p90 <= 3 x median, no outage beyond 1 km, auto within 10 % of
the better forced platform; walks with stops below hold-last-fix in median and p90).
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
from codegen.kernel import fused  # noqa: E402
from codegen.kernel.layout import FUSED  # noqa: E402
from codegen.sim.methods import registered_methods  # noqa: E402
from codegen.sim.mpu6050 import MpuErrors  # noqa: E402
from codegen.sim.run import (  # noqa: E402
    in_sample,
    REAL_CAR,
    REPORT_SEEDS,
    SCENARIOS,
    TUNING_SEEDS,
    build_run,
    evaluate,
    format_table,
    format_table_ci,
    require_recordings,
)

HORIZONS = (10.0, 30.0, 60.0)
GOALS = {10.0: 3.0, 30.0: 25.0, 60.0: 100.0}  # the goals: median horizontal error, m
STEP = {"replay-walk": 2.0}  # s between outage starts (the real walk is short)
# the real car (car-comma2k19, 60 s): 10 s outages, and 30 s ones measured at 10 and 30 s; a start every second
CAR_OUTAGES = ((10.0,), (10.0, 30.0))
CAR_STEP = 1.0
PLATFORMS = ("vehicle", "pedestrian")  # forced beside the board's own fused_platform (the bundled boards: auto)
# Further tables: callables (pooled results, car results by outage length) -> text, printed after the goals. A
# consistency module (the filter's sigma against the truth per outage) joins here without this script importing it.
SECTIONS: list = []


def _forced_platform(platform: str):
    """The fused method with fused_platform forced to `platform`, whatever the board says."""
    code = float(FUSED.param("platform").code(platform))

    def estimate(run, starts, times):
        cfg = replace(fused.FusedConfig.from_board(run.board), platform=code)
        return fused.estimate(run, starts, times, cfg)

    return estimate


def benchmark_methods() -> dict:
    """Every registered method, and fused with each platform forced (fused-vehicle, fused-pedestrian)."""
    methods = registered_methods()
    for platform in PLATFORMS:
        methods[f"fused-{platform}"] = _forced_platform(platform)
    return methods


def _chosen(methods):
    available = benchmark_methods()
    unknown = sorted(set(methods or ()) - set(available))
    if unknown:
        raise SystemExit(f"--method {unknown[0]}: no such method; choose from {', '.join(available)}")
    return {m: available[m] for m in methods} if methods else available


def _job(args):
    scenario, seed, quality, board_path, errors, methods = args
    board = load_board(board_path).board
    if scenario == REAL_CAR:
        run = build_run(REAL_CAR, board, seed=seed, errors=errors)
        return [replace(evaluate(run, h, _chosen(methods), step=CAR_STEP), scenario=f"car-comma {h[-1]:g} s")
                for h in CAR_OUTAGES]
    run = build_run(scenario, board, seed=seed, quality=quality, errors=errors)
    return evaluate(run, HORIZONS, _chosen(methods), step=STEP.get(scenario, 5.0))


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


BASELINES = ("const-velocity", "hold-last-fix")
VEHICLES = ("car", "bike", "car-town")


def goal_lines(pooled) -> list[str]:
    """Per scenario: which methods reach the goals (medians, and below const-velocity at every horizon), on
    the absolute error and on the drift since the last fix; for vehicles also the vehicle goal (p90 <= 3 x median, below
    every baseline)."""
    lines = []
    for res in pooled:
        if res.scenario in ("static", "push"):
            continue
        for name in res.errors:
            if name in BASELINES:
                continue
            verdicts = []
            for label, table in (("absolute", res.errors), ("drift", res.drift)):
                med = np.nanmedian(table[name][:, 1:], axis=0)
                meets = all(m <= GOALS[h] for m, h in zip(med, res.horizons) if h in GOALS)
                cv = table.get("const-velocity")
                beats = cv is None or bool(np.all(med < np.nanmedian(cv[:, 1:], axis=0)))
                verdicts.append(f"{label}: {'meets' if meets and beats else 'misses'}"
                                + ("" if beats else " (not below const-velocity)"))
            if res.scenario in VEHICLES:
                err = res.errors[name][:, 1:]
                med, p90 = np.nanmedian(err, axis=0), np.nanpercentile(err, 90, axis=0)
                spread = bool(np.all(p90 <= 3 * med))
                below = all(np.all(med < np.nanmedian(res.errors[b][:, 1:], axis=0)) for b in BASELINES + ("seed",)
                            if b in res.errors and b != name)
                verdicts.append(f"vehicle goal: {'meets' if spread and below and 'meets' in verdicts[0] else 'misses'}"
                                f" (p90/median {', '.join(f'{r:.1f}' for r in p90 / med)}"
                                f"{'' if below else '; not below every baseline'})")
            tag = " (in-sample)" if in_sample(res.scenario) else ""
            lines.append(f"  {res.scenario:16s} {name:16s} " + "; ".join(verdicts) + tag)
    return lines


GOALS_VEHICLE = {10.0: 3.0, 30.0: 10.0, 60.0: 40.0}  # the vehicle goal: a vehicle's median horizontal error, m
WORST_M = 1000.0  # the vehicle goal: no vehicle outage beyond this, m
WALKS_WITH_STOPS = ("walk-stand", "replay-walk")


def _platform_name(board) -> str:
    return str(getattr(board.algorithm, FUSED.board_key(FUSED.param("platform"))))


def platform_goal_lines(results) -> list[str]:
    """The vehicle and walk goals per vehicle scenario (simulated and the real car) and per walk with stops, for each fused
    variant present."""
    lines = []
    variants = ("fused",) + tuple(f"fused-{p}" for p in PLATFORMS) + ("eskf", "eskf-c")  # the error-state filter
    for res in results:
        vehicle = res.scenario in VEHICLES or res.scenario.startswith("car-comma")
        if not vehicle and res.scenario not in WALKS_WITH_STOPS:
            continue
        forced = [res.errors[f"fused-{p}"][:, 1:] for p in PLATFORMS if f"fused-{p}" in res.errors]
        for name in (v for v in variants if v in res.errors):
            err = res.errors[name][:, 1:]
            med, p90 = np.nanmedian(err, axis=0), np.nanpercentile(err, 90, axis=0)
            if vehicle:
                goals = [GOALS_VEHICLE[h] for h in res.horizons]
                checks = [("median", bool(np.all(med <= goals))), ("p90 <= 3 x median", bool(np.all(p90 <= 3 * med))),
                          ("worst <= 1 km", bool(np.nanmax(err) <= WORST_M))]
                if name == "fused" and forced:
                    best = np.min([np.nanmedian(f, axis=0) for f in forced], axis=0)
                    checks.append(("auto within 10 % of the better forced", bool(np.all(med <= 1.1 * best))))
            elif "hold-last-fix" not in res.errors:
                lines.append(f"  {res.scenario:16s} {name:17s} not judged: hold-last-fix was not run (--method)")
                continue
            else:
                hold = res.errors["hold-last-fix"][:, 1:]
                checks = [("median below hold-last-fix", bool(np.all(med < np.nanmedian(hold, axis=0)))),
                          ("p90 below hold-last-fix", bool(np.all(p90 < np.nanpercentile(hold, 90, axis=0))))]
            missed = [label for label, ok in checks if not ok]
            verdict = "meets" if not missed else "misses: " + ", ".join(missed)
            tag = " (in-sample)" if in_sample(res.scenario) else ""
            lines.append(f"  {res.scenario:16s} {name:17s} {verdict}{tag}")
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


def _seed_list(first: range, count: int) -> list[int]:
    if count > len(first):
        raise SystemExit(f"at most {len(first)} seeds in {first}")
    return list(first[:count])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("board", nargs="?", default=None, help="board YAML (default: the bundled T-Beam v1.1)")
    parser.add_argument("--seeds", type=int, default=len(REPORT_SEEDS),
                        help=f"seeds per simulated scenario (default {len(REPORT_SEEDS)})")
    parser.add_argument("--tuning", action="store_true", help="run the tuning seeds instead of the reported ones")
    parser.add_argument("--replay-seeds", type=int, default=5, help="degradations of the real walk (default 5)")
    parser.add_argument("--gps", default="open-sky", choices=("open-sky", "poor", "rtk"))
    parser.add_argument("--car-seeds", type=int, default=5,
                        help="degradations of the real car, car-comma2k19 (default 5; 0: leave it out)")
    parser.add_argument("--scenario", action="append", choices=SCENARIOS + (REAL_CAR,),
                        help="only these (repeatable)")
    parser.add_argument("--method", action="append", help="only these methods (repeatable)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--resamples", type=int, default=1000, help="bootstrap resamples (default 1000)")
    parser.add_argument("--budget", action="store_true", help="add the seed method's error-budget table")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    _chosen(args.method)  # an unknown method fails here, before any work
    scenarios = args.scenario or list(SCENARIOS) + ([REAL_CAR] if args.car_seeds > 0 else [])
    require_recordings(scenarios)
    seeds = _seed_list(TUNING_SEEDS if args.tuning else REPORT_SEEDS, args.seeds)
    # the real car's degradations follow the seed ranges too
    car_seeds = _seed_list(TUNING_SEEDS if args.tuning else REPORT_SEEDS, max(args.car_seeds, 1))
    jobs = []
    for scenario in scenarios:
        chosen = {"replay-walk": list(range(args.replay_seeds)), REAL_CAR: car_seeds}.get(scenario, seeds)
        jobs += [(scenario, seed, args.gps, args.board, None, args.method) for seed in chosen]
    results = []
    for out in _run_all(jobs, args.jobs):
        results += out if isinstance(out, list) else [out]
    everything = _pool(results)
    pooled = [res for res in everything if res.horizons == HORIZONS]
    car = [res for res in everything if res.horizons != HORIZONS]
    board = load_board(args.board).board
    print(f"deadreckon accuracy benchmark: board {board.name}, algorithm {board.algorithm.mode}; GPS {args.gps} "
          f"NEO-6M at {board.gps.rate_hz:g} Hz; IMU MPU-6050 datasheet errors at {board.imu.sample_rate_hz:g} Hz")
    print(f"seeds: {'TUNING' if args.tuning else 'reported'} {seeds[0]}-{seeds[-1]} ({len(seeds)} per simulated "
          f"scenario); tuning seeds are {TUNING_SEEDS.start}-{TUNING_SEEDS.stop - 1}, reported seeds "
          f"{REPORT_SEEDS.start}-{REPORT_SEEDS.stop - 1}; replay-walk degradations 0-{args.replay_seeds - 1}")
    print(f"fused is the board's fused_platform ({_platform_name(board)}); fused-vehicle and fused-pedestrian "
          "force it")
    print("horizontal error (m) against truth, pooled over seeds and outage starts; 95 % intervals resample runs;")
    print("worst: the largest error of any outage, and the seed it came from\n")
    if pooled:
        print(format_table_ci(pooled, args.resamples))
        print("\ndrift: error of the displacement since the last fix (the fix's own error taken out), m\n")
        print(format_table(pooled, drift=True))
    if car:
        print(f"\nthe real car, car-comma2k19 (60 s on a highway at 8-20 m/s): its IMU read at "
              f"{board.imu.sample_rate_hz:g} Hz and degraded to an MPU-6050 (degradations {car_seeds[0]}-"
              f"{car_seeds[-1]}), its u-blox fixes at {board.gps.rate_hz:g} Hz, truth the pose (global_pose); "
              f"calibrated on its first {board.algorithm.calibration_s:g} s of driving; an outage every "
              f"{CAR_STEP:g} s\n")
        for res in car:
            print(format_table_ci([res], args.resamples))
            print()
    if pooled:
        print("\ngoals (median <= 3 / 25 / 100 m at 10 / 30 / 60 s, below const-velocity; for "
              "vehicles also: p90 <= 3 x median, below every baseline):")
        for line in goal_lines(pooled):
            print(line)
    print("\nvehicle and walk goals (vehicles: median <= 3 / 10 / 40 m at 10 / 30 / 60 s, p90 <= 3 x median, no outage "
          "beyond 1 km, auto within 10 % of the better forced platform; walks with stops: below hold-last-fix at "
          "every horizon in median and p90):")
    for line in platform_goal_lines(pooled + car):
        print(line)
    for section in SECTIONS:
        print()
        print(section(pooled, car))
    if args.budget and (not args.method or "seed" in args.method):
        print()
        print(error_budget(args.board, min(args.seeds, 3), args.jobs))
    print(f"\n({time.perf_counter() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
