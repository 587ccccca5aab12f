"""The app with `algorithm.mode: eskf`: the error-state filter in the native module, on the emulated board.

The generated app runs unmodified on the 32-bit board-precision unix MicroPython with the board's dr_native.mpy
built for x86 (tests/appkit.x86_natmod, as tests/test_app_outages.py runs the fused natmod) through the simulated
car with three GPS outages. The tap (tests/appkit.TAP) records every window the app fed the filter and every fix
it gave it (time, position in the run's frame, velocity); the same filter's C, compiled on the host by cffi
(codegen/kernel/hosteskf.py, the benchmark's "eskf-c"), then runs on exactly that record, and each position the
app's filter reached is compared with the host's.

The tolerance: both are the same float32 C, but compiled twice (gcc -Os for the i386 natmod, the host's x86-64
build for cffi), so the compilers' choices (contracting a * b + c, the order of a sum they may not reorder but
inline differently, x87 against SSE registers) round differently, by an ulp here and there. The filter corrects
such differences at every fix; through an outage they integrate. The bound is measured, not derived: OUTAGE_TOL_M
is about twenty times the largest difference seen (2.2 mm over 53 outage windows; the test prints it), far below
what a wrong input would give (one window of 512 samples missed or fed twice at 15 m/s moves the position by ~38 m;
a fix fed at the wrong place, by its metres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from appkit import TAP, driving_world, outage_world, read_record, x86_natmod

from codegen.board.loader import load_board
from codegen.kernel import reference as ref
from codegen.kernel.eskf import EskfConfig
from codegen.kernel.hosteskf import load_eskf
from codegen.kernel.layout import ESKF
from codegen.kernel.reference import KernelConfig
from codegen.sim.harness import generate_app, run_app
from conftest import board_micropython

DURATION = 75.0
OUTAGES = [(26.5, 36.5), (44.5, 54.5), (62.5, 72.5)]
MODE_GPS, MODE_IMU = 0, 1
OUTAGE_TOL_M = 0.05  # m, horizontal: see the module's docstring


@pytest.fixture(scope="module")
def eskf_app(tmp_path_factory):
    folder = tmp_path_factory.mktemp("eskf")
    yaml = folder / "tbeam-eskf.yaml"
    yaml.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-eskf\nalgorithm:\n  mode: eskf\n")
    loaded = load_board(yaml)
    out = generate_app(yaml, folder / "out")
    return {"loaded": loaded, "board": loaded.board, "out": out, "natmod": x86_natmod(out, folder / "natmod")}


def run_car(entry, work: Path, extra):
    board = entry["board"]
    world, traj, track = outage_world(board, "car", 42, DURATION, OUTAGES, work)
    return run_tapped(entry["out"], world, work, extra)


def run_tapped(out: Path, world, work: Path, extra):
    """The app in `out` on `world` with the tap recording into work/record.bin; it must exit cleanly."""
    script = work / "tap.py"
    script.write_text(f"DUMP = {str(work / 'record.bin')!r}\n" + TAP)
    run = run_app(board_micropython(), out, world, work / "w", script=str(script), extra_path=extra)
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    return run


def board_config(board) -> EskfConfig:
    """The filter's parameters as the board gives them (its eskf_* keys; the cadences at their defaults)."""
    return EskfConfig(**{p.name: getattr(board.algorithm, ESKF.board_key(p)) for p in ESKF.params if p.board})


