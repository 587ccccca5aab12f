"""Faults on the emulated board: the device keeps or regains GPS mode, says what failed, and its log
loses at most the open block.

Each run is the default board (fused, T-Beam v1.1) walking with fixes, on the board's clock and heap, with one
fault: an I2C NACK mid-run, the IMU gone (and back), the GPS UART silent, a MemoryError inside a window (once, and
twice: the top-level handler), a full filesystem, a power cut in the middle of a flash write, a bus that hangs
until the watchdog resets the board (and, in a car, the calibration from before the reset taken up again).
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest
from appkit import outage_world

from codegen.board.loader import load_board
from codegen.kernel.layout import FUSED
from codegen.post.devicelog import parse_device_log
from codegen.sim.harness import generate_app, read_log, run_app
from conftest import board_micropython

DURATION = 45.0
BLOCK_SPAN_S = 6.0  # one 4096-byte log block at the defaults (50 Hz IMU records of 17 bytes, fixes, windows)


@pytest.fixture(scope="module")
def tbeam(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tbeam")
    return load_board("ttgo-tbeam-v1.1").board, generate_app("ttgo-tbeam-v1.1", folder / "out")


def run(tbeam, work: Path, edit=None, outages=(), duration=DURATION):
    board, out = tbeam
    world, _, _ = outage_world(board, "walk", 5, duration, list(outages), work)
    if edit:
        edit(world)
    result = run_app(board_micropython(), out, world, work / "w")
    assert "Traceback" not in result.stderr, result.stderr
    return result


def head(lines):
    return lines[0].split()[0] if lines and lines[0] else ""


def gps_shown(screen):
    """The screen shows the GPS's position: GPS mode, or a calibration running beside it (after a reset)."""
    return head(screen) in ("GPS", "CAL") and " fix " in screen[0] and re.match(r"\d+\.\d{7} [NS]$", screen[1])


def said(result, text):
    """The failure was said: on the screen's status line, on the console, and in the log."""
    on_screen = any(text in e["lines"] for e in result.screens())
    on_console = f"WARN {text}" in result.stdout
    return on_screen and on_console


def log_records(result, work):
    files = sorted((work / "fs").glob("dr*.bin"))
    assert files, "no log file on the flash"
    out = []
    for path in files:
        parse_device_log(path)  # the post-processor reads every file (whole blocks, no damage)
        out.append(read_log(path.read_bytes()))
    return files, out


def events(records):
    return [r[2] for r in records if r[0] == "E"]


def test_i2c_nack_for_a_moment_costs_nothing(tbeam, tmp_path):
    def edit(world):
        world["i2c"]["0"][0].update(nack_after_s=22.0, nack_until_s=22.3)

    result = run(tbeam, tmp_path, edit)
    assert result.returncode == 0, result.stdout[-2000:]
    assert "IMU lost" not in result.stdout
    last = result.console("DIAG")[-1]
    assert "dropped=0" in last, last  # the FIFO held the samples of the 0.3 s
    assert head(result.screen_at(DURATION - 0.1)) == "GPS"


def test_imu_gone_keeps_gps_and_says_so(tbeam, tmp_path):
    def edit(world):
        world["i2c"]["0"][0].update(nack_after_s=20.0)

    result = run(tbeam, tmp_path, edit)
    assert result.returncode == 0, result.stdout[-2000:]
    assert said(result, "IMU lost")
    screen = result.screen_at(DURATION - 0.1)
    assert head(screen) == "GPS" and "IMU missing" in screen
    _, logs = log_records(result, tmp_path)
    assert "warn IMU lost" in events(logs[-1][1])


def test_imu_back_is_calibrated_again(tbeam, tmp_path):
    def edit(world):
        world["i2c"]["0"][0].update(nack_after_s=14.0, nack_until_s=16.0)

    # a walk that stands still again from 17 s on is not available: the device is put down for the new calibration
    result = run(tbeam, tmp_path, edit, duration=40.0)
    assert said(result, "IMU lost") and said(result, "IMU back")
    assert len([line for line in result.stdout.splitlines() if line.startswith("CAL start")]) == 2


