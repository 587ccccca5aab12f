"""A watchdog's reset on the road: what taking up the kernel's state from before the reset buys.

    python3 benchmarks/watchdog_reset.py                         # tuning seeds 100-105, 30 s outages
    python3 benchmarks/watchdog_reset.py --seeds 0,1,2,3,4,5     # reported seeds

The generated app of the default board runs on the emulated board (codegen/sim/mpsim) under the `micropython`
command, as `deadreckon simulate --on-micropython` runs it (its fused fallback kernel), through the simulated car: it
calibrates at rest, drives off, and its I2C bus hangs while the car drives, until the watchdog resets the board; the
calibration after the boot moves. A GPS outage follows once the kernel has had fixes again (--fixes-after: 20, 40,
60 and 80 s of them, a run each). Each outage runs three times on the same world: with the RTC's memory (the app
takes up what fused_keep kept at its last fix before the reset: docs/watchdog.md), on a port without it (the app
keeps the calibration it made in motion: a car's acceleration taken for gravity, its turn rate for the gyro's
bias, and the kernel learns everything again), and without the reset. Prints
the app's horizontal error (m, from its screen) at the outage's horizons, and the median and 90th percentile over
the outages. Conditions: the x86-64 host; the PyPI `micropython` computes in double, the board in float32; the
MPU-6050 and NEO-6M models' errors. About 8 minutes.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.sim import trajectory  # noqa: E402
from codegen.sim.onmicropython import record_on_micropython, screen_positions  # noqa: E402

BOARD = "ttgo-tbeam-v1.1"
WATCHDOG_S = 5.0  # the board's micropython.watchdog_s
HANG_S = WATCHDOG_S + 1.0  # the bus is held past the watchdog, free a second after the reset
MOVING = 3.0  # m/s: the car drives at least this fast through the calibration after the boot
VARIANTS = (("restored", "reset, RTC memory"), ("in motion", "reset, none"), ("no reset", "no reset"))


def hang_time(traj, calibration_s: float) -> float | None:
    """The first moment after the first calibration from which the car drives through the boot's calibration."""
    for t in np.arange(calibration_s + 8.0, traj.duration - 200.0, 1.0):
        span = np.arange(t + WATCHDOG_S, t + WATCHDOG_S + 1.0 + calibration_s + 1.0, 0.25)
        if np.hypot(*traj.velocity_at(span)[:, :2].T).min() > MOVING:
            return float(t)
    return None


def run_one(loaded, traj, seed: int, hang: float, t_loss: float, outage_s: float, horizons, variant: str,
            work: Path):
    """The app's horizontal errors at the horizons of the outage from t_loss (stops where the app restored a
    calibration in a variant that should not, or did not where it should)."""

    def edit(world):
        if variant != "no reset":
            world["i2c"]["0"][0].update(hang_at_s=hang, hang_s=HANG_S)
        world["rtc_memory"] = variant != "in motion"

    rec = record_on_micropython(loaded, traj, seed=seed, duration=t_loss + outage_s + 1.0,
                                outages=[(t_loss, t_loss + outage_s)], work=work, what=variant, edit_world=edit)
    restored = bool(rec.result.console("CAL moved: the calibration from before the reset restored"))
    if restored != (variant == "restored"):
        raise SystemExit(f"seed {seed}, {variant}: the app {'did' if restored else 'did not'} restore")
    shown_t, shown_p, _ = screen_positions(rec.result, rec.gps.origin)
    times = t_loss + np.asarray(horizons, dtype=float)
    k = np.maximum(np.searchsorted(shown_t, times, side="right") - 1, 0)
    return np.linalg.norm(shown_p[k] - traj.at(times)[:, :2], axis=1)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="100,101,102,103,104,105")
    ap.add_argument("--outage", type=float, default=30.0)
    ap.add_argument("--fixes-after", default="20,40,60,80",
                    help="s of fixes between the calibration after the boot and the outage (a run each)")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    after = [float(s) for s in args.fixes_after.split(",")]
    horizons = (10.0, args.outage) if args.outage > 10.0 else (args.outage,)
    loaded = load_board(BOARD)
    calibration_s = loaded.board.algorithm.calibration_s
    cols = "".join(f" {f'{h:g} s':>7s}" for h in horizons)
    head = f"{'seed':>4s} {'reset s':>7s} {'m/s':>5s} {'lost s':>6s}" + "".join(f"  {name:>{len(cols)}s}"
                                                                             for _, name in VARIANTS)
    print(f"deadreckon: a watchdog's reset on the road, board {BOARD} (fused), the simulated car; GPS lost for "
          f"{args.outage:g} s after {args.fixes_after} s of fixes that follow the calibration after the boot; "
          "horizontal error (m) from the app's screen at " + ", ".join(f"{h:g} s" for h in horizons))
    print(head)
    print("-" * len(head))
    errors = {v: [] for v, _ in VARIANTS}
    for seed in seeds:
        traj = trajectory.make_scenario("car", seed=seed)
        hang = hang_time(traj, calibration_s)
        if hang is None:
            print(f"{seed:4d}  (the car never drives through a calibration after a reset)")
            continue
        speed = float(np.hypot(*traj.velocity_at(np.array([hang + WATCHDOG_S]))[0][:2]))
        for fixes in after:
            t_loss = hang + WATCHDOG_S + calibration_s + 1.0 + fixes + 0.5
            line = f"{seed:4d} {hang + WATCHDOG_S:7.1f} {speed:5.1f} {t_loss:6.1f}"
            for variant, _ in VARIANTS:
                with tempfile.TemporaryDirectory(prefix="deadreckon-wdt-") as tmp:
                    err = run_one(loaded, traj, seed, hang, t_loss, args.outage, horizons, variant, Path(tmp))
                errors[variant].append(err)
                line += "  " + "".join(f" {e:7.1f}" for e in err)
            print(line, flush=True)
    print("-" * len(head))
    for label, q in (("median", 50), ("p90", 90)):
        line = f"{label:>25s}"
        for variant, _ in VARIANTS:
            line += "  " + "".join(f" {e:7.1f}" for e in np.percentile(np.array(errors[variant]), q, axis=0))
        print(line)


if __name__ == "__main__":
    main()
