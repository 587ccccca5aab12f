"""The generated CircuitPython app, unmodified, on CircuitPython's own unix port (30-bit floats, ulab; built from
../shared/circuitpython) as the emulated CircuitPython board (codegen/sim/cpsim over mpsim's world): it builds as CircuitPython takes it, boots within the board's heap on the board's clock, shows and logs as
the MicroPython app does, gives the drive back when asked, survives a stuck bus through the watchdog, and on the
same recording gets the same fixes and the same outage estimates as its MicroPython twin."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from appkit import TAP, read_record
from cpkit import CODE_PY_IMPORTS, run_cp, walk_world
from test_app_outages import EPS30, EPS32, fused_compare, outages_of

from codegen.board.loader import load_board
from codegen.deploy.build import build
from codegen.errors import UserError
from codegen.sim.harness import generate_app, read_log, run_app
from conftest import board_micropython, circuitpython, circuitpython_mpy_cross, require_tool

PICO = "pico-gy521-circuitpython"
S3 = "esp32s3-devkitc-gy521-circuitpython"
LAT, LON = 51.4778, -0.0015


@pytest.fixture(scope="module")
def apps(tmp_path_factory):
    """Each bundled CircuitPython board's app, generated and built."""
    made = {}
    for name in (PICO, S3):
        out = generate_app(name, tmp_path_factory.mktemp(name) / "out")
        build(out, progress=lambda line: None)
        made[name] = (load_board(name).board, out)
    return made


def _static_world(board, work: Path, duration: float, pins: dict | None = None):
    from codegen.sim.cpharness import breadboard_world
    from codegen.sim.harness import imu_counts, nmea_epoch, write_counts, write_stream

    work.mkdir(parents=True, exist_ok=True)
    counts = write_counts(work / "imu.bin", imu_counts(duration + 1, board.imu.achieved_sample_rate_hz))
    gps = write_stream(work / "gps.txt", [(t + 0.1, nmea_epoch(t, LAT, LON)) for t in range(1, int(duration))])
    return breadboard_world(board, work, counts, gps, duration, rate_hz=board.imu.achieved_sample_rate_hz,
                            pins=pins)


@pytest.mark.parametrize("name", [PICO, S3])
def test_build_ships_circuitpython_mpy(apps, name):
    """lib/ compiled by CircuitPython's own mpy-cross (built from the shared tree, the boards' release): .mpy that
    start with 'C', which CircuitPython loads and MicroPython's would not be; code.py and boot.py stay source."""
    circuitpython_mpy_cross()  # the compiler the build found (skips locally without the shared tree)
    board, out = apps[name]
    app = out / "build" / "app"
    files = sorted(p.relative_to(app).as_posix() for p in app.rglob("*"))
    assert "code.py" in files and "boot.py" in files and "lib/app.mpy" in files and "lib/dr_fallback.mpy" in files
    assert not [f for f in files if f.startswith("lib/") and f.endswith(".py")], files
    assert all((app / f).read_bytes()[:2] == b"C\x06" for f in files if f.endswith(".mpy"))
    assert not (out / "build" / "fs.img").exists()
    assert not (out / "native").exists()  # CircuitPython loads no native module


def test_build_without_circuitpythons_mpy_cross_ships_checked_py(apps, tmp_path, monkeypatch):
    from codegen import tools

    monkeypatch.delenv("DEADRECKON_CP_MPY_CROSS", raising=False)
    monkeypatch.delenv("CIRCUITPY_DIR", raising=False)
    monkeypatch.setattr(tools, "SHARED_CIRCUITPYTHON", tmp_path / "none")
    board, out = apps[PICO]
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    said = []
    build(copy, progress=said.append)
    files = sorted(p.relative_to(copy / "build" / "app").as_posix() for p in (copy / "build" / "app").rglob("*"))
    assert "lib/app.py" in files and not [f for f in files if f.endswith(".mpy")]
    assert any("no CircuitPython 10.2.1 mpy-cross: set DEADRECKON_CP_MPY_CROSS" in line for line in said), said


