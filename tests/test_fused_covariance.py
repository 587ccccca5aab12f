"""Every Kalman filter of the fused method stays consistent, on every implementation (the float64 reference, the
float32 C kernel through cffi, the generated fallback on the unix-port `micropython`):

- each hand-expanded step (the tilt/offset filter's, the lateral filter's and the position filter's predict and
  update) against the generic matrix form on random states: F P F^T + Q, and the Joseph-form update
  (I - K H) P (I - K H)^T + K R K^T with K = P H^T S^-1;
- every covariance symmetric and positive semi-definite after every step over the simulated runs the equivalence
  tests use, driven with a GPS outage so that the lateral filter runs too (tests/fusedkit.py observes each step
  inside each implementation and checks it; the physics tests go through the same check);
- a covariance that went wrong is repaired (reset to the filter's prior), counted in cov_repairs, and not used.

Tolerances: float32 steps of well-conditioned matrices (eigenvalues 0.1-10 of the scale) round each entry to a few
eps32 of the largest one: 1e-5 relative to max|P| leaves two orders of margin; float64: 1e-12.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from codegen.kernel import fused as F
from fusedkit import FCFG, IMPLEMENTATIONS, KCFG, chunks, run

DRIVER = Path(__file__).resolve().parent / "mp_fused_steps.py"
CASES = 6  # random states per step


@pytest.fixture(params=IMPLEMENTATIONS)
def impl(request):
    from conftest import require_tool

    if request.param != "reference":
        require_tool("cc" if request.param == "c" else "micropython")
    return request.param


def _random_covariance(rng, n, scale):
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T / n + 0.1 * np.eye(n))


def _with_covariance(state: np.ndarray, which: int, p: np.ndarray) -> np.ndarray:
    state = state.copy()
    for (i, j), name in F.FILTER_COVARIANCES[which].items():
        state[F.IDX[name]] = p[i, j]
    return state


def _covariance(state, which: int) -> np.ndarray:
    st = F.FusedState()
    for name, x in zip(F.STATE_FIELDS, state):
        setattr(st, name, float(x))
    return F.covariance_matrix(st, which)


def _joseph(p, h, r):
    """The generic update: K = P H^T S^-1, (I - K H) P (I - K H)^T + K R K^T; returns (P+, K)."""
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    i_kh = np.eye(len(p)) - k @ h
    return i_kh @ p @ i_kh.T + k @ r @ k.T, k


# ------------------------------------------------------------------------------- one step on each implementation
def _apply(impl, cases, work):
    """Each case (step, state vector, args) run on `impl`: returns [(state after, returned), ...]. The steps and
    their arguments as the fallback names them; the reference and the C are called with the same values."""
    if impl == "reference":
        return [_apply_reference(*case) for case in cases]
    if impl == "c":
        from codegen.kernel.hostfused import load_fused

        fk = load_fused()
        return [_apply_c(fk, *case) for case in cases]
    from conftest import require_tool
    from kernelkit import write_fallback

    write_fallback(work)
    payload = {"cases": [{"fn": fn, "state": [float(x) if np.isfinite(x) else str(float(x)) for x in state],
                          "args": args} for fn, state, args in cases]}
    (work / "steps.json").write_text(json.dumps(payload))
    done = subprocess.run([require_tool("micropython"), str(DRIVER), str(work / "steps.json")], capture_output=True,
                          text=True, env=dict(os.environ, MICROPYPATH=f"{work}:.frozen"), timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    return [(np.array(state), returned) for state, returned in json.loads(done.stdout.strip().splitlines()[-1])]


def _apply_reference(fn, state, args):
    st = F.FusedState()
    for name, x in zip(F.STATE_FIELDS, state):
        setattr(st, name, float(x))
    if fn == "_kf_update":
        z0, z1, h, r = args
        returned = F._kf_update(st, z0, z1, (h[:3], h[3:]), r, FCFG)
    elif fn == "fused_keep":
        returned = F.keep(st)
    elif fn == "fused_restore":
        returned = F.restore(st, args[0], FCFG)
    else:
        returned = getattr(F, fn)(st, *args, FCFG)
    return st.vector(), returned


def _apply_c(fk, fn, state, args):
    ffi, lib = fk.ffi, fk.lib
    session = fk.session()
    session.set_state_vector(state)
    cfg, st = session.cfg, session.st
    if fn == "_lateral_predict":
        returned = bool(lib.dr_fused_lateral_predict(cfg, st, *args))
    elif fn == "_lateral_correct":
        h, r, y = args
        x = ffi.new("float[4]")
        returned = list(x) if lib.dr_fused_lateral_correct(cfg, st, h, r, y, x) else None
    elif fn == "_kf_predict":
        returned = bool(lib.dr_fused_kf_predict(cfg, st))
    elif fn == "_kf_update":
        z0, z1, h, r = args
        x = ffi.new("float[5]")
        returned = list(x) if lib.dr_fused_kf_update(cfg, st, z0, z1, [h[:3], h[3:]], r, x) else None
    elif fn == "_position_predict":
        phi = ffi.new("float *")
        returned = phi[0] if lib.dr_fused_position_predict(cfg, st, args[0], phi) else None
    elif fn == "_position_correct":
        gain = ffi.new("float[2]")
        returned = list(gain) if lib.dr_fused_position_correct(cfg, st, gain) else None
    elif fn == "_speed_predict":
        returned = bool(lib.dr_fused_speed_predict(cfg, st, *args))
    elif fn == "_speed_correct":
        gain = ffi.new("float[2]")
        returned = list(gain) if lib.dr_fused_speed_correct(cfg, st, args[0], gain) else None
    elif fn == "fused_keep":
        returned = [float(v) for v in session.keep()]
    elif fn == "fused_restore":
        returned = session.restore(args[0])
    else:
        raise ValueError(fn)
    return session.state_vector().astype(float), returned


def _tolerance(impl, p):
    return (1e-12 if impl == "reference" else 1e-5) * float(np.abs(p).max())


# ------------------------------------------------------------------------------------------- the generic forms
def test_lateral_predict_is_f_p_ft_plus_q(impl, tmp_path):
    """The speed error grows by f . (offsets - their estimate): F = I + (row 0: f2, f3 in columns 2, 3). The
    corner P'(0,0) = P00 + 2 (A P)00 + A P A^T needs the cross term twice (it once had it once)."""
    rng = np.random.default_rng(26)
    cases, want = [], []
    for _ in range(CASES):
        p = _random_covariance(rng, 4, rng.uniform(0.01, 1.0))
        f2, f3 = rng.uniform(-3.0, 3.0, 2)
        q_speed, q_leak = rng.uniform(0.0, 0.05, 2)
        f = np.eye(4)
        f[0, 2], f[0, 3] = f2, f3
        want.append(f @ p @ f.T + np.diag([q_speed, q_leak, 0.0, 0.0]))
        cases.append(("_lateral_predict", _with_covariance(F.FusedState().vector(), F.FILTER_LATERAL, p),
                      [float(f2), float(f3), float(q_speed), float(q_leak)]))
    for (state, returned), expected in zip(_apply(impl, cases, tmp_path), want):
        assert returned is True
        np.testing.assert_allclose(_covariance(state, F.FILTER_LATERAL), expected, rtol=0,
                                   atol=_tolerance(impl, expected))


