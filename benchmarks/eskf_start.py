"""The error-state filter's start on the move: the yaw fit (codegen/kernel/eskf.py, alignment_fit) fix by fix on a
run that calibrates while it drives, with and without the fix interval that spans the calibration.

    python3 benchmarks/eskf_start.py                         # the real car, car-comma2k19, degradation 0
    python3 benchmarks/eskf_start.py --scenario car-town --seed 102 --until 80

Prints, at each fix before the filter would start (the start's own test is not applied): the intervals in the fit,
|z| (the GPS velocity change over the IMU's: 1 when the fit holds), the fitted yaw and its 1-sigma, and |b| (the
body-fixed horizontal offset a calibration in motion leaves, m/s^2), then the fix the filter starts at with the
default EskfConfig. Host x86-64, float64 reference.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import default_board  # noqa: E402
from codegen.kernel import eskf  # noqa: E402
from codegen.kernel.reference import KernelConfig  # noqa: E402
from codegen.sim.run import REAL_CAR, build_run, require_recordings  # noqa: E402


def trace(run, with_interval: bool, until: float) -> tuple[list[tuple], float | None]:
    """The fit at each fix up to `until` s (never starting), and the fix time the default start test passes."""
    cfg = eskf.EskfConfig()
    kcfg = KernelConfig.from_board(run.board)
    t = run.t_us * 1e-6
    dts = (np.diff(run.t_us) * 1e-6).tolist()
    acc, gyr = eskf._samples(run, kcfg)
    n_cal = int(np.searchsorted(t, run.board.algorithm.calibration_s))
    st = eskf.EskfState()
    eskf.calibrate(st, run.counts[:n_cal], kcfg)
    gps, vel = run.gps, run.gps.device_velocity()
    spanning = eskf.calibration_fix(gps, float(t[0]), float(t[n_cal]))
    if with_interval and spanning is not None:
        eskf.calibration_interval(st, vel[spanning], float(t[n_cal] - gps.t[spanning]))
    rows, started, k = [], None, n_cal
    for j in np.flatnonzero(gps.valid & (gps.t >= t[n_cal])):
        if gps.t[j] > until:
            break
        stop = min(int(np.searchsorted(t, gps.t[j], side="left")), len(dts))
        if stop > k:
            eskf.mechanise(st, acc[k:stop], gyr[k:stop], dts[k:stop], kcfg, cfg)
            k = stop
        trial = st.copy()
        if started is None and eskf.align(trial, float(gps.t[j]), gps.enu[j], vel[j], cfg):
            started = float(gps.t[j])
        eskf._alignment_sums(st, vel[j])
        fit = eskf.alignment_fit(st.al_sums)
        if fit is not None:
            z, c, sigma = fit
            rows.append((float(gps.t[j]), int(st.al_sums[0]), abs(z), math.degrees(math.atan2(z.imag, z.real)),
                         math.degrees(sigma), abs(c / z), float(np.hypot(*vel[j]))))
    return rows, started


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default=REAL_CAR)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--until", type=float, default=40.0, help="s: the last fix shown")
    args = parser.parse_args(argv)
    require_recordings([args.scenario])
    run = build_run(args.scenario, default_board(), seed=args.seed)
    for with_interval in (True, False):
        rows, started = trace(run, with_interval, args.until)
        print(f"\n{args.scenario} seed {args.seed}, "
              f"{'with' if with_interval else 'without'} the calibration's fix interval")
        print(f"{'fix s':>6} {'n':>3} {'|z|':>6} {'yaw deg':>8} {'sigma deg':>9} {'|b| m/s2':>9} {'speed':>6}")
        for row in rows:
            print("%6.1f %3d %6.3f %8.1f %9.2f %9.2f %6.1f" % row)
        print("the filter starts at", "no fix up to %g s" % args.until if started is None else f"{started:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
