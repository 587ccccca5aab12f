"""The app's dead reckoning through GPS outages equals its method's reference.

The generated app runs unmodified on the emulated board (codegen/sim/mpsim) through simulated walks and drives with
three GPS outages each: walk and car, algorithm seed and fused, the generated fallback and the x64 natmod, 24 outages.
A tap (tests/appkit.py) records what the app fed its kernel and where it took each fix; the references of
codegen/kernel then run on exactly those samples, with each fix at the sample where the app had it, and every
position the app computes in IMU mode is compared with the reference's position for the same samples.

What may differ, and why (the bound, derived per comparison):
- float32: the kernel computes in float32 (the natmod; the fallback rounds at every store of its state). Fused: the
  running-sum bound of tests/test_fused.py (N eps |path| + 1e-4 m for the state since calibration), twice (the offset
  is a difference of two such positions), plus the app's own geodesy between fixes (offset_latlon rounds to 1e-7
  degree, ~1.1 cm per km: 2e-5 of the path). Seed: kernelkit.window_bound chained over the windows since the fix
  (errors composed: a velocity error dv adds dv T), from the orientation error the app's calibration left.
- sample timing: the fused method takes any number of samples, so the fix falls exactly between two samples in both.
  The seed's kernel integrates whole blocks of b samples: the samples of the fix's block read before the fix are
  integrated after it. The app takes their time back at the fix's velocity (v0 T_r); what remains is exact and is
  added to the reference: the block's held acceleration a over those T_r seconds, a T_r (t - t_fix) + a T_r^2 / 2.
Neither bound knows where the outage started: an app that loses samples, time or a window shows as metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from appkit import TAP, driving_world, outage_world, read_record, x86_natmod

from codegen.board.loader import load_board
from codegen.kernel import fused as F
from codegen.kernel import reference as ref
from codegen.kernel.reference import KernelConfig
from codegen.sim import methods, neo6m
from codegen.sim.harness import generate_app, run_app
from conftest import board_micropython
from kernelkit import U, window_bound

EPS32 = 2.0**-24
EPS30 = 2.0**-22  # CircuitPython's boards: 30-bit floats, 22 significant bits (tests/test_circuitpython_app.py)
DURATION = 75.0
OUTAGES = [(26.5, 36.5), (44.5, 54.5), (62.5, 72.5)]  # fixes at whole seconds: the last one at 26, 44, 62 s
MODE_IMU = 1
SEEDS = {"walk": 41, "car": 42}


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    """Per algorithm: the board, its generated app, and (lazily) its x64 natmod folder."""
    made = {}
    for mode in ("seed", "fused"):
        folder = tmp_path_factory.mktemp(mode)
        yaml = folder / f"tbeam-{mode}.yaml"
        yaml.write_text(f"extends: ttgo-tbeam-v1.1\nname: tbeam-{mode}\nalgorithm:\n  mode: {mode}\n")
        made[mode] = {"board": load_board(yaml).board, "out": generate_app(yaml, folder / "out"), "folder": folder}
    return made


def natmod(entry) -> Path:
    if "natmod" not in entry:
        entry["natmod"] = x86_natmod(entry["out"], entry["folder"] / "natmod")
    return entry["natmod"]


def run_outages(entry, scenario, kernel, work: Path):
    micropython = board_micropython()
    board = entry["board"]
    extra = [natmod(entry)] if kernel == "native" else []
    world, traj, track = outage_world(board, scenario, SEEDS[scenario], DURATION, OUTAGES, work)
    script = work / "tap.py"
    script.write_text(f"DUMP = {str(work / 'record.bin')!r}\n" + TAP)
    run = run_app(micropython, entry["out"], world, work / "w", script=str(script), extra_path=extra)
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    assert f"KERNEL {kernel}" in run.stdout
    return read_record(work / "record.bin"), run, track


def fix_enu(fix, origin):
    return neo6m.geodetic_to_enu(np.array([fix.lat_e7 * 1e-7]), np.array([fix.lon_e7 * 1e-7]), np.array([0.0]),
                                 origin)[0]


def outages_of(rec):
    """The IMU-mode calls grouped by the fix they dead-reckon from: {fix index: [call index, ...]}."""
    groups: dict[int, list[int]] = {}
    for i, c in enumerate(rec.calls):
        if c.mode == MODE_IMU:
            assert c.fix is not None, f"call {i} in IMU mode without a fix"
            groups.setdefault(c.fix, []).append(i)
    return groups


def check_anchor_and_screen(rec, calls, fix):
    for i in calls:
        c = rec.calls[i]
        assert c.anchor == (fix.lat_e7, fix.lon_e7), f"call {i}: anchored at {c.anchor}, the last fix was " \
                                                       f"{(fix.lat_e7, fix.lon_e7)}"
        lat, lon = ref.offset_latlon_e7(*c.anchor, float(c.enu[0]), float(c.enu[1]))
        assert abs(c.pos[0] - lat) <= 1 and abs(c.pos[1] - lon) <= 1, (i, c.pos, (lat, lon))


# ------------------------------------------------------------------------------------------------------- fused
def fused_compare(rec, board, origin, eps=EPS32):
    """Per app call: (reference offset from its anchor, bound, path since the fix) after it, or None; `eps`: the
    unit roundoff of the interpreter the app ran on (float32; CircuitPython's 30-bit floats: EPS30)."""
    kcfg = KernelConfig.from_board(board)
    fcfg = F.FusedConfig.from_board(board)
    assert F.IDX["flags"] == 32  # where the tap reads the app's flags (API.md)
    st = F.FusedState()
    assert int(F.calibrate(st, rec.calib, kcfg)) == rec.moved == 0
    samples, dt = rec.stream()
    fixes = sorted((f.index, n) for n, f in enumerate(rec.fixes) if f.running and not f.test_mode)
    k = 0
    path = 0.0
    prev = None  # the previous fix the app anchored at (any, for its metres between fixes)
    base = {}  # fix -> (pe, pn) of the reference right after it, and its smoothed offset
    offsets = []  # per call: (reference offset from its anchor, bound) after the call
    j = 0

    def advance(to):
        nonlocal k, path
        if to > k:
            out, _ = F.process(st, samples[k:to], dt[k:to], kcfg, fcfg)
            path += float(np.hypot(out[0], out[1]))
            k = to

    taken = [n for n, f in enumerate(rec.fixes) if not f.test_mode]

    def take_fixes(before_end):
        """The fixes up to the call's end (before it: before_end; at it: after the call, as the app takes them, a
        fix may set a flag: FAST)."""
        nonlocal j, prev
        while j < len(fixes) and (fixes[j][0] < end if before_end else fixes[j][0] == end):
            idx, n = fixes[j]
            advance(idx)
            fix = rec.fixes[n]
            earlier = [m for m in taken if m < n]
            prev = rec.fixes[earlier[-1]] if earlier else None
            d = fix_enu(fix, origin) - fix_enu(prev, origin) if prev is not None else np.zeros(3)
            F.position_update(st, float(fix.vel[0]), float(fix.vel[1]), float(d[0]), float(d[1]), fcfg)
            F.gps_update(st, float(fix.vel[0]), float(fix.vel[1]), fcfg)
            base[n] = (st.pe, st.pn, st.fix_ae, st.fix_an, path)
            j += 1

    for ci, c in enumerate(rec.calls):
        end = c.start + c.m
        take_fixes(True)
        advance(end)
        assert int(c.before[0]) == int(st.flags), f"call {ci}: the app's flags {int(c.before[0])} differ from the " \
                                                  f"reference's {int(st.flags)}: a threshold decided differently"
        take_fixes(False)
        a = c.fix
        if a is None or a not in base:
            offsets.append(None)
            continue
        pe0, pn0, ae, an, path0 = base[a]
        n_samples = end
        bound = 2 * (n_samples * eps * max(path, 1.0) + 1e-4) + 2 * 2e-5 * path
        offsets.append((np.array([ae + st.pe - pe0, an + st.pn - pn0]), bound, path - path0))
    return offsets


# ------------------------------------------------------------------------------------------------------- seed
def seed_compare(rec, board):
    cfg = KernelConfig.from_board(board)
    rc = ref.calibrate(rec.calib, cfg)
    assert int(rc.moved) == rec.moved == 0
    q_app, bias_app = rec.cal_state[:4], rec.cal_state[4:]
    # the app's calibration is the reference's on the same samples (float32: a few eps of a unit quaternion)
    assert np.allclose(q_app, rc.q, atol=1e-6) and np.allclose(bias_app, rc.gyro_bias_lsb, atol=1e-3)
    samples, dt_us = rec.stream()
    assert len(samples) % cfg.block == 0, "the seed's kernel got a partial block"
    dt = dt_us * 1e-6
    a, qs = methods.enu_acceleration(samples, dt, rc.q, rc.gyro_bias_lsb, cfg)
    held = np.repeat(ref.deadband(ref.block_median(a, cfg.block), cfg.deadband_ms2), cfg.block, axis=0)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    # the app's own kernel output per call, from its own state going in (kernel equivalence on the app's calls)
    for i, c in enumerate(rec.calls):
        q0, v0, b0 = c.before[:4], c.before[4:7], c.before[7:]
        bp, bv, _, res = window_bound(c.samples, c.dt, q0, v0, b0, cfg)
        assert np.all(np.abs(c.out[:3] - res.displacement) <= bp), (i, c.out, res.displacement, bp)
        assert np.all(np.abs(c.out[3:] - res.velocity) <= bv), (i, c.out, res.velocity, bv)
    # orientation error entering the run: the app's calibration against the reference's, and its bias's drift
    theta = float(np.linalg.norm(q_app - rc.q)) + 8 * U
    bias_rate = float(np.linalg.norm(bias_app - rc.gyro_bias_lsb)) * cfg.gyro_rads_per_lsb
    offsets = []
    chain = {}  # fix -> [e_p, e_v, reference velocity] of the chained float32 bound from the fix's block on
    for ci, c in enumerate(rec.calls):
        s0, e = c.start, c.start + c.m
        fix = rec.fixes[c.fix] if c.fix is not None else None
        link = None
        if fix is not None and fix.running:
            b0 = fix.index - fix.index % cfg.block
            if c.fix not in chain and s0 >= b0:
                chain[c.fix] = [0.0, U * float(np.linalg.norm(fix.vel)), fix.vel.astype(np.float64)]
            link = chain.get(c.fix)
        v_in = link[2] if link else np.zeros(3)
        bp, bv, theta_end, res = window_bound(c.samples, c.dt, qs[s0], v_in, rc.gyro_bias_lsb, cfg, theta0=theta)
        span = float(c.dt.sum()) * 1e-6
        theta = theta_end + bias_rate * span
        if link is None:
            offsets.append(None)
            continue
        link[0] += bp + link[1] * span
        link[1] += bv
        link[2] = res.velocity
        s = fix.index
        b0 = s - s % cfg.block
        t_r = t[s] - t[b0]
        a_fix = held[b0]
        _, pos = ref.integrate_zoh(held[s:e], dt[s:e])
        expect = fix.vel * (t[e] - t[s]) + pos[-1] + a_fix * t_r * (t[e] - t[s]) + 0.5 * a_fix * t_r * t_r
        offsets.append((expect[:2], link[0] + 1e-9))
    return offsets


@pytest.mark.parametrize("kernel", ["python", "native"])
@pytest.mark.parametrize("mode", ["fused", "seed"])
@pytest.mark.parametrize("scenario", ["walk", "car"])
def test_outages_follow_the_reference(boards, scenario, mode, kernel, tmp_path):
    entry = boards[mode]
    rec, run, track = run_outages(entry, scenario, kernel, tmp_path)
    assert rec.calib is not None and rec.calls, run.stdout[-1500:]
    origin = track.origin
    offsets = fused_compare(rec, entry["board"], origin) if mode == "fused" else seed_compare(rec, entry["board"])
    groups = outages_of(rec)
    assert len(groups) == len(OUTAGES), f"{len(groups)} outages dead-reckoned, {len(OUTAGES)} expected"
    worst = []
    for fix_n, calls in sorted(groups.items()):
        fix = rec.fixes[fix_n]
        check_anchor_and_screen(rec, calls, fix)
        assert len(calls) >= 3, calls
        errs = []
        for i in calls:
            want, bound = offsets[i][0], offsets[i][1]
            got = rec.calls[i].enu[:2]
            err = float(np.abs(got - want).max())
            errs.append((err, bound, i))
        first_t = (rec.calls[calls[0]].start + rec.calls[calls[0]].m - fix.index) / entry["board"].imu.sample_rate_hz
        err, bound, i = max(errs, key=lambda e: e[0] - e[1])
        moved = float(np.hypot(*offsets[calls[-1]][0]))
        worst.append((fix.index, len(calls), err, bound, moved, first_t))
        print(f"{scenario} {mode} {kernel}: outage from sample {fix.index}: {len(calls)} positions over "
              f"{moved:.1f} m, worst |app - reference| {err:.5f} m (bound {bound:.5f} m; first position "
              f"{first_t:.2f} s after the fix)")
    for fix_index, count, err, bound, moved, _ in worst:
        assert err <= bound, (f"{scenario} {mode} {kernel}: the outage from sample {fix_index} is {err:.3f} m from "
                              f"the reference (bound {bound:.5f} m over {moved:.1f} m)")
    # no time went missing: the intervals the kernel got add up to the clock between the reads (data-ready mode:
    # exactly, per call; the FIFO's records carry the chip's nominal period, read up to a FIFO's backlog late)
    calls = rec.calls
    period = 1e6 / entry["board"].imu.achieved_sample_rate_hz
    elapsed = (calls[-1].t_last - calls[0].t_last) % (1 << 30)
    total = int(sum(int(c.dt.sum()) for c in calls[1:]))
    backlog = (85 if entry["board"].imu.use_fifo else 0) + (2 * entry["board"].algorithm.block if mode == "seed" else 0)
    assert abs(total - elapsed) <= (backlog + 2) * period, (total, elapsed)
    dropped = [int(line.split("dropped=")[1].split()[0]) for line in run.console("DIAG")]
    print(f"{scenario} {mode} {kernel}: the kernel's intervals {total / 1e6:.3f} s, the clock between the reads "
          f"{elapsed / 1e6:.3f} s; dropped samples: {dropped[-1]}")
    if kernel == "native":  # on the board's clock, at the board's rate, the native module misses no sample
        assert dropped[-1] == 0, run.console("DIAG")


def test_fused_app_switched_on_in_a_moving_car_keeps_its_calibration(boards, tmp_path):
    """The default method switched on in a car that drives: the calibration moves, the last fix says the board
    travels, so the app keeps the calibration (it restarted it forever before: "moved! again" on the screen, no dead
    reckoning at all) and its kernel runs from it, the fixes feeding it."""
    entry = boards["fused"]
    world, speed = driving_world(entry["board"], tmp_path, skip_s=60.0, duration=40.0)
    assert speed > 5.0
    script = tmp_path / "tap.py"
    script.write_text(f"DUMP = {str(tmp_path / 'record.bin')!r}\n" + TAP)
    run = run_app(board_micropython(), entry["out"], world, tmp_path / "w", script=str(script),
                  extra_path=[natmod(entry)])
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    lines = run.stdout.splitlines()
    assert any(line.startswith("CAL moved: travelling at") for line in lines), run.stdout[-3000:]
    assert not any(line.startswith("CAL moved: restart") for line in lines)
    assert any(line.startswith("CAL ok") for line in lines)
    rec = read_record(tmp_path / "record.bin")
    assert rec.moved == 1
    samples, _ = rec.stream()
    assert len(samples) > 20 * entry["board"].imu.achieved_sample_rate_hz  # the kernel ran on the rest of the drive
    assert sum(f.running for f in rec.fixes) >= 15  # and took the fixes