def test_lateral_update_is_the_joseph_form(impl, tmp_path):
    rng = np.random.default_rng(27)
    cases, want = [], []
    for _ in range(CASES):
        p = _random_covariance(rng, 4, rng.uniform(0.01, 1.0))
        h = np.array([-rng.uniform(0.0, 0.5), 1.0, *rng.uniform(-1.0, 1.0, 2)])
        r = float(rng.uniform(0.01, 0.2))
        y = float(rng.uniform(-1.0, 1.0))
        post, k = _joseph(p, h[None, :], np.array([[r]]))
        want.append((post, k[:, 0] * y))
        cases.append(("_lateral_correct", _with_covariance(F.FusedState().vector(), F.FILTER_LATERAL, p),
                      [[float(v) for v in h], r, y]))
    for (state, returned), (post, x) in zip(_apply(impl, cases, tmp_path), want):
        np.testing.assert_allclose(_covariance(state, F.FILTER_LATERAL), post, rtol=0, atol=_tolerance(impl, post))
        np.testing.assert_allclose(returned, x, rtol=0, atol=_tolerance(impl, x) + 1e-7)


def test_tilt_and_offset_predict_adds_the_process_noise(impl, tmp_path):
    """F = I (the leak and the offsets are constants): P + diag(qd, qd, qb, qb, qb), qd = kf_tilt_noise^2 T +
    (kf_turn_noise turn)^2, qb = kf_bias_noise^2 T over the T = kf_t s since the last prediction."""
    rng = np.random.default_rng(28)
    cases, want = [], []
    for _ in range(CASES):
        p = _random_covariance(rng, 5, rng.uniform(0.01, 0.5))
        kf_t, turn = rng.uniform(0.5, 30.0), rng.uniform(0.0, 3.0)
        qd = FCFG.kf_tilt_noise ** 2 * kf_t + (FCFG.kf_turn_noise * turn) ** 2
        qb = FCFG.kf_bias_noise ** 2 * kf_t
        want.append(p + np.diag([qd, qd, qb, qb, qb]))
        state = _with_covariance(F.FusedState().vector(), F.FILTER_TILT, p)
        state[F.IDX["kf_t"]], state[F.IDX["turn"]] = kf_t, turn
        cases.append(("_kf_predict", state, []))
    for (state, returned), expected in zip(_apply(impl, cases, tmp_path), want):
        assert returned is True
        np.testing.assert_allclose(_covariance(state, F.FILTER_TILT), expected, rtol=0, atol=_tolerance(impl, expected))
        assert state[F.IDX["kf_t"]] == 0.0 and state[F.IDX["turn"]] == 0.0


