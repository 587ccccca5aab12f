"""The generated app, unmodified, on the unix-port MicroPython against emulated peripherals (codegen/sim/mpsim).

One scripted run of the default board (T-Beam v1.1) covers what a user sees: calibration at boot, GPS mode with a
fix, the fix disappearing (IMU mode, positions moving with the IMU), the test-mode button (TEST, LED on) and the
fix coming back; the run crosses the ticks_us wrap. Other runs: a missing IMU, a clone WHO_AM_I, motion during
calibration, real NMEA captures through the UART, SH1106 and AXP2101 boards, the log format and its rotation.
"""

from __future__ import annotations

import re

import pytest

from codegen.sim.harness import (
    TICKS_PERIOD,
    generate_app,
    imu_counts,
    nmea_epoch,
    press,
    read_log,
    run_app,
    tbeam_scenario,
    write_counts,
    write_stream,
)
from conftest import board_micropython, require_shared_data

LAT, LON = 40.0350855, -75.52009367  # the gr601-w capture's place (Malvern PA)
RATE = 200.0


@pytest.fixture(scope="module")
def micropython():
    return board_micropython()

SEED_BOARD = "extends: ttgo-tbeam-v1.1\nname: tbeam-seed\nalgorithm:\n  mode: seed\n"


@pytest.fixture(scope="module")
def tbeam(tmp_path_factory):
    """The default board with algorithm mode seed: the push-and-coast assertions are the seed's (the fused default
    takes a vibration-free coast for rest and stops, by design; it runs in test_app_boards and test_app_sim)."""
    folder = tmp_path_factory.mktemp("tbeam")
    board = folder / "tbeam-seed.yaml"
    board.write_text(SEED_BOARD)
    return generate_app(board, folder / "out")


def gps_chunks(t_from, t_to, **kw):
    return [(t, nmea_epoch(t, LAT, LON, **kw)) for t in range(t_from, t_to)]


@pytest.fixture(scope="module")
def modes_run(micropython, tbeam, tmp_path_factory):
    """60 s: calibrate 0-10 s, fixes 1-25 s, fix lost -> IMU, push East 30-34 s, TEST 40-48 s, fixes again 50 s."""
    work = tmp_path_factory.mktemp("modes")
    counts = write_counts(work / "imu.bin", imu_counts(60, RATE, seed=1, pushes=[(30, 34, 0, 0.5)]))
    gps = write_stream(work / "gps.txt", gps_chunks(1, 25) + gps_chunks(50, 60))
    scenario = tbeam_scenario(work, counts, gps, 60, pins={"25": press(40) + press(48)},
                              ticks_start_us=TICKS_PERIOD - 20_000_000)  # ticks_us wraps at t = 20 s
    run = run_app(micropython, tbeam, scenario, work)
    assert run.returncode == 0, run.stderr + run.stdout[-2000:]
    assert "Traceback" not in run.stdout + run.stderr
    return run, work


def _head(lines):
    return lines[0].split()[0] if lines and lines[0] else ""


def test_no_fix_yet_shows_no_position(modes_run):
    run, _ = modes_run
    screen = run.screen_at(0.9)  # before the first fix: no uninitialised GPS record on screen (the seed's bug)
    assert screen[0] == "CAL 0s no fix" and screen[1] == "waiting for GPS" and screen[2] == ""
    assert screen[6] == "calibrating"


def test_gps_mode_screen(modes_run):
    run, _ = modes_run
    screen = run.screen_at(20)
    print("GPS mode screen:\n" + "\n".join(screen))
    assert _head(screen) == "GPS"
    assert screen[0].startswith("GPS fix 0.") or screen[0].startswith("GPS fix 1.")
    assert screen[1] == "40.0350855 N"
    assert screen[2] == "75.5200937 W"
    assert screen[3].startswith("0.00m/s")
    assert screen[4] == "sats 7 hdop 1.7"
    assert screen[5] == "imu 200Hz drop 0"