def test_eskf_app_outages_match_the_host_filter_on_the_same_input(eskf_app, tmp_path):
    board = eskf_app["board"]
    run = run_car(eskf_app, tmp_path, [eskf_app["natmod"]])
    lines = run.stdout.splitlines()
    assert "KERNEL native" in run.stdout and "Traceback" not in run.stdout, run.stdout[-2000:]
    assert "WARN" not in run.stdout, [line for line in lines if line.startswith("WARN")]
    assert any(line.startswith("ESKF started") for line in lines), run.stdout[-3000:]
    rec = read_record(tmp_path / "record.bin")
    assert rec.moved == 0 and rec.eskf_fixes

    session = load_eskf(eskf_app["loaded"]).session(board_config(board))
    session.use_kernel_config(KernelConfig.from_board(board))
    assert session.calibrate(rec.calib) is False
    if rec.eskf_interval is not None:  # the fix before the calibration, as the app gave it
        session.calibration_interval(rec.eskf_interval[:2], rec.eskf_interval[2])
    fixes = list(rec.eskf_fixes)
    worst = 0.0
    compared = 0
    outage_calls = 0
    for i, call in enumerate(rec.calls):
        while fixes and fixes[0][0] == i:
            _, args, started = fixes.pop(0)
            assert session.gps(args[0], args[1:4], args[4:6]) == started
        gps_speed, aligned = call.before[0], call.before[1]
        # what the app's filter held going in: its own, or 0 when an outage began (the app's one write, API.md)
        assert aligned == session.st.aligned
        if gps_speed == 0.0:
            session.st.gps_speed = 0.0
        else:  # the same sqrt, rounded by two compilers
            assert gps_speed == pytest.approx(session.st.gps_speed, rel=1e-6), (i, gps_speed, session.st.gps_speed)
        out = session.process(call.samples, call.dt)
        if not aligned:
            continue
        d = float(np.hypot(*(call.out[:2] - out[:2])))
        compared += 1
        if call.mode == MODE_IMU:
            outage_calls += 1
            worst = max(worst, d)
            assert d <= OUTAGE_TOL_M, f"call {i}: the app's filter at {call.out[:2]}, the host's at {out[:2]}"
        else:  # between fixes the filter is pulled to each: the two stay as close
            assert d <= OUTAGE_TOL_M, (i, call.out[:2], out[:2])
    print(f"eskf app vs host cffi: {compared} windows after the start, {outage_calls} in outages, worst "
          f"{worst * 1000:.2f} mm")
    assert outage_calls >= 10  # every outage reached the comparison
    # each outage's first window starts with the last fix's speed cleared (rest may be seen in an outage)
    for prev, call in zip(rec.calls, rec.calls[1:]):
        if prev.mode == MODE_GPS and call.mode == MODE_IMU:
            assert call.before[0] == 0.0
    assert {c.mode for c in rec.calls} >= {MODE_GPS, MODE_IMU}


def test_eskf_app_feeds_each_fix_in_the_runs_frame(eskf_app, tmp_path):
    """Every fix the app took while running goes into the filter once, in order: its position in the ENU frame of
    the first one (the kernel's geodesy against the WGS-84 formula: 1e-7 degree rounding, ~1 cm, plus 1e-4 of the
    distance for the app's 1 km secant), its Doppler velocity as the app computed it, at the sample clock's time."""
    from codegen.sim import neo6m

    run_car(eskf_app, tmp_path, [eskf_app["natmod"]])
    rec = read_record(tmp_path / "record.bin")
    taken = [f for f in rec.fixes if f.running and not f.test_mode]
    assert len(taken) == len(rec.eskf_fixes) >= 30
    origin = (taken[0].lat_e7 * 1e-7, taken[0].lon_e7 * 1e-7, 0.0)
    times = []
    for fix, (_, args, _) in zip(taken, rec.eskf_fixes):
        t, e, n, u, ve, vn = args
        want = neo6m.geodetic_to_enu(fix.lat_e7 * 1e-7, fix.lon_e7 * 1e-7, 0.0, origin)
        assert np.hypot(e - want[0], n - want[1]) <= 0.02 + 1e-4 * np.hypot(*want[:2]), (fix, args, want)
        assert (ve, vn) == pytest.approx(tuple(fix.vel[:2]), abs=1e-5)
        times.append(t)
    # the time is the sample clock's when the app takes the fix (the epoch's sentences end a variable ~0.1 s after
    # it): within 0.15 s of the receiver's whole seconds, which weighs nothing against gps_tau_s (60 s), the one
    # thing the filter times with it
    steps = np.diff(times)
    assert times[0] == 0.0 and np.all(np.abs(steps - np.round(steps)) < 0.15) and np.all(steps >= 0.8), steps


def test_eskf_app_shows_the_filters_position_in_an_outage(eskf_app, tmp_path):
    """In IMU mode the shown position is the filter's, in the run's frame (from the first fix it got), back in
    degrees by the kernel's geodesy; the app's offset from the last fix is the filter's position less that fix's."""
    run_car(eskf_app, tmp_path, [eskf_app["natmod"]])
    rec = read_record(tmp_path / "record.bin")
    first = next(f for f in rec.fixes if f.running and not f.test_mode)
    origin = (first.lat_e7, first.lon_e7)
    anchors = {}  # calls before a fix -> its position in the run's frame
    for before, args, _ in rec.eskf_fixes:
        anchors[before] = np.array(args[1:3])
    anchor = None
    checked = 0
    for i, call in enumerate(rec.calls):
        if i in anchors:
            anchor = anchors[i]
        if call.mode != MODE_IMU or not call.before[1] or anchor is None:
            continue
        assert np.allclose(call.enu[:2], call.out[:2] - anchor, atol=1e-3), (i, call.enu, call.out, anchor)
        lat, lon = ref.offset_latlon_e7(*origin, float(anchor[0] + call.enu[0]), float(anchor[1] + call.enu[1]))
        assert abs(call.pos[0] - lat) <= 1 and abs(call.pos[1] - lon) <= 1, (i, call.pos, (lat, lon))
        checked += 1
    assert checked >= 10