def test_gps_silent_is_told_from_no_fix_and_gps_returns(tbeam, tmp_path):
    def edit(world):
        for uart in world["uart"].values():
            uart["silent"] = [22.0, 32.0]

    result = run(tbeam, tmp_path, edit)
    assert result.returncode == 0, result.stdout[-2000:]
    assert said(result, "GPS silent") and said(result, "GPS back")
    assert head(result.screen_at(29.0)) == "IMU"  # dead reckoning through the silence
    assert head(result.screen_at(DURATION - 0.1)) == "GPS"


def test_memory_error_in_a_window_is_retried(tbeam, tmp_path):
    result = run(tbeam, tmp_path, lambda world: world.update(faults={"memory_error_at_s": 25.0}))
    assert result.returncode == 0, result.stdout[-2000:]
    assert said(result, "memory: retried")
    assert "FATAL" not in result.stdout and not result.events("boot")
    assert [e for e in result.events("fault")]


def test_memory_error_twice_logs_shows_and_resets(tbeam, tmp_path):
    result = run(tbeam, tmp_path, lambda world: world.update(faults={"memory_error_at_s": 25.0,
                                                                     "memory_error_count": 2}))
    assert result.returncode == 0, result.stdout[-2000:]
    assert "FATAL" in result.stdout and "MemoryError" in result.stdout
    shown = [e for e in result.screens() if e["lines"] and e["lines"][0] == "ERROR"]
    assert shown and "MemoryError" in shown[-1]["lines"][1]  # its last page sent
    boots = result.events("boot")
    assert boots and boots[0]["cause"] == "machine.reset"
    assert said(result, "reset: error")
    assert gps_shown(result.screen_at(DURATION - 0.1))  # regained after the reset (walking: no calibration yet)
    files, logs = log_records(result, tmp_path)
    assert len(files) == 2  # the boot before the error, and the one after
    assert any(e.startswith("fatal MemoryError") for e in events(logs[0][1]))
    t_fatal = [r[1] for r in logs[0][1] if r[0] == "E" and r[2].startswith("fatal")][0]
    t_last = max(r[1] for r in logs[0][1])
    assert t_last == t_fatal  # the handler wrote the open block: nothing of that boot was lost


def test_full_filesystem_stops_logging_not_the_device(tbeam, tmp_path):
    def edit(world):
        # 2 MiB partition: a file that is not the app's leaves less than the log's floor (256 KiB)
        world["fs"]["prefill_bytes"] = 2 * 1024 * 1024 - 200 * 1024

    result = run(tbeam, tmp_path, edit)
    assert result.returncode == 0, result.stdout[-2000:]
    assert said(result, "log full")
    assert head(result.screen_at(DURATION - 0.1)) == "GPS"


def test_flash_failing_mid_run_keeps_the_blocks_written(tbeam, tmp_path):
    result = run(tbeam, tmp_path, lambda world: world["fs"].update(write_error_after_s=25.0))
    assert result.returncode == 0, result.stdout[-2000:]
    assert said(result, "log write failed")
    assert head(result.screen_at(DURATION - 0.1)) == "GPS"
    files, logs = log_records(result, tmp_path)
    t_last = max(r[1] for r in logs[0][1]) / 1e6
    assert 25.0 - 2 * BLOCK_SPAN_S < t_last < 25.0  # what reached the flash before it failed is all there


