"""Arguments of `deadreckon post` and the call behind them (codegen/cli.py only registers the subcommand)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from codegen.board.model import STANDARD_GRAVITY
from codegen.errors import UserError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="device log, IMU CSV (t,ax,ay,az; with --gps), or a recording folder (RTKLIB .pos + IMU .csv + .tag)")
    p.add_argument("--gps", help="GPS CSV (t,lat,lon,sog,cog,climb) on the IMU's time axis")
    p.add_argument("-o", "--output", default="post-out", help="output folder (default: post-out)")
    p.add_argument("--delay", type=float, help="IMU-to-GPS delay in seconds to use instead of estimating it")
    p.add_argument("--max-lag", type=float, default=1.0, help="delay search range, +- seconds (default 1)")
    p.add_argument("--window", type=int, default=10, help="GPS intervals on each side solved together (default 10)")
    p.add_argument("--min-horizontal-accel", type=float, default=0.5,
                   help="m/s^2 RMS over the window below which yaw is held and the interval flagged (default 0.5)")
    p.add_argument("--accel-offset", help="calibration offset x,y,z in g, subtracted from the raw accelerations")
    p.add_argument("--accel-scale", help="calibration scale x,y,z, applied after the offset")
    p.add_argument("--no-bias", action="store_true", help="do not estimate a constant accelerometer bias")
    p.add_argument("--velocity-only", action="store_true",
                   help="use GPS velocities only (no positions): the path is IMU + Doppler dead reckoning")
    p.add_argument("--rate", type=float, default=10.0, help="trajectory rows per second (default 10)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def _triple(text: str, what: str) -> np.ndarray:
    try:
        values = np.array([float(x) for x in text.split(",")])
    except ValueError:
        values = np.array([])
    if values.shape != (3,):
        raise UserError(f"{what} needs three comma-separated numbers, got {text!r}", hint="for example 0.01,-0.02,0.0")
    return values


MAX_LAG_LIMIT = 30.0  # s: streams further apart than this are on different clocks, not delayed
MAX_HALF_WINDOW = 1000  # GPS intervals on each side
MAX_RATE = 1000.0  # Hz, trajectory rows
MAX_DELAY = 60.0  # s
MAX_MIN_HORIZONTAL_ACCEL = 10.0  # m/s^2: about 1 g; above it no interval would ever be solved


def _in_range(value: float, name: str, low: float, high: float, hint: str, low_open: bool = False) -> None:
    below = value <= low if low_open else value < low
    if not np.isfinite(value) or below or value > high:
        bound = f"{'above' if low_open else 'at least'} {low:g} and at most {high:g}"
        raise UserError(f"{name} is {value:g}; it must be {bound}", hint=hint)


def check_ranges(args: argparse.Namespace) -> None:
    """Every numeric option inside the range where it means something, before any file is read."""
    _in_range(args.max_lag, "--max-lag", 0.0, MAX_LAG_LIMIT, "the delay search covers -max-lag..+max-lag seconds; "
              "to fix the delay instead, give --delay", low_open=True)
    _in_range(args.window, "--window", 1, MAX_HALF_WINDOW, "GPS intervals solved together on each side of each one "
              "(default 10): the device must keep its orientation relative to the track over the window")
    _in_range(args.rate, "--rate", 0.0, MAX_RATE, "trajectory rows per second (default 10)", low_open=True)
    _in_range(args.min_horizontal_accel, "--min-horizontal-accel", 0.0, MAX_MIN_HORIZONTAL_ACCEL,
              "m/s^2 (default 0.5)")
    if args.delay is not None:
        _in_range(args.delay, "--delay", -MAX_DELAY, MAX_DELAY, "seconds the IMU stamps are late by")
    if args.accel_scale:
        scale = _triple(args.accel_scale, "--accel-scale")
        if not np.all(np.isfinite(scale)) or np.any(np.abs(scale) < 0.5) or np.any(np.abs(scale) > 2.0):
            raise UserError(f"--accel-scale {args.accel_scale}: each factor must be within 0.5..2 (or -2..-0.5)",
                            hint="a calibration scale is close to 1")
    if args.accel_offset:
        offset = _triple(args.accel_offset, "--accel-offset")
        if not np.all(np.isfinite(offset)) or np.any(np.abs(offset) > 1.0):
            raise UserError(f"--accel-offset {args.accel_offset}: each offset must be within -1..1 g",
                            hint="offsets are in g, for example 0.01,-0.02,0.0")


class Progress:
    """Stage and percentage on stderr, at most every half second (a long log keeps the user informed)."""

    def __init__(self, stream=None):
        self.stream, self.last, self.stage = stream, 0.0, None

    def __call__(self, stage: str, fraction: float) -> None:
        now = time.monotonic()
        if stage == self.stage and now - self.last < 0.5 and fraction < 1.0:
            return
        self.stage, self.last = stage, now
        stream = self.stream or sys.stderr
        stream.write(f"post: {stage} {100 * fraction:3.0f}%\n")
        stream.flush()


def run_from_args(args: argparse.Namespace) -> int:
    from codegen.post import PostOptions, run_post
    from codegen.post.model import Calibration
    from codegen.post.orientation import OrientationOptions
    from codegen.post.smoother import SmootherOptions

    calibration = None
    if args.accel_offset or args.accel_scale:
        calibration = Calibration(
            offset=_triple(args.accel_offset, "--accel-offset") * STANDARD_GRAVITY if args.accel_offset else np.zeros(3),
            scale=_triple(args.accel_scale, "--accel-scale") if args.accel_scale else np.ones(3),
        )
    check_ranges(args)
    options = PostOptions(
        orientation=OrientationOptions(half_window=args.window, min_horizontal_accel=args.min_horizontal_accel,
                                       estimate_bias=not args.no_bias),
        smoother=SmootherOptions(use_positions=not args.velocity_only, rate=args.rate),
        delay=args.delay, max_lag=args.max_lag, calibration=calibration, plots=not args.no_plots,
    )
    result, files = run_post(Path(args.log), Path(args.output), gps=Path(args.gps) if args.gps else None,
                             options=options, progress=Progress())
    from codegen.post.outputs import report_text

    print(report_text(result), end="")
    print(f"wrote {', '.join(str(p) for p in files.values())}")
    return 0