def test_tilt_and_offset_update_is_the_joseph_form_and_feeds_back(impl, tmp_path):
    """z = d + h b + noise, H = [I2 | h] (h: the horizontal rows of R(q) averaged), R = r I2; the offsets found go
    into bax, bay, baz."""
    rng = np.random.default_rng(29)
    cases, want = [], []
    for _ in range(CASES):
        p = _random_covariance(rng, 5, rng.uniform(0.01, 0.5))
        h = rng.uniform(-1.0, 1.0, (2, 3))
        r = float(rng.uniform(0.001, 0.05))
        z = rng.uniform(-0.3, 0.3, 2)
        post, k = _joseph(p, np.hstack([np.eye(2), h]), r * np.eye(2))
        want.append((post, k @ z))
        state = _with_covariance(F.FusedState().vector(), F.FILTER_TILT, p)
        cases.append(("_kf_update", state, [float(z[0]), float(z[1]), [float(v) for v in h.ravel()], r]))
    for (state, returned), (post, x) in zip(_apply(impl, cases, tmp_path), want):
        np.testing.assert_allclose(_covariance(state, F.FILTER_TILT), post, rtol=0, atol=_tolerance(impl, post))
        np.testing.assert_allclose(returned, x, rtol=0, atol=_tolerance(impl, x) + 1e-7)
        np.testing.assert_allclose(state[[F.IDX["bax"], F.IDX["bay"], F.IDX["baz"]]], x[2:], rtol=0,
                                   atol=_tolerance(impl, x) + 1e-7)