def test_power_cut_mid_block_loses_at_most_the_open_block(tbeam, tmp_path):
    cut = 30.0
    result = run(tbeam, tmp_path, lambda world: world["fs"].update(power_cut_s=cut))
    assert result.returncode == 4, result.stdout[-2000:]  # the run ended in the cut
    assert result.events("power_cut")
    t_cut = result.events("power_cut")[0]["t_us"] / 1e6
    files, logs = log_records(result, tmp_path)
    header, records = logs[-1]
    t_last = max(r[1] for r in records) / 1e6
    # the file's clock starts when the app opens it, a fraction of a second after power-up; what is missing at the
    # end is the block being written when the power went and the open one: at most two blocks' time
    assert 0.0 <= t_cut - t_last < 2 * BLOCK_SPAN_S + 1.0, (t_cut, t_last)
    assert [r for r in records if r[0] == "G"] and [r for r in records if r[0] == "I"]


def test_watchdog_resets_a_stuck_loop_and_gps_returns(tbeam, tmp_path):
    def edit(world):
        world["i2c"]["0"][0].update(hang_at_s=22.0, hang_s=12.0)  # the bus held longer than the 5 s watchdog

    result = run(tbeam, tmp_path, edit)
    assert result.returncode == 0, result.stdout[-2000:]
    boots = result.events("boot")
    assert boots and boots[0]["cause"] == "watchdog"
    assert 26.5 < boots[0]["t_us"] / 1e6 < 27.5  # 22 s + the board's 5 s
    assert said(result, "reset: watchdog")
    assert gps_shown(result.screen_at(DURATION - 0.1))
    files, logs = log_records(result, tmp_path)
    assert len(files) == 2
    t_last = max(r[1] for r in logs[0][1]) / 1e6
    assert 22.0 - BLOCK_SPAN_S < t_last <= 22.0 + 0.1  # the first boot's log up to its last whole block


def test_watchdog_reset_on_the_road_takes_up_what_it_had_before(tbeam, tmp_path):
    """The simulated car calibrates at rest, drives off, and the bus hangs at 22 s, at 15 m/s: the watchdog resets
    the board, whose next calibration moves. The fused kernel's learnt state (fused_keep: attitude, gyro bias,
    accelerometer offsets, along-track bias), kept in the RTC's memory at the rest and at every fix after it, is
    taken up instead of the motion's calibration (a car's acceleration for gravity, its turns for the gyro's bias):
    "CAL ok" prints the last record's attitude and bias; said on the console and in the log."""
    board, out = tbeam
    world, traj, _ = outage_world(board, "car", 5, 45.0, [], tmp_path)
    world["i2c"]["0"][0].update(hang_at_s=22.0, hang_s=6.0)  # held past the 5 s watchdog, free again at 28 s
    assert float(np.hypot(*traj.velocity_at(np.array([22.0, 30.0]))[:, :2].T).min()) > 10.0
    result = run_app(board_micropython(), out, world, tmp_path / "w")
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stdout[-2000:]
    boots = result.events("boot")
    assert [b["cause"] for b in boots] == ["watchdog"]
    kept = [w for w in result.events("rtc_memory") if w["t_us"] < boots[0]["t_us"]]
    assert len(kept) >= 5, kept  # the rest's, then one per fix while it drove
    record = bytes.fromhex(kept[-1]["data"])
    assert record[:4] == b"DRf2" and len(record) == 4 + 4 * len(FUSED.kept)
    values = struct.unpack("<%df" % len(FUSED.kept), record[4:])
    calibrated = result.console("CAL ok")
    assert len(calibrated) == 2, result.stdout[-3000:]
    printed = [float(x) for x in re.findall(r"-?\d+\.\d+", calibrated[1])]
    np.testing.assert_allclose(printed[:4], values[:4], atol=1.5e-5)  # q, as "%.5f"
    np.testing.assert_allclose(printed[4:7], values[4:7], atol=0.015)  # the gyro's bias (counts), as "%.2f"
    assert calibrated[0] != calibrated[1]  # the attitude of the last fix before the reset, not the rest's
    assert result.console("CAL moved: the calibration from before the reset restored")
    assert not result.console("CAL moved: travelling")  # the motion's calibration was not the one kept
    _, logs = log_records(result, tmp_path)
    assert "calibration restored" in events(logs[1][1])