def test_fix_lost_switches_to_imu_and_moves(modes_run):
    run, _ = modes_run
    changes = [line for line in run.stdout.splitlines() if line.startswith("MODE")]
    assert changes[0] == "MODE GPS -> IMU"
    switch = [e for e in run.screens() if _head(e["lines"]) == "IMU"][0]["t_us"] / 1e6
    # last fix at t = 24 s (+ its transmission), lost after fix_timeout_s = 3 s, shown at the next refresh (0.5 s)
    assert 27.0 < switch < 28.7
    screen = run.screen_at(39)
    print("IMU mode screen:\n" + "\n".join(screen))
    assert _head(screen) == "IMU"
    assert screen[1] == "40.0350855 N"  # pushed East only
    east = float(re.match(r"E([+-][\d.]+)", screen[4]).group(1))
    lon = float(screen[2].split()[0])
    assert east > 5.0  # 0.5 m/s^2 for 4 s: 2 m/s from t = 34 s
    assert lon < 75.5200937  # West longitude shrinks going East
    # 0.5 m/s^2 for 4 s: 2 m/s East, within the seed's block medians of the noisy counts (0.5 %; the exact stream
    # shows 2.01, the emulator's float sample clock once repeated a sample of it and showed 2.00)
    speed, course = re.match(r"([\d.]+)m/s +(\d+)deg", screen[3]).groups()
    assert abs(float(speed) - 2.0) <= 0.01 and course == "90", screen[3]


def test_test_mode_button_and_led(modes_run):
    run, _ = modes_run
    screen = run.screen_at(46)
    print("TEST mode screen:\n" + "\n".join(screen))
    assert _head(screen) == "TEST"
    assert screen[-1] == "TEST MODE"
    led = [(e["t_us"] / 1e6, e["v"]) for e in run.events("pin") if e["pin"] == 4]
    on = [t for t, v in led if v == 0]  # active low
    off = [t for t, v in led if v == 1 and t > 1]
    assert on and 40.0 < on[0] < 40.5  # debounced press
    assert off and 48.0 < off[0] < 48.5
    assert _head(run.screen_at(49.5)) == "IMU"  # test off, still no fix


def test_fix_returns_to_gps(modes_run):
    run, _ = modes_run
    screen = run.screen_at(59)
    assert _head(screen) == "GPS"
    assert screen[1:3] == ["40.0350855 N", "75.5200937 W"]


def test_pmu_turns_on_gps_rail(modes_run):
    run, _ = modes_run
    writes = {(e["reg"], e["val"]) for e in run.events("pmu_write")}
    assert any(reg == 0x12 and val & 0x08 for reg, val in writes)  # LDO3 enable
    assert any(reg == 0x28 and val & 0x0F == 15 for reg, val in writes)  # 1.8 V + 15 * 0.1 V = 3.3 V
    rails = [e for e in run.events("rail") if e["rail"] == "ldo3"]
    assert rails[-1]["on"] is True


def test_calibrates_and_keeps_rate_across_ticks_wrap(modes_run):
    run, _ = modes_run
    assert any(line.startswith("CAL ok") for line in run.stdout.splitlines())
    diags = run.console("DIAG")
    assert len(diags) >= 10
    for line in diags[1:]:
        rate = float(re.search(r"rate=([\d.]+)Hz", line).group(1))
        assert abs(rate - RATE) < 1.0, line
        assert "dropped=0" in line, line
    config = {(e["reg"], e["val"]) for e in run.events("mpu_config")}
    assert {(0x19, 4), (0x1A, 3), (0x1B, 0), (0x1C, 0)} <= config  # 1 kHz / (1 + 4), DLPF 3, +-250 dps, +-2 g


