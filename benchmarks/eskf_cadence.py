"""What the error-state filter's covariance cadence costs in accuracy: the float32 C (codegen.kernel.hosteskf, the
same outages as benchmarks/accuracy.py: every 5 s, 60 s each) with the covariance propagated every 0.1 s (the
default) and slower, on the simulated vehicles. benchmarks/device.py --algorithm eskf --cov-dt S gives each
cadence's instructions per window on ESP32 code.

    python3 benchmarks/eskf_cadence.py [--seeds 5] [--tuning] [--cov-dt 0.1 --nhc-dt 0.2 ...] [--nhc-sigma 0.2]
                                       [--scenario car ...]

Horizontal error in m against truth, median / p90 over every outage of the seeds, at 10, 30 and 60 s.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.kernel import hosteskf  # noqa: E402
from codegen.kernel.eskf import EskfConfig  # noqa: E402
from codegen.sim.run import REPORT_SEEDS, TUNING_SEEDS, build_run, outage_starts  # noqa: E402

HORIZONS = (10.0, 30.0, 60.0)


def errors(run, cfg: EskfConfig) -> np.ndarray:
    """(outages, horizons) horizontal errors of the C filter with cfg."""
    starts = outage_starts(run, max(HORIZONS), 5.0)
    times = starts[:, None] + np.array(HORIZONS)[None, :]
    est = hosteskf.estimate(run, starts, times, cfg)
    return np.linalg.norm(est - run.truth.at(times)[..., :2], axis=-1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--tuning", action="store_true", help="the tuning seeds instead of the reported ones")
    parser.add_argument("--cov-dt", type=float, action="append", help="s (repeatable; default 0.1 and 0.2)")
    parser.add_argument("--nhc-dt", type=float, action="append",
                        help="s between pseudo-measurements, one per --cov-dt (default: max(0.2, cov_dt))")
    parser.add_argument("--nhc-sigma", type=float, default=0.0,
                        help="m/s: the constraint's noise for every row (default: the filter's)")
    parser.add_argument("--scenario", action="append", help="default car, car-town, bike")
    args = parser.parse_args(argv)
    board = load_board(None).board
    seeds = list(TUNING_SEEDS if args.tuning else REPORT_SEEDS)[:args.seeds]
    cadences = args.cov_dt or [0.1, 0.2]
    nhc = args.nhc_dt or [max(EskfConfig().nhc_dt_s, c) for c in cadences]
    if len(nhc) != len(cadences):
        parser.error("give one --nhc-dt per --cov-dt")
    started = time.time()
    print(f"eskf (float32 C via cffi, x86-64), seeds {seeds[0]}-{seeds[-1]} "
          f"({'tuning' if args.tuning else 'reported'}), outages every 5 s, nhc_sigma "
          f"{args.nhc_sigma or EskfConfig().nhc_sigma:g} m/s; horizontal error m, median / p90")
    print(f"{'scenario':10s} {'cov_dt_s':>8s} {'nhc_dt_s':>8s} " + " ".join(f"{h:>13.0f} s" for h in HORIZONS))
    for scenario in args.scenario or ["car", "car-town", "bike"]:
        runs = [build_run(scenario, board, seed=seed) for seed in seeds]
        for cov_dt, nhc_dt in zip(cadences, nhc):
            cfg = replace(EskfConfig(), cov_dt_s=cov_dt, nhc_dt_s=nhc_dt,
                          nhc_sigma=args.nhc_sigma or EskfConfig().nhc_sigma)
            err = np.vstack([errors(run, cfg) for run in runs])
            cells = " ".join(f"{np.median(err[:, h]):>6.1f} / {np.percentile(err[:, h], 90):>6.1f}"
                             for h in range(len(HORIZONS)))
            print(f"{scenario:10s} {cov_dt:>8.2f} {nhc_dt:>8.2f} {cells}")
    print(f"({time.time() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
