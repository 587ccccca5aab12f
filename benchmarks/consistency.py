"""Consistency of the fused method's Kalman filters and of the error-state filter: does each filter's covariance
describe its real errors?

    python3 benchmarks/consistency.py                         # car and bike, 5 reported seeds each
    python3 benchmarks/consistency.py --scenario car --seeds 10
    python3 benchmarks/consistency.py --tuning                # the tuning seeds
    python3 benchmarks/consistency.py --eskf reference|c      # the error-state filter's rows too (float64 / C)

For each simulated run (codegen.sim.run.build_run) the fused reference (codegen/kernel/fused.py) runs as the device
does, and from every outage start benchmarks/accuracy.py uses (every 5 s, codegen.sim.run.outage_starts) through the
outage's first 60 s; a covariance observer (codegen.kernel.fused.observe_covariances) sees every filter step:

- lateral filter (a vehicle in an outage): before each update, the speed error it carries, e = s - s_true (s_true the
  truth's horizontal speed), against its variance P_ss after the predict;
- position filter (at every fix): the smoothed position's error against the truth, East and North, against its
  variance pxx (the same for both axes);
- speed/bias filter (a vehicle's speed and along-track bias, at every fix it updates at): after its predict, the
  integrated speed's error s - s_true against its variance P_ss (the along-track bias's truth is not in the run).

Each row: how many samples, the mean normalised error squared (NEES: e^2 / P per degree of freedom; 1 for a
consistent filter, above 1 overconfident, below 1 too cautious), the share of samples within 1 sigma (68.3 % for a
consistent Gaussian error) and within 2 sigma (95.4 %), and how often a covariance was repaired (cov_repairs, 0).

The error-state filter (--eskf; codegen/kernel/eskf.py, or its float32 C through cffi): its horizontal position
against the truth, East and North each against its own variance P_pE / P_pN, at every fix ("eskf fix") and 10, 30
and 60 s into every outage ("eskf 10 s", ...): the share of outages whose truth lies within 1 and 2 sigma.
The tilt/offset filter's truth (the tilt error and the offsets left after calibration) is not in the simulator's
run, so it has no row. benchmarks/accuracy.py may import `consistency_rows` and `format_rows` to print the same table
beside its own (one module, so the two files do not collide).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.kernel import fused as F  # noqa: E402
from codegen.sim.run import REPORT_SEEDS, TUNING_SEEDS, build_run, outage_starts, require_recordings  # noqa: E402

LONGEST = 60.0  # s of each outage followed, as benchmarks/accuracy.py's longest horizon
STEP = 5.0  # s between outage starts
SPEED_STEP = 0.05  # s: the truth's speed by central differences over +-this


@dataclass
class Samples:
    """One filter's errors against the truth: `errors` (K, dof) and the variance of each (K,)."""

    filter: str
    errors: np.ndarray
    variances: np.ndarray
    repairs: int = 0

    def merge(self, other: "Samples") -> "Samples":
        return Samples(self.filter, np.vstack([self.errors, other.errors]),
                       np.concatenate([self.variances, other.variances]), self.repairs + other.repairs)


def _true_speed(run, times) -> np.ndarray:
    ahead = run.truth.at(np.asarray(times) + SPEED_STEP)[..., :2]
    behind = run.truth.at(np.asarray(times) - SPEED_STEP)[..., :2]
    return np.linalg.norm(ahead - behind, axis=-1) / (2.0 * SPEED_STEP)


def position_samples(run, fcfg=None) -> Samples:
    """At every fix of the device's pass: the smoothed position's error (East, North) and its variance pxx."""
    t, dt_us, snaps, kcfg, fcfg = F._fused_pass(run, fcfg)
    fixes = sorted(snaps)
    smoothed = np.array([run.gps.enu[j, :2] + (snaps[j][1].fix_ae, snaps[j][1].fix_an) for j in fixes])
    truth = run.truth.at(run.gps.t[fixes])[..., :2]
    variances = np.array([snaps[j][1].fix_pxx for j in fixes])
    repairs = int(snaps[fixes[-1]][1].cov_repairs) if fixes else 0
    ok = run.trusted(run.gps.t[fixes]) & (variances > 0.0)
    return Samples("position", (smoothed - truth)[ok], variances[ok], repairs)