def test_position_predict_and_update_are_the_matrix_forms(impl, tmp_path):
    """Per axis x (position) and e (the receiver's error, Gauss-Markov): F = diag(1, phi), Q = diag((pos_step_sigma
    t)^2, pos_sigma^2 (1 - phi^2)), phi = exp(-t / pos_tau_s) to its cubic Taylor polynomial; the fix y = x + e,
    H = [1, 1], R = 0 (the receiver's error is a state)."""
    rng = np.random.default_rng(30)
    cases, want = [], []
    sigma2 = FCFG.pos_sigma_m ** 2
    for _ in range(CASES):
        p = _random_covariance(rng, 2, rng.uniform(0.5, 5.0))
        t = float(rng.uniform(0.2, 1.9))
        x = t / FCFG.pos_tau_s
        phi = 1.0 - x + x * x / 2.0 - x ** 3 / 6.0
        assert abs(phi - np.exp(-x)) < x ** 4 / 24.0
        f = np.diag([1.0, phi])
        prior = f @ p @ f.T + np.diag([(FCFG.pos_step_sigma_ms * t) ** 2, sigma2 * (1.0 - phi * phi)])
        post, k = _joseph(prior, np.array([[1.0, 1.0]]), np.zeros((1, 1)))
        want.append((prior, phi, post, k[:, 0]))
        state = _with_covariance(F.FusedState().vector(), F.FILTER_POSITION, p)
        cases.append(("_position_predict", state, [t]))
        cases.append(("_position_correct", _with_covariance(F.FusedState().vector(), F.FILTER_POSITION, prior), []))
    answers = _apply(impl, cases, tmp_path)
    for k, (prior, phi, post, gain) in enumerate(want):
        (predicted, got_phi), (updated, got_gain) = answers[2 * k], answers[2 * k + 1]
        np.testing.assert_allclose(_covariance(predicted, F.FILTER_POSITION), prior, rtol=0,
                                   atol=_tolerance(impl, prior))
        assert got_phi == pytest.approx(phi, abs=1e-6)
        np.testing.assert_allclose(_covariance(updated, F.FILTER_POSITION), post, rtol=0, atol=_tolerance(impl, prior))
        np.testing.assert_allclose(got_gain, gain, rtol=0, atol=1e-5)


def test_speed_and_bias_predict_and_update_are_the_matrix_forms(impl, tmp_path):
    """A vehicle's speed s and along-track bias b, s integrating the acceleration less b: over t s F = [[1, -t],
    [0, 1]], Q = diag(q_speed, q_bias); the fix's speed, H = [1, 0], R = r."""
    rng = np.random.default_rng(31)
    cases, want = [], []
    for _ in range(CASES):
        p = _random_covariance(rng, 2, rng.uniform(0.01, 1.0))
        t = float(rng.uniform(0.2, 30.0))
        q_speed, q_bias = (float(v) for v in rng.uniform(0.0, 0.05, 2))
        r = float(rng.uniform(0.005, 0.1))
        f = np.array([[1.0, -t], [0.0, 1.0]])
        prior = f @ p @ f.T + np.diag([q_speed, q_bias])
        post, k = _joseph(p, np.array([[1.0, 0.0]]), np.array([[r]]))
        want.append((prior, post, k[:, 0]))
        cases.append(("_speed_predict", _with_covariance(F.FusedState().vector(), F.FILTER_SPEED, p),
                      [t, q_speed, q_bias]))
        cases.append(("_speed_correct", _with_covariance(F.FusedState().vector(), F.FILTER_SPEED, p), [r]))
    answers = _apply(impl, cases, tmp_path)
    for k, (prior, post, gain) in enumerate(want):
        (predicted, ok), (updated, got_gain) = answers[2 * k], answers[2 * k + 1]
        assert ok is True
        np.testing.assert_allclose(_covariance(predicted, F.FILTER_SPEED), prior, rtol=0, atol=_tolerance(impl, prior))
        np.testing.assert_allclose(_covariance(updated, F.FILTER_SPEED), post, rtol=0, atol=_tolerance(impl, post))
        np.testing.assert_allclose(got_gain, gain, rtol=0, atol=1e-5)