def test_log_records(modes_run):
    run, work = modes_run
    files = sorted((work / "fs").glob("dr*.bin"))
    assert len(files) == 1
    data = files[0].read_bytes()
    assert len(data) % 4096 == 0  # whole blocks only
    header, records = read_log(data)
    assert header["board"] == "tbeam-seed" and header["imu_rate_hz"] == "200.0" and header["log_every"] == "4"
    imu = [r for r in records if r[0] == "I"]
    gps = [r for r in records if r[0] == "G"]
    win = [r for r in records if r[0] == "W"]
    times = [r[1] for r in imu]
    steps = {b - a for a, b in zip(times, times[1:])}
    assert min(steps) >= 19000 and max(steps) <= 21000  # 50 Hz
    # the dump is taken at the end of the run like a power cut: at most the open block (~4.5 s) is missing
    assert times[-1] > 60e6 - 6e6
    assert 30 <= len(gps) <= 34
    t_us, utc_ms, year, month, day, lat, lon, alt_mm, sog_mm, cog, climb, mode, quality, sats, hdop = gps[0][1:]
    assert (year, month, day) == (2013, 10, 24) and lat == 400350855 and lon == -755200937
    assert alt_mm == 183800 and sog_mm == 0 and cog == 0xFFFF and mode == 3 and sats == 7 and hdop == 172
    assert gps[1][11] == 0  # climb 0 mm/s between two fixes at the same altitude
    assert len(win) >= 15
    events = [r[2] for r in records if r[0] == "E"]
    assert "mode IMU" in events and "mode TEST" in events and any(e.startswith("calibrated") for e in events)


def test_imu_missing_keeps_gps(micropython, tbeam, tmp_path):
    counts = write_counts(tmp_path / "imu.bin", imu_counts(1, RATE))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 8))
    scenario = tbeam_scenario(tmp_path, counts, gps, 8, imu={"nack": True})
    run = run_app(micropython, tbeam, scenario, tmp_path)
    assert run.returncode == 0, run.stderr
    screen = run.screen_at(7.9)
    assert _head(screen) == "GPS" and screen[1] == "40.0350855 N"
    assert "IMU missing" in screen


def test_a_native_module_the_firmware_refuses_falls_back_and_says_so(micropython, tbeam, tmp_path):
    """A dr_native.mpy built for another MicroPython (here .mpy version 5, as before 1.19) makes `import` raise
    ValueError, not ImportError: the app runs on the pure-Python kernel and says why on the screen and console."""
    natmod = tmp_path / "natmod"
    natmod.mkdir()
    (natmod / "dr_native.mpy").write_bytes(b"M\x05\x00\x1f" + bytes(60))
    counts = write_counts(tmp_path / "imu.bin", imu_counts(3, RATE))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 3))
    run = run_app(micropython, tbeam, tbeam_scenario(tmp_path, counts, gps, 3), tmp_path, extra_path=[natmod])
    assert run.returncode == 0, run.stderr
    assert "kernel=python" in run.stdout and "WARN native refused" in run.stdout
    assert "native refused" in run.screen_at(2.9)


def test_imu_lost_mid_run_keeps_gps(micropython, tbeam, tmp_path):
    counts = write_counts(tmp_path / "imu.bin", imu_counts(20, RATE))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 20))
    scenario = tbeam_scenario(tmp_path, counts, gps, 20, imu={"nack_after_s": 14.0})
    run = run_app(micropython, tbeam, scenario, tmp_path)
    assert run.returncode == 0, run.stderr
    assert "WARN IMU lost" in run.stdout
    screen = run.screen_at(19.9)
    assert _head(screen) == "GPS" and screen[1] == "40.0350855 N" and "IMU missing" in screen


def test_display_unplugged_keeps_running(micropython, tbeam, tmp_path):
    counts = write_counts(tmp_path / "imu.bin", imu_counts(16, RATE))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 16))
    scenario = tbeam_scenario(tmp_path, counts, gps, 16)
    scenario["i2c"]["0"][1]["nack_after_s"] = 5.0
    run = run_app(micropython, tbeam, scenario, tmp_path)
    assert run.returncode == 0, run.stderr
    assert "DISPLAY lost" in run.stdout
    assert len(run.console("DIAG")) == 3 and any(line.startswith("WIN") for line in run.stdout.splitlines())