def test_eskf_without_its_native_module_runs_fused_and_says_so(eskf_app, tmp_path):
    """No dr_native.mpy (or one the firmware refuses): there is no pure-Python eskf, so the fused fallback runs,
    and the status line and the console say it."""
    run = run_car(eskf_app, tmp_path, [])
    assert "KERNEL python" in run.stdout and "Traceback" not in run.stdout, run.stdout[-2000:]
    assert "WARN no eskf: fused" in run.stdout
    assert "ESKF the native module is not loaded (kernel python): the fused method runs instead" in run.stdout
    assert any(line.startswith("MODE GPS -> IMU") for line in run.stdout.splitlines())
    assert "no eskf: fused" in run.screen_at(5.0)  # on the status line from boot (as "native refused")


BINDING_SCRIPT = r"""
from array import array
import dr_native as dr


def said(f, *args):
    try:
        f(*args)
    except (TypeError, ValueError) as e:
        return "%s: %s" % (type(e).__name__, e)
    return "ok"


st = array("f", bytes(4 * dr.ESKF_STATE_LEN))
samples = array("h", [0, 0, 16384, 0, 0, 0] * 4)
dt = array("i", [5000] * 4)
out = array("f", bytes(4 * dr.OUT_LEN))
print("init", said(dr.eskf_init, st))
print("short", said(dr.eskf_init, array("f", bytes(4 * (dr.ESKF_STATE_LEN - 1)))))
print("state_i", said(dr.eskf_init, array("i", bytes(4 * dr.ESKF_STATE_LEN))))
print("cal", dr.eskf_calibrate(st, samples))
print("cal_f", said(dr.eskf_calibrate, st, array("f", [0.0] * 6)))
print("cal_none", said(dr.eskf_calibrate, st, array("h")))
print("cal_partial", said(dr.eskf_calibrate, st, array("h", [0] * 7)))
print("process", said(dr.eskf_process, st, samples, dt, out))
print("dt_h", said(dr.eskf_process, st, samples, array("h", [5] * 4), out))
print("dt_short", said(dr.eskf_process, st, samples, array("i", [5000] * 3), out))
print("out_short", said(dr.eskf_process, st, samples, dt, array("f", [0.0] * 5)))
print("out_d", said(dr.eskf_process, st, samples, dt, array("d", [0.0] * 6)))
print("gps", dr.eskf_gps(st, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0))
print("offsets", dr.ESKF_POS, dr.ESKF_VEL, dr.ESKF_Q, dr.ESKF_ALIGNED, dr.ESKF_GPS_SPEED, dr.ESKF_COV_REPAIRS)
print("q", st[dr.ESKF_Q])
"""


def test_eskf_binding_checks_its_buffers(eskf_app, tmp_path):
    """dr_native's eskf functions as API.md has them: caller-owned buffers of the right typecode and size, a
    TypeError or ValueError naming what is wrong, and the offsets of the declaration (codegen/kernel/layout.py)."""
    from codegen.kernel.layout import LAYOUT
    from codegen.sim.harness import run_script

    script = tmp_path / "binding.py"
    script.write_text(BINDING_SCRIPT)
    done = run_script(board_micropython(), eskf_app["natmod"], str(script))
    assert done.returncode == 0, done.stdout + done.stderr
    said = dict(line.split(" ", 1) for line in done.stdout.splitlines())
    assert said["init"] == "ok" and said["process"] == "ok" and said["cal"] == "0" and said["gps"] == "0"
    assert said["short"] == "ValueError: eskf state buffer shorter than ESKF_STATE_LEN"
    assert said["state_i"] == "TypeError: expected array('f')"
    assert said["cal_f"] == "TypeError: expected array('h')"
    assert said["cal_none"] == "ValueError: calibration needs at least 1 sample with gravity in it"
    assert said["cal_partial"] == "ValueError: samples must hold 6 values per sample"
    assert said["dt_h"] == "TypeError: expected array('i')"
    assert said["dt_short"] == "ValueError: samples must hold 6 values and dt_us 1 value per sample"
    assert said["out_short"] == "ValueError: out must hold OUT_LEN floats"
    assert said["out_d"] == "TypeError: expected array('f')"
    offsets = ESKF.state_offsets
    assert said["offsets"] == " ".join(str(offsets[name]) for name in ("pos", "vel", "q", "aligned", "gps_speed",
                                                                         "cov_repairs"))
    assert float(said["q"]) == 1.0  # level at rest: the identity attitude, at the declared offset
    assert LAYOUT.eskf_buffer_floats == ESKF.state_floats + ESKF.config_floats + LAYOUT.seed.config_floats


