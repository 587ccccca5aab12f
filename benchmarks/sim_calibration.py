"""Where the simulator's shaking came from: the real recordings' figures beside the simulated scenarios'.

    python3 benchmarks/sim_calibration.py              # seeds 0-5 of each simulated scenario (about a minute)
    python3 benchmarks/sim_calibration.py --seeds 20

Every figure comes from codegen.sim.features on 2 s windows of |f| (steady speed within each window): the shaking
(standard deviation of |f| about its 0.5 s running mean, mg) and the share of its variance above 8 Hz (analogue
filters, bilinear at each stream's rate), the medians and the 10th-90th percentiles over windows by speed band; and
the fused method's own statistic (codegen.sim.features.fused_statistic_share: its Euler steps) on a ~100 Hz stream
(every other sample of the device's 200 Hz), which is how a real car park outside ../shared/data was measured (0.02-0.04). Rows:
- car-comma2k19: the recording's dash unit IMU at ~104 Hz, speed from CAN; it drives at 8-20 m/s only;
- gnss-imu-walk: the hand-held walk's IMU (imu_1730_sf.csv, ~167 Hz), speed from the RTK Doppler;
- the simulated scenarios through the MPU-6050 model at the board's 200 Hz (car, car-town, walk, walk-stand),
  stands counted after the engine runs or the device is picked up.
A second table sets a car's along-track acceleration against the board's deadband: car-comma2k19's highway beside
the simulated car's cruises (what trajectory.CAR_TRAFFIC_MS2 is calibrated on) and its whole moving drive.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.board.model import STANDARD_GRAVITY  # noqa: E402
from codegen.sim import comma, features, mpu6050, replay, trajectory  # noqa: E402
from codegen.sim.run import REAL_CAR, require_recordings  # noqa: E402

BANDS = (("stand", 0.0, 0.05), ("walking", 0.8, 2.0), ("2-7 m/s", 2.0, 7.0), ("8-20 m/s", 8.0, 20.0))


def _band_rows(label, windows, stat=None, stat_speed=None):
    rows = []
    for band, low, high in BANDS:
        w = windows.speeds(low, high)
        if len(w.speed) < 3:
            continue
        row = (f"{label:22s} {band:9s} {len(w.speed):5d} {np.median(w.shaking_mg):7.1f} "
               f"[{np.percentile(w.shaking_mg, 10):5.1f}-{np.percentile(w.shaking_mg, 90):5.1f}] "
               f"{np.median(w.high_share):6.3f} [{np.percentile(w.high_share, 10):.3f}-"
               f"{np.percentile(w.high_share, 90):.3f}]")
        if stat is not None:
            keep = (stat_speed >= low) & (stat_speed < high)
            row += f" {np.median(stat[keep]):8.3f}" if keep.any() else f" {'':8s}"
        rows.append(row)
    return rows


def _simulated(name, seeds, board):
    pooled, stats, speeds = None, [], []
    for seed in seeds:
        tr = trajectory.make_scenario(name, seed=seed, duration=300.0)
        t_us, counts = mpu6050.simulate_imu(tr, board, seed=seed)
        f, _ = mpu6050.counts_to_si(counts, board)
        t = t_us * 1e-6
        speed = np.linalg.norm(tr.velocity_at(t)[:, :2], axis=1)
        awake = tr.events.get("engine_on_s", tr.rest_s) + 1.0  # the engine runs, or the device was picked up
        w = features.window_features(t, f, speed)
        w = w.where(w.start > awake)
        pooled = w if pooled is None else features.WindowFeatures(*(np.concatenate([a, b]) for a, b in zip(
            (pooled.start, pooled.speed, pooled.shaking_mg, pooled.high_share),
            (w.start, w.speed, w.shaking_mg, w.high_share))))
        stat = features.fused_statistic_share(t[::2], f[::2])
        keep = t[::2] > awake + 2.0
        stats.append(stat[keep])
        speeds.append(speed[::2][keep])
    return pooled, np.concatenate(stats), np.concatenate(speeds)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=6, help="seeds per simulated scenario (default 6, from 0)")
    args = parser.parse_args(argv)
    require_recordings(["replay-walk", REAL_CAR])
    board = load_board(None).board
    head = (f"{'stream':22s} {'band':9s} {'wins':>5s} {'shaking mg [p10-p90]':>21s} {'share>8 Hz [p10-p90]':>21s}"
            f" {'fused@100':>8s}")
    lines = [head, "-" * len(head)]
    car = comma.load_car()
    speed = np.interp(car.t, car.can_t, car.can_speed)
    stat = features.fused_statistic_share(car.t, car.accel)
    lines += _band_rows("car-comma2k19 (104 Hz)", features.window_features(car.t, car.accel, speed), stat, speed)
    t, accel_g, _, truth = replay.load_walk()
    walk_speed = np.linalg.norm(truth.velocity_at(t)[:, :2], axis=1)
    walk = features.window_features(t, accel_g * STANDARD_GRAVITY, walk_speed)
    lines += _band_rows("gnss-imu-walk (167 Hz)", walk.where(walk.start < truth.t[-1] - 30.0))
    for name in ("car", "car-town", "walk", "walk-stand"):
        w, stat, speed = _simulated(name, range(args.seeds), board)
        lines += _band_rows(f"sim {name}", w, stat, speed)
    print(f"|f| features per 2 s window; simulated: seeds 0-{args.seeds - 1}, 300 s each, MPU-6050 at "
          f"{board.imu.sample_rate_hz:g} Hz (DLPF {board.imu.dlpf})")
    print("\n".join(lines))
    print()
    print("\n".join(_traffic_rows(car, range(args.seeds), board.algorithm.deadband_g * STANDARD_GRAVITY)))
    return 0


def _traffic_rows(car, seeds, deadband_ms2):
    """A car's along-track acceleration (its speed through a 1 s gaussian, differentiated) under 0.1 m/s^2, within
    the board's deadband and over it: car-comma2k19's highway (CAN speed, after its on-ramp) beside the simulated
    car's cruises (their middles, 2 s in from each end) and its whole drive while it moves."""
    head = f"{'stream':34s} {'s':>6s} {'<0.1':>6s} {f'0.1-{deadband_ms2:.2f}':>9s} {'over':>6s} {'rms m/s^2':>9s}"
    rows = [f"along-track acceleration against the deadband (l = {deadband_ms2:.3f} m/s^2); simulated: seeds "
            f"0-{seeds[-1]}, 420 s each", head, "-" * len(head)]

    def row(label, a, seconds):
        shares = features.deadband_shares(a, deadband_ms2)
        return (f"{label:34s} {seconds:6.0f} {shares[0]:6.2f} {shares[1]:9.2f} {shares[2]:6.2f} "
                f"{np.sqrt(np.mean(a * a)):9.2f}")

    t, a = features.along_track_acceleration(car.can_t, car.can_speed)
    highway = t > 12.0
    rows.append(row("car-comma2k19 highway (CAN, >12 s)", a[highway], np.ptp(t[highway])))
    cruising, moving = [], []
    for seed in seeds:
        tr = trajectory.make_scenario("car", seed=seed)
        speed, a, inside = features.car_cruises(tr)
        cruising.append(a[inside])
        moving.append(a[speed > 1.0])
    for label, parts in (("sim car, cruises", cruising), ("sim car, moving (> 1 m/s)", moving)):
        a = np.concatenate(parts)
        rows.append(row(label, a, len(a) / tr.rate_hz))
    return rows


if __name__ == "__main__":
    sys.exit(main())