def test_a_broken_speed_and_bias_covariance_is_reset_counted_and_not_used(impl, tmp_path):
    """The speed/bias filter's steps on a covariance gone wrong: the step says so, cov_repairs counts it, the speed
    is not known (the next fix restarts it) and the bias's variance is its start's (a still calibration:
    nhc_leak_sigma_ms2^2); speed and bias untouched."""
    base = F.FusedState().vector()
    base[F.IDX["cov_repairs"]] = 2.0
    base[F.IDX["speed"]], base[F.IDX["bias"]] = 12.0, 0.3
    negative = _with_covariance(base, F.FILTER_SPEED, np.diag([0.04, -0.5]))
    not_a_number = _with_covariance(base, F.FILTER_SPEED, np.array([[np.nan, 0.0], [0.0, 0.01]]))
    cases = [("_speed_predict", negative, [1.0, 0.01, 0.001]), ("_speed_correct", not_a_number, [0.02])]
    for (fn, _, _), (state, returned) in zip(cases, _apply(impl, cases, tmp_path)):
        assert returned in (False, None), fn
        assert state[F.IDX["cov_repairs"]] == 3.0, fn
        np.testing.assert_allclose(_covariance(state, F.FILTER_SPEED),
                                   np.diag([F.SPEED_UNKNOWN_VAR, FCFG.nhc_leak_sigma_ms2 ** 2]), rtol=1e-6)
        assert (state[F.IDX["speed"]], state[F.IDX["bias"]]) == pytest.approx((12.0, 0.3)), fn


# ------------------------------------------------------------------------------------------ a reset on the road
def test_keep_copies_out_what_the_declaration_names(impl, tmp_path):
    """fused_keep gives the values codegen/kernel/layout.py's FUSED.kept names, in its order, on every
    implementation (the app writes them to the RTC's memory as they come)."""
    rng = np.random.default_rng(31)
    state = rng.uniform(-2.0, 2.0, F.FUSED.state_floats)
    (after, kept), = _apply(impl, [("fused_keep", state, [])], tmp_path)
    want = state[list(F.FUSED.kept_offsets)]
    np.testing.assert_allclose(kept, want, rtol=0, atol=(0 if impl == "reference" else 1e-6))
    np.testing.assert_allclose(after, state, rtol=0, atol=(0 if impl == "reference" else 1e-6))  # read only


def test_restore_takes_up_the_kept_state_and_restarts_the_tilt(impl, tmp_path):
    """After a calibration that moved: the kept values are taken up; the tilt/offset filter keeps its offsets'
    block and restarts the leak's as the prior's (var R_h R_h^T, from the restored attitude), uncorrelated with the
    offsets; the covariance is symmetric positive semi-definite; the calibration counts as a rest's (cal_moved 0);
    the speed's variance (unknown after the moved calibration) and the rest of the state stay as calibration left
    them. A kept record whose covariance went wrong is repaired and counted, never used."""
    rng = np.random.default_rng(32)
    cases, kept_of = [], []
    for broken in (False, False, True):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        p = _random_covariance(rng, 5, rng.uniform(0.01, 0.3))
        source = _with_covariance(F.FusedState().vector(), F.FILTER_TILT, p)
        source[0:4] = q
        for name in ("bgx", "bgy", "bgz", "bax", "bay", "baz", "bias", "walk_speed"):
            source[F.IDX[name]] = rng.uniform(-1.0, 1.0)
        source[F.IDX["sb_pbb"]] = rng.uniform(0.001, 0.01)
        kept = [float(v) for v in source[list(F.FUSED.kept_offsets)]]
        if broken:
            kept[F.FUSED.kept.index("p33")] = -0.5
        # as fused_calibrate leaves a calibration that moved, over a covariance the restore must not keep any of
        moved = _with_covariance(F.FusedState().vector(), F.FILTER_TILT, _random_covariance(rng, 5, 0.5))
        moved[F.IDX["cal_moved"]] = 1.0
        moved[F.IDX["sb_pss"]] = F.SPEED_UNKNOWN_VAR
        moved[F.IDX["speed"]] = 0.0
        moved[F.IDX["cov_repairs"]] = 4.0
        cases.append(("fused_restore", moved, [kept]))
        kept_of.append((source, p))
    tol = 1e-12 if impl == "reference" else 1e-5
    for (case, (source, p)), (state, _) in zip(zip(cases, kept_of), _apply(impl, cases, tmp_path)):
        broken = case[2][0][F.FUSED.kept.index("p33")] < 0.0
        assert state[F.IDX["cal_moved"]] == 0.0
        assert state[F.IDX["sb_pss"]] == pytest.approx(F.SPEED_UNKNOWN_VAR)
        got = _covariance(state, F.FILTER_TILT)
        if broken:  # repaired to the prior at the restored attitude, counted
            assert state[F.IDX["cov_repairs"]] == 5.0
            st = F.FusedState()
            st.qw, st.qx, st.qy, st.qz = (float(v) for v in source[0:4])
            F._kf_prior(st, FCFG)
            np.testing.assert_allclose(got, F.covariance_matrix(st, F.FILTER_TILT), rtol=0, atol=tol)
            continue
        assert state[F.IDX["cov_repairs"]] == 4.0
        names = [n for n in F.FUSED.kept if n not in ("p22", "p23", "p24", "p33", "p34", "p44")]
        np.testing.assert_allclose([state[F.IDX[n]] for n in names], [source[F.IDX[n]] for n in names], rtol=0,
                                   atol=tol)
        r_h = F.quat_to_matrix(source[0:4])[:2]
        want = np.zeros((5, 5))
        want[:2, :2] = (FCFG.kf_bias_init_g * F.STANDARD_GRAVITY) ** 2 * r_h @ r_h.T
        want[2:, 2:] = p[2:, 2:]
        np.testing.assert_allclose(got, want, rtol=0, atol=tol * np.abs(want).max())
        np.testing.assert_allclose(got, got.T)
        assert np.linalg.eigvalsh(got).min() >= -tol * np.abs(want).max()
        assert state[F.IDX["kf_t"]] == 0.0 and state[F.IDX["turn"]] == 0.0