def test_build_refuses_micropythons_mpy_cross_for_circuitpython(apps, tmp_path, monkeypatch):
    monkeypatch.setenv("DEADRECKON_CP_MPY_CROSS", require_tool("mpy-cross"))
    board, out = apps[PICO]
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    with pytest.raises(UserError, match="is not CircuitPython's mpy-cross"):
        build(copy, progress=lambda line: None)


def test_build_refuses_a_library_the_board_lacks(apps, tmp_path):
    board, out = apps[PICO]
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    nmea = copy / "app" / "lib" / "nmea.py"
    nmea.write_text(nmea.read_text() + "\nimport adafruit_gps\n")
    with pytest.raises(UserError, match=r"lib/nmea.py:\d+ imports 'adafruit_gps', which is neither part of the app "
                                         r"nor built into CircuitPython on the Raspberry Pi Pico"):
        build(copy, board=board, progress=lambda line: None)


@pytest.mark.parametrize("name", [PICO, S3])
def test_app_boots_shows_and_logs_within_the_boards_heap(apps, name, tmp_path):
    micropython = circuitpython()
    board, out = apps[name]
    run = run_cp(micropython, out, board, _static_world(board, tmp_path, 16.0), tmp_path)
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    assert "Traceback" not in run.stdout and "WARN" not in run.stdout, run.stdout[:2000]
    assert f"DEADRECKON board={name} kernel=python imu=ok display=ok" in run.stdout
    assert any(line.startswith("CAL ok") for line in run.stdout.splitlines())
    assert [e["readonly"] for e in run.events("remount")] == [False]  # boot.py gave the drive to the app
    screen = run.screen_at(15.9)
    assert screen[0].startswith("GPS fix") and screen[1] == "51.4778000 N" and screen[2] == "0.0015000 W"
    assert screen[5].startswith("imu %dHz drop 0" % round(board.imu.achieved_sample_rate_hz))
    logs = sorted((tmp_path / "fs").glob("dr*.bin"))
    assert logs, list((tmp_path / "fs").iterdir())
    header, records = read_log(logs[0].read_bytes())
    assert header["board"] == name and header["kernel"] == "python"
    fixes = [r for r in records if r[0] == "G"]
    assert fixes and fixes[-1][6] == round(LAT * 1e7) and fixes[-1][7] == round(LON * 1e7)
    diag = run.console("DIAG")[-1]
    assert "dropped=0" in diag, diag


def test_an_exception_in_code_py_is_printed_as_the_firmware_prints_it(apps, tmp_path):
    """CircuitPython has no sys.print_exception: the emulated firmware prints what code.py raised, names its type
    and message, and says the code is done (it once failed inside its own printing and hid the app's error)."""
    micropython = circuitpython()
    board, out = apps[PICO]
    run = run_cp(micropython, out, board, _static_world(board, tmp_path, 3.0), tmp_path,
                 code="raise ValueError('the app broke here')\n")
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    assert "ValueError: the app broke here" in run.stdout, run.stdout[-2000:]
    assert "Code done running." in run.stdout


def test_a_button_held_at_start_leaves_the_drive_to_the_computer(apps, tmp_path):
    micropython = circuitpython()
    board, out = apps[PICO]
    held = {str(board.buttons.calibrate.pin.pin): [[0, 0], [3.0, 1]]}  # held through boot.py, released at 3 s
    run = run_cp(micropython, out, board, _static_world(board, tmp_path, 12.0, pins=held), tmp_path)
    assert run.returncode == 0, run.stderr
    assert "boot.py: calibrate button held: the drive stays the computer's, the app will not log" in run.stdout
    assert not run.events("remount")
    warned = [line for line in run.console("WARN") if line.startswith("WARN log")]
    assert warned and "30" in warned[0], run.stdout[:1500]  # EROFS: said on the console, the screen, the log (none)
    assert run.screen_at(11.9)[0].startswith("GPS fix")
    assert not list((tmp_path / "fs").glob("dr*.bin"))


