"""The app's watchdog and the REPL, on the emulated board (codegen/sim/mpsim: machine.WDT and machine.Timer on
virtual time): stopped by Ctrl-C at any moment, even twice in a row, the app hands its watchdog to a timer, so the
REPL lives through a host's transfer three watchdog timeouts long; without a timer the board resets."""

from __future__ import annotations

import pytest

from codegen.sim.harness import generate_app, imu_counts, nmea_epoch, run_app, tbeam_scenario, write_counts, \
    write_stream
from conftest import require_tool

LAT, LON = 40.0350855, -75.52009367
WATCHDOG_S = 5.0  # the T-Beam's micropython.watchdog_s
REPL_SCRIPT = """
import time
try:
    import main  # the app's main.py, as the board boots it
except KeyboardInterrupt:
    print("REPL")
t0 = time.ticks_ms()
time.sleep_ms(%d)  # a host's transfer through the REPL
print("STILL UP after %%d ms" %% time.ticks_diff(time.ticks_ms(), t0))
time.sleep_ms(10000000)  # until the run ends
"""


@pytest.fixture(scope="module")
def tbeam(tmp_path_factory):
    return generate_app("ttgo-tbeam-v1.1", tmp_path_factory.mktemp("wdt") / "out")


def interrupted(micropython, app, work, at_s: list[float], timers: bool = True):
    duration = max(at_s) + 3 * WATCHDOG_S + 2.0
    counts = write_counts(work / "imu.bin", imu_counts(duration, 200.0, seed=4))
    gps = write_stream(work / "gps.txt", [(t, nmea_epoch(t, LAT, LON)) for t in range(1, int(duration))])
    scenario = tbeam_scenario(work, counts, gps, duration)
    scenario["interrupts_s"] = at_s
    scenario["timers"] = timers
    script = work / "repl.py"
    script.write_text(REPL_SCRIPT % int(3 * WATCHDOG_S * 1000))
    return run_app(micropython, app, scenario, work, script=str(script))


@pytest.mark.parametrize("at_s", [[0.05], [3.0, 3.0001], [11.37], [12.0, 12.00002]],
                         ids=["at-start", "calibrating-twice", "running", "running-twice"])
def test_the_repl_outlives_the_watchdog_after_ctrl_c(tbeam, tmp_path, at_s):
    micropython = require_tool("micropython")
    run = interrupted(micropython, tbeam, tmp_path, at_s)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "REPL" in run.stdout.splitlines()
    assert not run.events("boot"), run.events("boot")  # no reset
    still_up = [line for line in run.stdout.splitlines() if line.startswith("STILL UP after")]
    assert still_up == ["STILL UP after 15000 ms"]
    assert run.events("timer") and run.events("timer")[0]["period_ms"] == int(WATCHDOG_S * 1000) // 4


def test_without_a_timer_the_watchdog_resets_the_repl(tbeam, tmp_path):
    """The other side of the proof: the same Ctrl-C on a board without timers is reset by its watchdog."""
    micropython = require_tool("micropython")
    run = interrupted(micropython, tbeam, tmp_path, [11.37], timers=False)
    assert run.returncode == 0, run.stderr[-2000:]
    assert any(line.startswith("WARN watchdog: no timer") for line in run.stdout.splitlines())
    assert [e["cause"] for e in run.events("boot")][:1] == ["watchdog"]
    assert "STILL UP" not in run.stdout.split("DEADRECKON")[1]  # the first boot's REPL never got that far