# ----------------------------------------------------------------------------------------- the repair on device
def test_a_broken_covariance_is_reset_counted_and_not_used(impl, tmp_path):
    """Each filter's step on a covariance gone wrong (a negative variance, one not a number): the step says so,
    the covariance is its prior again (lateral: the filter restarted, all 0; position: restarted at the fix;
    tilt/offset: its start's), cov_repairs counts it, and nothing of the step reached the estimates."""
    base = F.FusedState().vector()
    base[F.IDX["cov_repairs"]] = 2.0
    lateral = _with_covariance(base, F.FILTER_LATERAL, np.diag([-293.0, 0.01, 0.04, 0.04]))
    lateral[F.IDX["nh_u0x"]] = 1.0
    lateral[F.IDX["nh_b"]] = 0.2
    position = _with_covariance(base, F.FILTER_POSITION, np.array([[1.0, 0.5], [0.5, np.nan]]))
    position[F.IDX["fix_ae"]] = 3.0
    tilt = _with_covariance(base, F.FILTER_TILT, np.diag([0.01, 0.01, -0.1, 0.1, 0.1]))
    cases = [("_lateral_predict", lateral, [0.5, 0.0, 0.01, 0.0]),
             ("_lateral_correct", lateral, [[-0.3, 1.0, 0.0, 0.5], 0.1, 0.4]),
             ("_position_predict", position, [1.0]),
             ("_position_correct", position, []),
             ("_kf_update", tilt, [0.1, -0.1, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0], 0.01])]
    answers = _apply(impl, cases, tmp_path)
    for (fn, before, _), (state, returned) in zip(cases, answers):
        assert returned in (False, None), fn
        assert state[F.IDX["cov_repairs"]] == 3.0, fn
    for state, _ in answers[:2]:  # the lateral filter restarted: it starts again on the next sample
        np.testing.assert_array_equal(state[[F.IDX[n] for n in F.NHC_FIELDS]], 0.0)
    for state, _ in answers[2:4]:
        p = _covariance(state, F.FILTER_POSITION)
        np.testing.assert_allclose(p, FCFG.pos_sigma_m ** 2 * np.array([[1.0, -1.0], [-1.0, 1.0]]), rtol=1e-6)
        assert state[F.IDX["fix_ae"]] == 0.0
    state = answers[4][0]
    st = F.FusedState()
    F._kf_prior(st, FCFG)  # identity attitude: offsets x, y across gravity, z along it (variance 0)
    np.testing.assert_allclose(_covariance(state, F.FILTER_TILT), F.covariance_matrix(st, F.FILTER_TILT), rtol=1e-6)
    assert state[F.IDX["bax"]] == state[F.IDX["bay"]] == state[F.IDX["baz"]] == 0.0
    np.testing.assert_array_equal(state[0:4], [1.0, 0.0, 0.0, 0.0])  # no leak rotated out of q