def test_test_mode_button_lights_the_led(apps, tmp_path):
    micropython = circuitpython()
    board, out = apps[PICO]
    pressed = {str(board.buttons.test_mode.pin.pin): [[13.0, 0], [13.3, 1]]}
    run = run_cp(micropython, out, board, _static_world(board, tmp_path, 15.0, pins=pressed), tmp_path)
    assert run.returncode == 0, run.stderr
    assert "TEST on" in run.stdout
    led = [e["v"] for e in run.events("pin") if e["pin"] == board.led.pin.pin]
    assert led[-1] == 1
    assert run.screen_at(14.9)[0].startswith("TEST") and "TEST MODE" in run.screen_at(14.9)


def test_watchdog_resets_a_stuck_bus_and_boot_py_runs_again(apps, tmp_path):
    micropython = circuitpython()
    board, out = apps[S3]
    world = _static_world(board, tmp_path, 30.0)
    world["i2c"][str(board.i2c[board.imu.bus].id)][0].update(hang_at_s=14.0, hang_s=10.0)
    run = run_cp(micropython, out, board, world, tmp_path)
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    boots = run.events("boot")
    assert boots and boots[0]["cause"] == "watchdog"
    assert 18.5 < boots[0]["t_us"] / 1e6 < 19.5  # 14 s + the board's 5 s (circuitpython.watchdog_s)
    assert len(run.events("remount")) == 2  # boot.py at power-on and after the reset
    assert "WARN reset: watchdog" in run.stdout
    assert run.screen_at(29.9)[0].split()[0] in ("GPS", "CAL")


# ------------------------------------------------------------------------ the same recording as MicroPython
DURATION = 75.0
OUTAGES = [(26.5, 36.5), (44.5, 54.5), (62.5, 72.5)]
TAP_HEAP = 2 << 20  # the tap keeps copies of what the kernel got: the comparison runs with room for them


def _twin(name: str, tmp_path: Path) -> Path:
    """The MicroPython twin of a CircuitPython board: the same wiring and sample rate."""
    twins = {PICO: "pico-gy521", S3: "esp32s3-devkitc-gy521"}
    board = load_board(name).board
    yaml = tmp_path / "twin.yaml"
    yaml.write_text(f"extends: {twins[name]}\nname: twin\nimu: {{sample_rate_hz: {board.imu.sample_rate_hz}}}\n")
    return yaml


def _stream_shift(mp_s: np.ndarray, cp_s: np.ndarray, most: int = 400) -> int:
    """How many samples later than MicroPython's the CircuitPython app's kernel stream starts in the recording
    (negative: earlier): where the first eight samples of one appear in the other."""
    for shift in range(-most, most + 1):
        a, b = (mp_s[shift:], cp_s) if shift >= 0 else (mp_s, cp_s[-shift:])
        if len(a) >= 8 and len(b) >= 8 and np.array_equal(a[:8], b[:8]):
            return shift
    raise AssertionError("the two apps' kernels got different streams: no shift within %d samples" % most)