def lateral_samples(run, fcfg=None) -> Samples:
    """Before every lateral update of every outage (60 s from each start): the speed error and its variance."""
    t, dt_us, snaps, kcfg, fcfg = F._fused_pass(run, fcfg)
    starts = outage_starts(run, LONGEST, STEP)
    seen = []  # (time, speed, P_ss)
    repairs = 0
    for j in run.gps.last_valid_before(starts):
        k, snap = snaps[int(j)]
        st = snap.copy()
        t_fix = float(run.gps.t[j])

        def observe(s, which, step, t_fix=t_fix):
            if which == F.FILTER_LATERAL and step == F.STEP_PREDICT:
                seen.append((t_fix + s.since_fix, s.speed, s.nh_pss))

        end = min(int(np.searchsorted(t, t_fix + LONGEST)), len(dt_us))
        previous = F.observe_covariances(observe)
        try:
            for a in range(k, end, 200):
                b = min(a + 200, end)
                F.process(st, run.counts[a:b], dt_us[a:b], kcfg, fcfg)
        finally:
            F.observe_covariances(previous)
        repairs += int(st.cov_repairs - snap.cov_repairs)
    if not seen:
        return Samples("lateral", np.zeros((0, 1)), np.zeros(0), repairs)
    times, speed, var = (np.array(c) for c in zip(*seen))
    ok = run.trusted(times) & (var > 0.0)
    err = speed - _true_speed(run, times)
    return Samples("lateral", err[ok, None], var[ok], repairs)


ESKF_HORIZONS = (10.0, 30.0, 60.0)  # s into an outage


def eskf_samples(run, implementation: str = "reference") -> list[Samples]:
    """The error-state filter's position errors and variances (East and North as separate samples): at every fix
    after the start, and at ESKF_HORIZONS into every outage (every STEP s) that starts after it."""
    from codegen.kernel import eskf as E

    cfg = E.EskfConfig()
    fixes, horizon = [], {h: [] for h in ESKF_HORIZONS}  # (error E, N), (var E, N)
    starts = outage_starts(run, LONGEST, STEP)
    if implementation == "c":
        from codegen.kernel import hosteskf as H

        H.estimate(run, starts[:1], starts[:1, None] + 1.0)  # fills the cache
        t, dt_us, snaps = run.cache[("eskf_c_pass", cfg)]

        def view(state):
            p = H.matrix(state.ek.ffi, state.st.p)
            return state.st.aligned != 0.0, (state.st.pos[0], state.st.pos[1]), (p[0, 0], p[1, 1])

        def advance(state, a, b):
            state.process(run.counts[a:b], dt_us[a:b])
        copy = lambda snap: snap.copy()  # noqa: E731
        repairs = lambda state: state.st.cov_repairs  # noqa: E731
    else:
        E.estimate(run, starts[:1], starts[:1, None] + 1.0, cfg)
        t, dts, acc, gyr, snaps, kcfg = run.cache[("eskf_pass", cfg)]

        def view(state):
            return state.aligned, (state.pe, state.pn), (state.p[0, 0], state.p[1, 1])

        def advance(state, a, b):
            E.mechanise(state, acc[a:b], gyr[a:b], dts[a:b], kcfg, cfg)
        copy = lambda snap: snap.copy()  # noqa: E731
        repairs = lambda state: state.cov_repairs  # noqa: E731
    for j in sorted(snaps):
        started, pos, var = view(snaps[j][1])
        if started and run.trusted(np.array([run.gps.t[j]]))[0]:
            fixes.append((np.subtract(pos, run.truth.at(np.array([run.gps.t[j]]))[0, :2]), var))
    n_samples = len(dt_us) if implementation == "c" else len(dts)
    for j, t0 in zip(run.gps.last_valid_before(starts), starts):
        k, snap = snaps[int(j)]
        if not view(snap)[0]:
            continue
        state = copy(snap)
        if implementation == "c":
            state.st.gps_speed = 0.0
        else:
            state.gps_speed = 0.0
        for h in ESKF_HORIZONS:
            end = min(int(np.searchsorted(t, t0 + h, side="right")) - 1, n_samples)
            if end > k:
                advance(state, k, end)
                k = end
            _, pos, var = view(state)
            when = float(t[min(k, len(t) - 1)])
            horizon[h].append((np.subtract(pos, run.truth.at(np.array([when]))[0, :2]), var))
    last = snaps[max(snaps)][1] if snaps else None
    out = []
    for name, rows in [("eskf fix", fixes)] + [(f"eskf {h:.0f} s", horizon[h]) for h in ESKF_HORIZONS]:
        if rows:
            errors = np.concatenate([np.asarray(e) for e, _ in rows])[:, None]
            variances = np.concatenate([np.asarray(v) for _, v in rows])
        else:
            errors, variances = np.zeros((0, 1)), np.zeros(0)
        out.append(Samples(name, errors, variances, int(repairs(last)) if last is not None else 0))
    return out