def test_an_outage_with_a_broken_lateral_covariance_keeps_its_speed_and_recovers(tmp_path, impl):
    """test_fused_physics' vehicle in an outage at 6 m/s that believes 8 m/s (4 s straight, then a turn at 0.3
    rad/s), its lateral filter starting with the speed error's variance at -293 (what the missing predict term once
    made of it, 9.5 s into a real outage). The first update finds it broken, restarts the filter (counted once) and
    changes nothing; the restarted filter finds the speed in the turn as a healthy one does."""
    n = 2400
    g, one_g = 9.80665, KCFG.accel_lsb_per_g
    t = np.arange(n) * 0.005
    rate_counts = np.where(t < 4.0, 0.0, np.round(math.degrees(0.3) * KCFG.gyro_lsb_per_dps))
    rate = np.radians(rate_counts / KCFG.gyro_lsb_per_dps)
    lateral = np.round(6.0 * rate / g * one_g)
    road = 0.05 * np.random.default_rng(1).standard_normal(n)
    zero = np.zeros(n)
    samples = np.stack([zero, lateral, np.round((1.0 + road) * one_g), zero, zero, rate_counts],
                       axis=-1).astype(np.int16)
    dt = np.full(n, 5000, dtype=np.int32)
    start = F.FusedState()
    start.mean_f = start.vib_lp1 = g
    start.since_fix = 10.0
    start.speed = start.zr_v = 8.0
    start.flags = float(F.VEHICLE)
    start.nh_pss = -293.0
    steps = [("p", samples[:90], dt[:90]), ("p", samples[90:110], dt[90:110])] + chunks(samples[110:], dt[110:], 200)
    trace = run(impl, steps, tmp_path, start=start, check_covariances=False)
    broken = [(which, step) for which, step, p in trace.covariances if p.min() < -1.0]
    assert broken == [(F.FILTER_LATERAL, F.STEP_PREDICT)]  # seen once, at the first update's predict
    assert trace.at(1, "cov_repairs") == 1.0 and trace.at(-1, "cov_repairs") == 1.0
    assert trace.at(1, "speed") == pytest.approx(8.0, abs=1e-3)  # nothing of the broken step reached the speed
    truth = float(lateral[-1] / one_g * g / rate[-1])  # 6 m/s but for the counts' rounding
    healthy = run(impl, steps, tmp_path, start=replace_state(start, nh_pss=0.0))
    assert healthy.at(-1, "cov_repairs") == 0.0
    assert healthy.at(-1, "speed") == pytest.approx(truth, abs=0.4)  # test_fused_physics' bound
    assert trace.at(-1, "speed") == pytest.approx(healthy.at(-1, "speed"), abs=0.1)  # restarted 0.5 s later


def replace_state(st: F.FusedState, **fields) -> F.FusedState:
    other = st.copy()
    for name, value in fields.items():
        setattr(other, name, value)
    return other


# ------------------------------------------------------------------------------- the simulated runs, with outages
RUNS = [("walk", 11, False), ("walk", 30, False), ("walk", 23, False), ("car", 12, False), ("car", 13, True),
        ("car", 22, False)]


def _outage_steps(scenario, seed, start=10.0, stop=72.0, outage=(28.0, 46.0)):
    """The app's calls on a simulated run: windows between fixes, a fix every second but in the outage."""
    from codegen.board.loader import default_board
    from codegen.sim.run import build_run

    run_ = build_run(scenario, default_board(), seed=seed, duration=stop + 2.0)
    t = run_.t_us * 1e-6
    dt = np.diff(run_.t_us).astype(np.int32)
    n_cal = int(np.searchsorted(t, start))
    vel = run_.gps.device_velocity()
    steps = []
    k = n_cal
    last = None
    for j in range(int(start) + 1, int(stop)):
        end = int(np.searchsorted(t, float(j)))
        steps.append(("p", run_.counts[k:end], dt[k:end]))
        k = end
        if outage[0] <= j < outage[1]:
            continue
        d = run_.gps.enu[j, :2] - run_.gps.enu[last, :2] if last is not None else np.zeros(2)
        steps.append(("g", float(vel[j, 0]), float(vel[j, 1]), float(d[0]), float(d[1])))
        last = j
    return run_.counts[:n_cal], steps


