"""The 1-sigma `post` reports inside a GPS gap, per gap kind: moving, ending at a stop, starting at a stop, and wholly
inside one, on synthetic runs that stand 100-140 s (seeds 55-58: none of the seeds anything was tuned on, 100-199,
nor reported on in benchmarks/post.py); and the misfit model that carries the IMU's misfit into a gap.

Why these bands. The rows of one gap are not independent draws: the error of a bridge is a smooth curve, and inside
a stand it is one constant (the stand's position, from the GPS fixes at its two ends), so one gap gives about one
draw per axis. Four gaps give about 8 draws: the share of them within 1 sigma scatters by sqrt(0.68 * 0.32 / 8) =
0.16 about 0.68, so the band 0.3-0.95 holds an honest sigma (2.3 of that scatter below, the top of what 8 draws
can show above). It fails a sigma off by 2.5x either way: the tests check that the same errors with the sigma
scaled by 2.5 (then within 1 sigma 0.95-1.00, the 2-sigma band always) or by 1/2.5 fall outside the bands. The
RMS of error / sigma over the rows is the second check: honest ~1 (for 8 draws, chi-square: 0.58-1.39 nine
times in ten), a 2.5x too wide sigma gives about 0.4, a 2.5x too narrow about 2.5; the band 0.45-1.5 tells those apart.

The target band. Pooled over the four gaps of a kind, the share within 1 sigma lies in 55-80 % on these seeds
(62-67 % with the gyro bridge's misfit counted in place of the bias and tilt priors where it is smaller; before
that, the 30 s gaps ending and starting at the stop covered 0.82 and 0.81 on the benchmark's seeds, too wide). That band is narrower than what 8 draws can always show, so it is
checked as it holds here, on these seeds, as a regression bound, beside the bands above that say why.

`python3 benchmarks/post.py stops` prints the same per kind over more seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

from codegen.post import PostOptions, process
from codegen.post.bridge import ImuMisfit
from codegen.post.gapcheck import cut_gap, gap_errors, truth_about
from codegen.post.synthetic import ORIGIN, Scenario, make_run

SEEDS = (55, 56, 57, 58)
STOP = (100.0, 140.0)  # s, the synthetic vehicle stands
LENGTH = 30.0  # s of missing epochs
KINDS = {  # gap start: 3 s into the stop, 3 s before it ends, wholly inside it, and well before it
    "ends at a stop": STOP[0] + 3.0 - LENGTH,
    "starts at a stop": STOP[1] - 3.0,
    "stationary": STOP[0] + 0.5 * (STOP[1] - STOP[0] - LENGTH),
    "moving": 40.0,
}
ONE_SIGMA_BAND = (0.3, 0.95)
TARGET_BAND = (0.55, 0.80)  # the share within 1 sigma per kind, pooled over its gaps
Z_RMS_BAND = (0.45, 1.5)
TWO_SIGMA_MIN = 0.8


def _statistics(errors, scale: float = 1.0) -> tuple[float, float, float]:
    """(share within 1 sigma, share within 2 sigma, RMS of error / sigma) over all rows, east and north, with the
    sigma scaled by `scale`."""
    post = np.concatenate([e.post.ravel() for e in errors])
    sigma = scale * np.concatenate([e.sigma.ravel() for e in errors])
    z = post / sigma
    return float(np.mean(np.abs(z) <= 1.0)), float(np.mean(np.abs(z) <= 2.0)), float(np.sqrt(np.mean(z**2)))


def _honest(one: float, two: float, z_rms: float) -> bool:
    return (ONE_SIGMA_BAND[0] <= one <= ONE_SIGMA_BAND[1] and two >= TWO_SIGMA_MIN
            and Z_RMS_BAND[0] <= z_rms <= Z_RMS_BAND[1])


@pytest.mark.parametrize("kind", list(KINDS))
def test_sigma_covers_the_error_per_gap_kind(kind):
    start = KINDS[kind]
    errors = []
    for seed in SEEDS:
        log, truth = make_run(Scenario(duration=200.0, seed=seed, stops=(STOP,)))
        result = process(cut_gap(log, start, LENGTH), PostOptions(plots=False))
        t = result.track.t
        e = gap_errors(result, start, LENGTH, t, truth_about(result, truth.position(t), ORIGIN))
        assert e.post_rms < e.hermite_rms, (kind, seed, e.post_rms, e.hermite_rms)
        errors.append(e)
    one, two, z_rms = _statistics(errors)
    assert _honest(one, two, z_rms), (kind, one, two, z_rms)
    assert TARGET_BAND[0] <= one <= TARGET_BAND[1], (kind, one)
    # the bands have teeth: the same errors against a sigma 2.5x too wide or too narrow fail them
    assert not _honest(*_statistics(errors, 2.5)), (kind, _statistics(errors, 2.5))
    assert not _honest(*_statistics(errors, 1 / 2.5)), (kind, _statistics(errors, 1 / 2.5))
    if kind == "stationary":  # what the stand allows: the fixes' noise at its ends, never kilometres
        assert max(float(e.sigma.max()) for e in errors) < 2.0


def _misfit(velocity_error: np.ndarray, power: float = 4.0, doppler: float = 0.05, step: float = 0.25, seed: int = 0):
    """ImuMisfit of a run whose IMU velocity is off from the truth by `velocity_error` (K+1,3) at the epochs, the GPS
    velocity carrying white Doppler noise of `doppler` m/s, the horizontal acceleration power `power`."""
    n = len(velocity_error) - 1
    t = np.arange(n + 1) * step
    rng = np.random.default_rng(seed)
    gps = velocity_error + rng.normal(0.0, doppler, velocity_error.shape)
    residual = np.diff(gps, axis=0)
    sigma = np.full((n, 3), doppler)
    return ImuMisfit.from_intervals(t[:-1], t[1:], residual, np.full(n, power), sigma, sigma, np.ones(n, dtype=bool))


def test_misfit_tells_a_random_walk_from_a_bounded_swing_and_a_bias():
    """A white acceleration error is found at its density at every time scale; a hand's swing (a bounded velocity
    oscillation at the step rate) has a large misfit per interval that cancels over a gap's length (its white
    equivalent falls as 1 / sqrt(W)); a constant bias is what the gap's two ends take out (nothing is left)."""
    n, step, power = 2000, 0.25, 4.0
    rng = np.random.default_rng(1)
    walk = np.cumsum(np.concatenate([np.zeros((1, 3)), rng.normal(0.0, 0.1 * np.sqrt(step), (n, 3))]), axis=0)
    t = np.arange(n + 1)[:, None] * step

    def density(m, window):
        return np.sqrt(m.relative_power(window) * power)

    white = _misfit(walk)
    for window in (1.0, 10.0, 30.0):
        assert 0.085 < density(white, window) < 0.115, window
    swing = _misfit(0.2 * np.sin(2 * np.pi * 1.9 * t) * np.ones((1, 3)))
    assert density(swing, 1.0) > 4 * density(swing, 30.0)
    assert density(swing, 30.0) < 0.12  # the per-interval figure would grow a 30 s gap's sigma as a random walk
    assert density(swing, 10.0) / density(swing, 30.0) == pytest.approx(np.sqrt(3.0), rel=0.3)
    assert density(_misfit(0.05 * t * np.ones((1, 3))), 10.0) < 0.01
    # per unit of acceleration power: the same misfit over twice the power is half the relative power
    loud = _misfit(walk, power=2 * power)
    assert loud.relative_power(10.0) == pytest.approx(0.5 * white.relative_power(10.0), rel=1e-9)