def test_simulate_on_micropython_runs_the_eskf_board_natively(eskf_app, tmp_path):
    """`deadreckon simulate --on-micropython` on an eskf board builds its dr_native for the host's x64 `micropython`
    (codegen.natmod.build, as `deadreckon build` builds the board's) and the app runs the filter with it."""
    from codegen.sim import trajectory
    from codegen.sim.onmicropython import record_on_micropython
    from conftest import require_tool

    require_tool("micropython")
    traj = trajectory.make_scenario("car", seed=0)
    recording = record_on_micropython(eskf_app["loaded"], traj, duration=44.0, outages=[(32.5, 42.5)],
                                      work=tmp_path)
    stdout = recording.result.stdout
    assert "kernel=native" in stdout and "WARN" not in stdout, stdout[-1500:]
    assert any(line.startswith("ESKF started") for line in stdout.splitlines())
    assert any(line.startswith("MODE GPS -> IMU") for line in stdout.splitlines())


def test_eskf_app_test_mode_dead_reckons_with_the_filter(eskf_app, tmp_path):
    """The test-mode button, as in fused mode: pressed with GPS, the app leaves GPS mode for TEST, ignores the fixes
    (none goes into the filter) and shows the filter's position; pressed again, it takes the next fix."""
    from codegen.sim.harness import press

    board = eskf_app["board"]
    world, _, _ = outage_world(board, "car", 42, 50.0, [], tmp_path)
    world["pins"][str(board.buttons.test_mode.pin.pin)] = press(30.2) + press(40.2)
    run = run_tapped(eskf_app["out"], world, tmp_path, [eskf_app["natmod"]])
    lines = run.stdout.splitlines()
    assert "TEST on" in lines and "TEST off" in lines and "MODE GPS -> TEST" in lines
    assert any(line.startswith("ESKF started") for line in lines)
    rec = read_record(tmp_path / "record.bin")
    ignored = [f for f in rec.fixes if f.test_mode]
    assert len(ignored) >= 8 and len(rec.eskf_fixes) == len([f for f in rec.fixes if f.running and not f.test_mode])
    test_calls = [c for c in rec.calls if c.mode == 2]
    assert len(test_calls) >= 3 and test_calls[0].before[0] == 0.0  # the outage's start cleared the fix's speed
    assert all(c.before[1] for c in test_calls)  # the filter ran through it
    assert "TEST MODE" in run.screen_at(35.0)


def test_a_calibration_in_a_moving_car_is_kept_and_the_filter_starts(eskf_app, tmp_path):
    """Switched on in a car that drives: the calibration moves, the last fix says the board travels, so the app keeps
    the calibration (it restarted forever before), hands the filter the fix interval that spans it, and the filter
    starts within seconds."""
    board = eskf_app["board"]
    world, speed = driving_world(board, tmp_path, skip_s=60.0, duration=40.0)
    assert speed > 5.0
    run = run_tapped(eskf_app["out"], world, tmp_path, [eskf_app["natmod"]])
    lines = run.stdout.splitlines()
    assert any(line.startswith("CAL moved: travelling at") for line in lines), run.stdout[-3000:]
    assert not any(line.startswith("CAL moved: restart") for line in lines)
    rec = read_record(tmp_path / "record.bin")
    assert rec.moved == 1 and rec.eskf_interval is not None
    started = [args[0] for _, args, s in rec.eskf_fixes if s]
    # s after the first fix it got: the yaw fit's intervals (5 at least) until its 1-sigma passes; 10.9 s on this
    # drive (9.9 s while the emulated chip's stream lagged the truth by its wake-up: one interval more now)
    assert started and started[0] <= 12.0, (started, run.stdout[-2000:])