@pytest.mark.parametrize("name", [S3, PICO])
def test_same_fixes_and_outage_estimates_as_the_micropython_app(apps, name, tmp_path):
    micropython, cp_interpreter = board_micropython(), circuitpython()
    cp_board, cp_out = apps[name]
    twin = _twin(name, tmp_path)
    mp_board = load_board(twin).board
    mp_out = generate_app(twin, tmp_path / "mp-out")
    records, runs = {}, {}
    for target in ("micropython", "circuitpython"):
        work = tmp_path / target
        board = mp_board if target == "micropython" else cp_board
        world, track = walk_world(board, "walk", 41, DURATION, OUTAGES, work)
        dump = work / "record.bin"
        tap = f"DUMP = {str(dump)!r}\n" + TAP
        if target == "micropython":
            script = work / "tap.py"
            script.write_text(tap)
            run = run_app(micropython, mp_out, world, work / "w", script=str(script), heap_bytes=TAP_HEAP)
        else:
            run = run_cp(cp_interpreter, cp_out, cp_board, world, work, code=CODE_PY_IMPORTS + tap,
                         heap_bytes=TAP_HEAP)
        assert run.returncode == 0, run.stderr + run.stdout[-2000:]
        assert "KERNEL python" in run.stdout
        assert "dropped=0" in run.console("DIAG")[-1], run.console("DIAG")
        records[target], runs[target] = read_record(dump), run
    mp, cp = records["micropython"], records["circuitpython"]
    # the same samples reached the kernel, with the same intervals: the recording's, each app's from where the run
    # was when it woke the chip (the emulated MPU-6050 serves the moment's sample; the two firmwares boot in their own
    # times), `shift` samples later on CircuitPython
    (mp_s, mp_dt), (cp_s, cp_dt) = mp.stream(), cp.stream()
    shift = _stream_shift(mp_s, cp_s)
    if shift < 0:  # CircuitPython woke its chip first: drop its own first samples
        cp_s, cp_dt = cp_s[-shift:], cp_dt[-shift:]
    else:
        mp_s, mp_dt = mp_s[shift:], mp_dt[shift:]
    n = min(len(mp_s), len(cp_s))
    assert n > 0.9 * len(mp_s) and np.array_equal(mp_s[:n], cp_s[:n]) and np.array_equal(mp_dt[:n], cp_dt[:n])
    # the same fixes, in the same order, each taken within one of the app's kernel batches of the other
    assert [(f.lat_e7, f.lon_e7) for f in mp.fixes] == [(f.lat_e7, f.lon_e7) for f in cp.fixes]
    # the same velocities but for rounding: CircuitPython's 30-bit floats (speed in knots * 0.514444, the course
    # in radians, its sine and cosine, their product: a few roundings of 2^-22 each) against float32's
    for a, b in zip(mp.fixes, cp.fixes):
        assert np.all(np.abs(a.vel - b.vel) <= 8 * EPS30 * float(np.abs(a.vel).max()) + 1e-12), (a.vel, b.vel)
    batch = 128
    lags = [b.index - (a.index - shift) for a, b in zip(mp.fixes, cp.fixes)]
    assert max(abs(lag) for lag in lags) <= batch, lags
    # each app's outage estimates are its kernel's reference on those samples, with each fix where the app took it
    origin = track.origin
    estimates = {}
    for target, rec, board in (("micropython", mp, mp_board), ("circuitpython", cp, cp_board)):
        offsets = fused_compare(rec, board, origin, eps=EPS30 if target == "circuitpython" else EPS32)
        groups = outages_of(rec)
        assert len(groups) == len(OUTAGES)
        for fix_n, calls in sorted(groups.items()):
            for i in calls:
                want, bound = offsets[i][0], offsets[i][1]
                assert float(np.abs(rec.calls[i].enu[:2] - want).max()) <= bound, (target, i)
            last = rec.calls[calls[-1]]
            estimates.setdefault(fix_n, {})[target] = (last.start + last.m, last.enu[:2].copy(), offsets[calls[-1]])
    # and so the two apps' outage estimates are the same, but for the samples between their fixes
    rate = cp_board.imu.achieved_sample_rate_hz
    for fix_n, both in sorted(estimates.items()):
        (mp_end, mp_enu, mp_ref), (cp_end, cp_enu, cp_ref) = both["micropython"], both["circuitpython"]
        moved = float(np.abs(mp_ref[0] - cp_ref[0]).max())  # the reference's own motion between the two ends
        gap = float(np.abs(mp_enu - cp_enu).max())
        print(f"{name}: outage from fix {fix_n}: MicroPython {mp_enu.round(3)} at sample {mp_end}, CircuitPython "
              f"{cp_enu.round(3)} at sample {cp_end}: {gap:.4f} m apart ({abs(cp_end - mp_end) / rate:.3f} s of "
              f"samples between their ends)")
        assert gap <= moved + mp_ref[1] + cp_ref[1], (fix_n, gap, moved)


def test_without_a_log_boot_py_leaves_the_drive_to_the_computer(tmp_path):
    from codegen.generate import render_tree

    yaml = tmp_path / "nolog.yaml"
    yaml.write_text(f"extends: {PICO}\nname: nolog\nlogging: {{enabled: false}}\n")
    boot = render_tree(load_board(yaml))["app/boot.py"].content.decode()
    assert "remount" not in boot.split('"""')[-1] and "stays the computer's" in boot
    s3 = render_tree(load_board(S3))["app/boot.py"].content.decode()
    assert "board.IO4" in s3 and "board.IO0" not in s3  # not the BOOT button: held at reset, it selects the ROM
