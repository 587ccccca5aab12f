"""What a vehicle's lateral residual sees in an outage: the measurement behind the fused lateral update.

    python3 benchmarks/lateral_residual.py                    # car, tuning seeds 100-119 (about 6 minutes)
    python3 benchmarks/lateral_residual.py --seeds 5 --scenario bike

A vehicle does not slide sideways, so across its travel direction u its acceleration is the centripetal s r (s the
speed, r the rate about Up) and the residual z = a_lat - s r is the lateral leak (tilt, offsets) minus
(s - s_true) r. This runs the fused reference with the lateral update switched off (`nhc_sigma_ms2` 0) through every
outage of the benchmark (starts every 5 s, 60 s long), in chunks of 0.5 s while the vehicle moves, and compares z
with the truth: the lateral and along-track leaks (the estimated horizontal acceleration minus the true one,
across and along the true velocity) and the speed error. Then, per turn (|r| > 0.12 rad/s), the speed error a
least-squares fit of z = -e r gives against the true one; and, per outage that turns by 45 degrees or more in its
first 30 s, how well the along-track leak is predicted from a fit of the fold of offsets into tilt to the lateral
leak (the true one, and the measured z). Tuning seeds only (codegen.sim.run.TUNING_SEEDS).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from codegen.board.loader import load_board  # noqa: E402
from codegen.kernel import fused as F  # noqa: E402
from codegen.sim.run import TUNING_SEEDS, build_run, outage_starts  # noqa: E402

CHUNK_S = 0.5
OUTAGE_S = 60.0
COLUMNS = ("seed", "outage", "t", "s", "s_true", "r", "z", "leak_along", "leak_lat", "psi")


def chunk_rows(scenario: str, seed: int, board) -> list[tuple]:
    """One row per CHUNK_S of every outage of one run: the columns of COLUMNS."""
    run = build_run(scenario, board, seed=seed)
    fcfg = replace(F.FusedConfig.from_board(board), nhc_sigma_ms2=0.0)
    t, dt_us, snaps, kcfg, fcfg = F._fused_pass(run, fcfg)
    starts = outage_starts(run, OUTAGE_S, 5.0)
    rows = []
    for o, j in enumerate(run.gps.last_valid_before(starts)):
        k, snap = snaps[int(j)]
        st = snap.copy()
        psi = 0.0
        while True:
            end = min(int(np.searchsorted(t, t[k] + CHUNK_S)), len(dt_us))
            if end <= k + 1 or t[end] > starts[o] + OUTAGE_S:
                break
            ang0, s0, dv0, ta = math.atan2(st.uy, st.ux), st.speed, (st.dvx, st.dvy), t[k]
            F.process(st, run.counts[k:end], dt_us[k:end], kcfg, fcfg)
            tb, k = t[end], end
            span = tb - ta
            ang1 = math.atan2(st.uy, st.ux)
            turn = (ang1 - ang0 + math.pi) % (2 * math.pi) - math.pi
            psi += turn
            r = turn / span
            s = 0.5 * (s0 + st.speed)
            ax, ay = (st.dvx - dv0[0]) / span, (st.dvy - dv0[1]) / span  # kernel frame, the chunk's mean
            ux, uy = math.cos(ang0 + 0.5 * turn), math.sin(ang0 + 0.5 * turn)
            z = (-uy * ax + ux * ay) - s * r
            v0, v1 = run.truth.velocity_at(np.array([ta, tb]))[:, :2]
            v = 0.5 * (v0 + v1)
            s_true = float(np.linalg.norm(v))
            leak = np.array([st.cos_t * ax - st.sin_t * ay, st.sin_t * ax + st.cos_t * ay]) - (v1 - v0) / span
            course = np.array([st.cos_t * ux - st.sin_t * uy, st.sin_t * ux + st.cos_t * uy])  # u, true ENU
            fwd = v / s_true if s_true > 0.5 else course
            lat = np.array([-fwd[1], fwd[0]])
            rows.append((seed, o, tb - starts[o], s, s_true, r, z, float(leak @ fwd), float(leak @ lat), psi))
    return rows


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def report(data: np.ndarray) -> str:
    c = {name: data[:, i] for i, name in enumerate(COLUMNS)}
    e = c["s"] - c["s_true"]
    moving = (c["s_true"] > 2.0) & (c["s"] > 2.0) & (c["t"] > 0.0)
    lines = [f"{'0.5 s chunks, moving':22s} {'n':>7s} {'rms z':>7s} {'lat leak':>9s} {'along leak':>11s} {'e r':>7s}"
             f" {'corr(z, lat)':>13s} {'corr(z, lat-er)':>16s} {'rms rest':>9s}  (m/s^2)"]
    for label, m in (("all", moving), ("turning |r| > 0.1", moving & (np.abs(c["r"]) > 0.1)),
                     ("straight |r| < 0.03", moving & (np.abs(c["r"]) < 0.03))):
        model = c["leak_lat"] - e * c["r"]
        lines.append(f"{label:22s} {m.sum():7d} {_rms(c['z'][m]):7.3f} {_rms(c['leak_lat'][m]):9.3f}"
                     f" {_rms(c['leak_along'][m]):11.3f} {_rms((e * c['r'])[m]):7.3f}"
                     f" {np.corrcoef(c['z'][m], c['leak_lat'][m])[0, 1]:13.2f}"
                     f" {np.corrcoef(c['z'][m], model[m])[0, 1]:16.2f}"
                     f" {_rms((c['z'] - model)[m]):9.3f}")
    # per turn: the speed error from z = -e r, least squares
    turns = []
    key = c["seed"] * 1000 + c["outage"]
    for kk in np.unique(key):
        idx = np.flatnonzero((key == kk) & (c["t"] > 0.0))
        on = (np.abs(c["r"][idx]) > 0.12) & (c["s"][idx] > 2.0)
        i = 0
        while i < len(idx):
            if not on[i]:
                i += 1
                continue
            j = i
            while j < len(idx) and on[j]:
                j += 1
            seg = idx[i:j]
            fit = -np.sum(c["z"][seg] * c["r"][seg]) / np.sum(c["r"][seg] ** 2)
            turns.append((c["t"][seg[-1]], e[seg].mean(), fit))
            i = j
    turns = np.array(turns)
    lines += ["", f"{'per turn (|r| > 0.12)':22s} {'n':>7s} {'rms e':>7s} {'rms(e - fit)':>13s} {'corr':>6s}  (m/s)"]
    for lo, hi in ((0, 10), (10, 30), (30, 60)):
        m = (turns[:, 0] > lo) & (turns[:, 0] <= hi)
        lines.append(f"{f'ends {lo}-{hi} s in':22s} {m.sum():7d} {_rms(turns[m, 1]):7.3f}"
                     f" {_rms(turns[m, 1] - turns[m, 2]):13.3f} {np.corrcoef(turns[m, 1], turns[m, 2])[0, 1]:6.2f}")
    # per turning outage: the fold fitted to the lateral leak, lat = a - m (1 - cos psi) + k sin psi, predicts
    # along = e_u + k (1 - cos psi) + m sin psi (e_u: the along-track leak at the start)
    fits = {"true lateral leak": [], "measured z": []}
    for kk in np.unique(key):
        m = (key == kk) & moving & (c["t"] <= 30.0)
        if m.sum() < 20 or np.ptp(c["psi"][m]) < math.radians(45):
            continue
        p = c["psi"][m]
        basis = np.stack([np.ones_like(p), -(1 - np.cos(p)), np.sin(p)], axis=1)
        e_u = c["leak_along"][m][:4].mean()
        for label, y in (("true lateral leak", c["leak_lat"][m]), ("measured z", c["z"][m])):
            _, mm, kk2 = np.linalg.lstsq(basis, y, rcond=None)[0]
            pred = e_u + kk2 * (1 - np.cos(p)) + mm * np.sin(p)
            fits[label].append((_rms(c["leak_along"][m]), _rms(c["leak_along"][m] - pred)))
    lines += ["", f"{'fold fitted to':22s} {'outages':>7s} {'along leak med / p90':>22s} {'left med / p90':>16s}"
              "  (rms over the first 30 s, m/s^2)"]
    for label, vals in fits.items():
        a = np.array(vals)
        lines.append(f"{label:22s} {len(a):7d} {np.median(a[:, 0]):10.3f} / {np.percentile(a[:, 0], 90):.3f}"
                     f" {np.median(a[:, 1]):8.3f} / {np.percentile(a[:, 1], 90):.3f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="car", choices=("car", "bike"))
    parser.add_argument("--seeds", type=int, default=20, help="tuning seeds from 100 (default 20)")
    args = parser.parse_args(argv)
    board = load_board(None).board
    seeds = list(TUNING_SEEDS)[: args.seeds]
    rows = []
    for seed in seeds:
        rows += chunk_rows(args.scenario, seed, board)
        print(f"seed {seed} done", file=sys.stderr, flush=True)
    print(f"{args.scenario}, TUNING seeds {seeds[0]}-{seeds[-1]}, the fused reference without its lateral update\n")
    print(report(np.array(rows, dtype=float)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