def test_clone_who_am_i_is_a_warning(micropython, tbeam, tmp_path):
    counts = write_counts(tmp_path / "imu.bin", imu_counts(6, RATE))
    scenario = tbeam_scenario(tmp_path, counts, None, 6, imu={"who_am_i": 0x70})
    run = run_app(micropython, tbeam, scenario, tmp_path)
    assert run.returncode == 0, run.stderr
    assert "WARN IMU clone 70" in run.stdout
    assert run.console("DIAG")  # it keeps sampling


def test_motion_during_calibration_restarts_it(micropython, tbeam, tmp_path):
    counts = write_counts(tmp_path / "imu.bin", imu_counts(25, RATE, pushes=[(3, 4, 1, 3.0)]))
    scenario = tbeam_scenario(tmp_path, counts, None, 25)
    run = run_app(micropython, tbeam, scenario, tmp_path)
    assert run.returncode == 0, run.stderr
    cal = [line.split()[1] for line in run.stdout.splitlines() if line.startswith("CAL ") and not line.startswith("CAL start")]
    assert cal == ["moved:", "ok"]
    said = [e for e in run.screens() if "moved! again" in e["lines"]]
    assert said and 10.0 < said[0]["t_us"] / 1e6 < 11.0


def test_calibrate_button(micropython, tbeam, tmp_path):
    counts = write_counts(tmp_path / "imu.bin", imu_counts(26, RATE))
    scenario = tbeam_scenario(tmp_path, counts, None, 26, pins={"38": press(12)})
    run = run_app(micropython, tbeam, scenario, tmp_path)
    assert run.returncode == 0, run.stderr
    assert len([line for line in run.stdout.splitlines() if line.startswith("CAL ok")]) == 2
    assert _head(run.screen_at(15)) == "CAL"


@pytest.mark.parametrize("capture,lat_line,lon_line", [("gr601-w", "40.0350", "75.5200"),
                                                        ("ublox-lea-5h", "51.925", "4.577")])
def test_real_nmea_capture_through_uart(micropython, tbeam, tmp_path, capture, lat_line, lon_line):
    log = require_shared_data("nmea-gpsd", f"{capture}.log")
    lines = [line for line in log.read_text().splitlines() if line.startswith("$")]
    # the capture's sentences in bursts of 8 per second, like a 1 Hz receiver
    chunks = [(1 + i // 8, line + "\r\n") for i, line in enumerate(lines)]
    gps = write_stream(tmp_path / "gps.txt", chunks)
    end = chunks[-1][0] + 2
    counts = write_counts(tmp_path / "imu.bin", imu_counts(end, RATE))
    run = run_app(micropython, tbeam, tbeam_scenario(tmp_path, counts, gps, end), tmp_path)
    assert run.returncode == 0, run.stderr
    shown = [e["lines"] for e in run.screens() if _head(e["lines"]) in ("GPS", "CAL") and "fix" in e["lines"][0]
             and "no fix" not in e["lines"][0]]
    assert shown, run.stdout[-1500:]
    assert shown[-1][1].startswith(lat_line) and shown[-1][2].startswith(lon_line)
    diag = run.console("DIAG")[-1]
    assert "bad_checksum=0" in diag


@pytest.mark.parametrize("board,display,pmu,rail,reg,bit", [
    ("ttgo-tbeam-v1.2", "ssd1306", "axp2101", "aldo3", 0x90, 2),
])
def test_axp2101_board(micropython, tmp_path, board, display, pmu, rail, reg, bit):
    out = generate_app(board, tmp_path / "out")
    counts = write_counts(tmp_path / "imu.bin", imu_counts(5, RATE))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 5))
    scenario = tbeam_scenario(tmp_path, counts, gps, 5, display=display, pmu=pmu, rail=rail)
    run = run_app(micropython, out, scenario, tmp_path / "w")
    assert run.returncode == 0, run.stderr
    assert any(e["reg"] == reg and e["val"] >> bit & 1 for e in run.events("pmu_write"))
    assert run.screen_at(4.9)[1] == "40.0350855 N"