def speed_samples(run, fcfg=None) -> Samples:
    """At every fix whose speed/bias filter predicts (a moving vehicle): the integrated speed's error against the
    truth and its variance P_ss after the predict, before the fix corrects it. Each interval between two fixes is
    run again from the state the first left, with the second's updates observed."""
    t, dt_us, snaps, kcfg, fcfg = F._fused_pass(run, fcfg)
    vel = run.gps.device_velocity()
    fixes = sorted(snaps)
    seen = []  # (time, speed, P_ss)
    repairs = 0
    for prev, j in zip(fixes, fixes[1:]):
        k, snap = snaps[prev]
        st = snap.copy()
        stop = snaps[j][0]
        if stop > k:
            F.process(st, run.counts[k:stop], dt_us[k:stop], kcfg, fcfg)
        t_fix = float(run.gps.t[j])

        def observe(s, which, step, t_fix=t_fix):
            if which == F.FILTER_SPEED and step == F.STEP_PREDICT:
                seen.append((t_fix, s.speed, s.sb_pss))

        d = run.gps.enu[j, :2] - run.gps.enu[prev, :2]
        v = vel[j]
        previous = F.observe_covariances(observe)
        try:
            F.position_update(st, float(v[0]), float(v[1]), float(d[0]), float(d[1]), fcfg)
            F.gps_update(st, float(v[0]), float(v[1]), fcfg)
        finally:
            F.observe_covariances(previous)
        repairs += int(st.cov_repairs - snap.cov_repairs)
    if not seen:
        return Samples("speed", np.zeros((0, 1)), np.zeros(0), repairs)
    times, speed, var = (np.array(c) for c in zip(*seen))
    ok = run.trusted(times) & (var > 0.0)
    err = speed - _true_speed(run, times)
    return Samples("speed", err[ok, None], var[ok], repairs)


def summarise(samples: Samples) -> dict:
    """n, NEES per degree of freedom, the shares within 1 and 2 sigma (per error component)."""
    if len(samples.variances) == 0:
        return {"n": 0, "nees": float("nan"), "within1": float("nan"), "within2": float("nan"),
                "repairs": samples.repairs}
    z = np.abs(samples.errors) / np.sqrt(samples.variances)[:, None]
    return {"n": len(samples.variances), "nees": float(np.mean(z * z)), "within1": float(np.mean(z <= 1.0)),
            "within2": float(np.mean(z <= 2.0)), "repairs": samples.repairs}


def consistency_rows(runs, fcfg=None, eskf: str = "") -> list[tuple[str, str, dict]]:
    """(scenario, filter, summary) for the runs (codegen.sim.run.RunData), one row per scenario and filter; eskf
    "reference" or "c": the error-state filter's rows too."""
    merged = {}
    for run in runs:
        found = [lateral_samples(run, fcfg), position_samples(run, fcfg), speed_samples(run, fcfg)]
        if eskf:
            found += eskf_samples(run, eskf)
        for samples in found:
            key = (run.scenario, samples.filter)
            merged[key] = merged[key].merge(samples) if key in merged else samples
    return [(scenario, name, summarise(samples)) for (scenario, name), samples in sorted(merged.items())]


def format_rows(rows, file=sys.stdout) -> None:
    print(f"{'scenario':<12} {'filter':<10} {'samples':>8} {'NEES':>7} {'<=1 sigma':>10} {'<=2 sigma':>10} "
          f"{'repairs':>8}", file=file)
    print(f"{'(consistent)':<12} {'':<10} {'':>8} {'1.00':>7} {'68.3 %':>10} {'95.4 %':>10} {'0':>8}", file=file)
    for scenario, name, s in rows:
        print(f"{scenario:<12} {name:<10} {s['n']:>8d} {s['nees']:>7.2f} {100 * s['within1']:>8.1f} % "
              f"{100 * s['within2']:>8.1f} % {s['repairs']:>8d}", file=file)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("board", nargs="?", default=None, help="board YAML (default: the bundled T-Beam v1.1)")
    parser.add_argument("--scenario", action="append", help="only these (repeatable; default car and bike)")
    parser.add_argument("--seeds", type=int, default=5, help="seeds per scenario (default 5)")
    parser.add_argument("--tuning", action="store_true", help="the tuning seeds instead of the reported ones")
    parser.add_argument("--eskf", choices=("reference", "c"), default="",
                        help="the error-state filter's rows too: its float64 reference or its C (cffi, float32)")
    args = parser.parse_args(argv)
    scenarios = args.scenario or ["car", "bike"]
    require_recordings(scenarios)
    board = load_board(args.board).board
    seeds = list(TUNING_SEEDS if args.tuning else REPORT_SEEDS)[:args.seeds]
    started = time.time()
    rows = []
    for scenario in scenarios:
        rows += consistency_rows((build_run(scenario, board, seed=seed) for seed in seeds), eskf=args.eskf)
    which = f" and the error-state filter ({args.eskf})" if args.eskf else ""
    print(f"Consistency of the fused filters{which}, seeds {seeds[0]}-{seeds[-1]} ({'tuning' if args.tuning else 'reported'}),"
          f" outages every {STEP:.0f} s, {LONGEST:.0f} s each")
    format_rows(rows)
    print(f"({time.time() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