def test_misfit_windows_never_cross_a_gap():
    """Stretches are split where an interval is unusable (a GPS gap): a window spans one stretch, so a jump across
    the gap is never read as misfit."""
    n = 400
    t = np.arange(n + 1) * 0.25
    residual = np.zeros((n, 3))
    usable = np.ones(n, dtype=bool)
    usable[200] = False
    residual[200] = 50.0  # the gap's own interval: a huge velocity jump
    sigma = np.full((n, 3), 0.01)
    m = ImuMisfit.from_intervals(t[:-1], t[1:], residual, np.ones(n), sigma, sigma, usable)
    assert set(np.unique(m.stretch)) == {0, 1}
    assert m.relative_power(10.0) == 0.0


def test_gyro_misfit_measures_a_body_fixed_error_the_gyro_bridge_turns_round():
    """GyroTrack orients each window as a gyro span there would be and measures the velocity misfit left: a
    body-fixed acceleration error added to the sensor's readings (as a bias error would be) shows in it in
    proportion to its square (the cross term with the run's own errors cancels between +delta and -delta)."""
    from codegen.post.bridge import GyroTrack

    log, _ = make_run(Scenario(duration=200.0, seed=101))
    log = cut_gap(log, 150.0, 10.0)  # a gap: the gyro bias is estimated for its span, and removed here too
    result = process(log, PostOptions(plots=False))
    assert result.gaps.gyro_bias is not None
    o = result.orientation
    moving = o.t[o.valid][result.intervals.moving[o.valid]]
    gyro = log.imu.gyro - result.gaps.gyro_bias if result.gaps.gyro_bias is not None else log.imu.gyro
    gps = result.log.gps

    def measured(delta: float) -> float:
        acc = log.imu.acc - o.bias + np.array([delta, 0.0, 0.0])
        track = GyroTrack.build(result.imu_t, acc, gyro, moving, o.slerp(), gps.t, gps.vel, gps.sigma_vel)
        return track.relative_power(30.0)

    base = measured(0.0)
    small = 0.5 * (measured(0.05) + measured(-0.05)) - base
    large = 0.5 * (measured(0.1) + measured(-0.1)) - base
    assert small > 0.0 and large / small == pytest.approx(4.0, rel=0.15), (base, small, large)
