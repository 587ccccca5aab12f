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
    if args.window < 1:
        raise UserError("--window must be at least 1")
    if args.rate <= 0:
        raise UserError("--rate must be positive")
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