def test_sh1106_column_offset(micropython, tmp_path):
    board = tmp_path / "sh.yaml"
    board.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-sh1106\ndisplay:\n  model: sh1106\n")
    out = generate_app(board, tmp_path / "out")
    counts = write_counts(tmp_path / "imu.bin", imu_counts(4, RATE))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 4))
    scenario = tbeam_scenario(tmp_path, counts, gps, 4, display="sh1106")
    run = run_app(micropython, out, scenario, tmp_path / "w")
    assert run.returncode == 0, run.stderr
    screen = run.screen_at(3.9)
    assert screen[1] == "40.0350855 N" and screen[2] == "75.5200937 W"  # decodes only if columns start at 2


def test_log_rotation_on_a_small_filesystem(micropython, tmp_path):
    board = tmp_path / "small.yaml"
    board.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-smalllog\nlogging:\n  max_files: 3\n"
                     "  min_free_kb: 16\n  block_bytes: 1024\n  imu_rate_hz: 200\n")
    out = generate_app(board, tmp_path / "out")
    counts = write_counts(tmp_path / "imu.bin", imu_counts(60, RATE))
    scenario = tbeam_scenario(tmp_path, counts, None, 60, fs_bytes=96 * 1024)
    scenario["fs"]["block"] = 1024
    run = run_app(micropython, out, scenario, tmp_path / "w")
    assert run.returncode == 0, run.stderr
    fs = run.events("fs")[0]
    names = fs["files"]
    assert 2 <= len(names) <= 3  # never more than max_files
    numbers = [int(n[2:7]) for n in names]
    assert numbers == sorted(numbers) and numbers[0] > 1  # the oldest were deleted
    assert fs["free"] >= 16 * 1024 - 1024
    for name in names:
        data = (tmp_path / "w" / "fs" / name).read_bytes() if (tmp_path / "w" / "fs" / name).exists() else None
        if data:
            header, records = read_log(data, block=1024)
            assert header["board"] == "tbeam-smalllog"
    assert "LOG disabled" not in run.stdout


def test_data_ready_mode_says_what_it_drops(micropython, tmp_path):
    """Without the FIFO (imu.use_fifo: false) the app polls the data-ready flag; on the board's clock the fallback's
    kernel batches and the flash's erases outlast a sample period: the samples it misses are counted, shown on the
    screen and logged, and their time stays in the integration."""
    board = tmp_path / "poll.yaml"
    board.write_text("extends: ttgo-tbeam-v1.1\nname: tbeam-poll\nimu:\n  use_fifo: false\n")
    out = generate_app(board, tmp_path / "out")
    counts = write_counts(tmp_path / "imu.bin", imu_counts(30, RATE, pushes=[(22, 24, 0, 0.5)]))
    gps = write_stream(tmp_path / "gps.txt", gps_chunks(1, 30))
    run = run_app(micropython, out, tbeam_scenario(tmp_path, counts, gps, 30), tmp_path / "w")
    assert run.returncode == 0, run.stderr
    assert [e["on"] for e in run.events("mpu_fifo")] == []  # never switched on
    dropped = int(re.search(r"dropped=(\d+)", run.console("DIAG")[-1]).group(1))
    assert dropped > 0
    shown = [e["lines"][5] for e in run.screens() if len(e["lines"]) > 5 and e["lines"][5].startswith("imu ")]
    assert any(int(line.split("drop ")[1]) > 0 for line in shown), shown[-3:]
    files = sorted((tmp_path / "fs").glob("dr*.bin"))
    _, records = read_log(files[0].read_bytes())
    logged = [r[2] for r in records if r[0] == "E" and r[2].startswith("dropped")]
    assert logged and sum(int(e.split()[1]) for e in logged) <= dropped
