"""The fused method's platform and rest features on a real car: ../shared/data/car-comma2k19 (60 s on a highway,
the dash unit's IMU at ~104 Hz, the car's CAN speed), computed as codegen/kernel/fused.py computes them (float64):
the standard deviation of |f| over stat_tau_s (0.5 s), the share of its variance above vibration_hz (8 Hz) over
vibration_tau_s (2 s), the body rate averaged over stat_tau_s.

    python3 benchmarks/real_car_features.py

Prints, over the samples where the car moves (CAN speed above 1 m/s, after 5 s for the averages to settle): the
distributions, the share that the shaking alone would take for steps (shaken beyond walk_accel_g with a broadband
share at most vibration_ratio), and the share whose amplitude and averaged rate would allow a rest at each limit
(only the speed before and the fixes keep those from rest: docs/fused.md, step 4).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import default_board  # noqa: E402
from codegen.kernel.fused import FusedConfig  # noqa: E402
from codegen.sim.comma import default_car_dir  # noqa: E402
from codegen.sim.run import REAL_CAR, require_recordings  # noqa: E402

DATA = default_car_dir() / "processed_log"
G = 9.80665


def features(fcfg: FusedConfig):
    t = np.load(DATA / "IMU" / "accelerometer" / "t")
    acc = np.load(DATA / "IMU" / "accelerometer" / "value")
    gyro_t = np.load(DATA / "IMU" / "gyro_uncalibrated" / "t")
    gyro = np.load(DATA / "IMU" / "gyro_uncalibrated" / "value")
    gyro = np.stack([np.interp(t, gyro_t, gyro[:, i]) for i in range(3)], axis=-1)
    gyro -= gyro.mean(axis=0)  # uncalibrated: the drive's mean rate taken as the bias
    nf = np.linalg.norm(acc, axis=1)
    mean, var, lp1, lp2, vib, tot = nf[0], 0.0, nf[0], 0.0, 0.0, 0.0
    ws = np.zeros(3)
    std, share, rate = np.zeros(len(t)), np.zeros(len(t)), np.zeros(len(t))
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        alpha = min(1.0, dt / fcfg.stat_tau_s)
        beta = min(1.0, dt * fcfg.vibration_hz * 2.0 * math.pi)
        gamma = min(1.0, dt / fcfg.vibration_tau_s)
        x = nf[k]
        mean += alpha * (x - mean)
        d = x - mean
        var += alpha * (d * d - var)
        lp1 += beta * (x - lp1)
        h = x - lp1
        lp2 += beta * (h - lp2)
        h -= lp2
        vib += gamma * (h * h - vib)
        tot += gamma * (d * d - tot)
        ws += alpha * (gyro[k] - ws)
        std[k], share[k], rate[k] = math.sqrt(var) / G, vib / tot if tot > 0.0 else 0.0, math.degrees(np.linalg.norm(ws))
    speed_t = np.load(DATA / "CAN" / "speed" / "t")
    speed = np.interp(t, speed_t, np.load(DATA / "CAN" / "speed" / "value").ravel())
    moving = (t > t[0] + 5.0) & (speed > 1.0)
    return std[moving], share[moving], rate[moving], speed[moving]


def main() -> int:
    require_recordings([REAL_CAR])
    fcfg = FusedConfig.from_board(default_board())
    std, share, rate, speed = features(fcfg)
    print(f"car-comma2k19: {len(std)} moving samples, CAN speed {speed.min():.1f}-{speed.max():.1f} m/s")
    print(f"|f| std over {fcfg.stat_tau_s} s, mg: p5 {1000 * np.percentile(std, 5):.1f}, median "
          f"{1000 * np.median(std):.1f}, p95 {1000 * np.percentile(std, 95):.1f}")
    print(f"broadband share over {fcfg.vibration_tau_s} s: p1 {np.percentile(share, 1):.3f}, median "
          f"{np.median(share):.3f}, p99 {np.percentile(share, 99):.3f}")
    steps = (std > fcfg.walk_accel_g) & (share <= fcfg.vibration_ratio)
    print(f"steps by the shaking alone: {100 * np.mean(steps):.2f} %; faster than pedestrian_max_ms "
          f"({fcfg.pedestrian_max_ms} m/s): {100 * np.mean(speed > fcfg.pedestrian_max_ms):.1f} %")
    for limit_g in (fcfg.rest_accel_g, 0.02, 0.025, fcfg.idle_accel_g, fcfg.still_accel_g):
        allowed = (std < limit_g) & (rate < fcfg.rest_gyro_dps)
        print(f"|f| std below {1000 * limit_g:.0f} mg and averaged rate below {fcfg.rest_gyro_dps} degree/s: "
              f"{100 * np.mean(allowed):.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