@pytest.mark.parametrize("scenario,seed,median", RUNS)
def test_every_covariance_stays_positive_semidefinite_on_simulated_runs(impl, tmp_path, scenario, seed, median):
    """fusedkit.run checks every filter's covariance after every step; here over the runs the equivalence tests
    use, each with an 18 s outage, so all three filters run (the lateral one on the cars), and nothing repaired."""
    calib, steps = _outage_steps(scenario, seed)
    params = replace(FCFG, median=1.0) if median else FCFG
    trace = run(impl, steps, tmp_path, params=params, calib=calib)
    seen = {(which, step) for which, step, _ in trace.covariances}
    assert {(F.FILTER_TILT, F.STEP_START), (F.FILTER_TILT, F.STEP_PREDICT), (F.FILTER_POSITION, F.STEP_PREDICT),
            (F.FILTER_POSITION, F.STEP_UPDATE)} <= seen
    if scenario == "car":  # a walk turns too little in a minute for the tilt/offset filter's alignment gate
        assert {(F.FILTER_TILT, F.STEP_UPDATE), (F.FILTER_LATERAL, F.STEP_PREDICT),
                (F.FILTER_LATERAL, F.STEP_UPDATE)} <= seen
    assert trace.at(-1, "cov_repairs") == 0.0


def test_a_fix_is_weighed_by_the_heading_alignments_angle_error():
    """tilt_and_offset_update's measurement noise counts the alignment's angle error: its predict, then the update
    with r = 2 kf_vel_sigma^2 / T^2 (1 + |dv_gps|^2 / |A|) (A the alignment's sums), not the velocity noise alone:
    a weak alignment, as a straight road's, weighs a fix that changed speed much the less (the reference; the C and
    the fallback follow it through the equivalence runs)."""
    rng = np.random.default_rng(31)
    st = F.FusedState()
    p = _random_covariance(rng, 5, 0.2)
    for (i, j), name in F.FILTER_COVARIANCES[F.FILTER_TILT].items():
        setattr(st, name, float(p[i, j]))
    st.kf_t, st.gps_ok, st.gps_ve, st.gps_vn = 1.0, 1.0, 3.0, 4.0
    norm = max(5.0, FCFG.kf_align_min)
    st.align_c, st.align_s, st.cos_t, st.sin_t = 0.6 * norm, 0.8 * norm, 0.6, 0.8
    st.dvx, st.dvy = 0.4, -1.9
    st.m00, st.m01, st.m02, st.m10, st.m11, st.m12 = (float(v) for v in rng.uniform(-1.0, 1.0, 6))
    ve, vn, t = 5.0, 3.0, 1.0  # dv_gps = (2, -1): |dv_gps|^2 = 5
    done = st.copy()
    F.tilt_and_offset_update(done, ve, vn, True, t, FCFG)

    def by_hand(r):
        want = st.copy()
        assert F._kf_predict(want, FCFG)
        gx, gy = ve - st.gps_ve, vn - st.gps_vn
        z0 = (st.dvx - (st.cos_t * gx + st.sin_t * gy)) / t
        z1 = (st.dvy - (-st.sin_t * gx + st.cos_t * gy)) / t
        h = ((st.m00 / t, st.m01 / t, st.m02 / t), (st.m10 / t, st.m11 / t, st.m12 / t))
        assert F._kf_update(want, z0, z1, h, r, FCFG) is not None
        return want.vector()

    plain = 2.0 * FCFG.kf_vel_sigma_ms ** 2 / t ** 2
    np.testing.assert_allclose(done.vector(), by_hand(plain * (1.0 + 5.0 / norm)), rtol=1e-12, atol=1e-12)
    assert not np.allclose(done.vector(), by_hand(plain), rtol=1e-6, atol=1e-9)
