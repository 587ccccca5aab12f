"""The emulated CircuitPython board (codegen/sim/cpsim): CircuitPython's modules over mpsim's world, with the
firmware's rules (locks, claimed pins, a read-only drive until boot.py remounts it, no machine, no ticks_us)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from codegen.board.loader import load_board
from codegen.sim.cpharness import breadboard_world, circuitpython_world, run_circuitpython
from codegen.sim.harness import imu_counts, nmea_epoch, write_counts, write_stream
from conftest import circuitpython

REMOUNT = 'import storage\nstorage.remount("/", readonly=False)\n'


def _run(tmp_path: Path, code: str, boot: str | None = REMOUNT, board_name: str = "pico-gy521-circuitpython",
         duration_s: float = 3.0, pins: dict | None = None):
    micropython = circuitpython()
    app = tmp_path / "app"
    (app / "lib").mkdir(parents=True, exist_ok=True)
    (app / "code.py").write_text(textwrap.dedent(code))
    if boot is not None:
        (app / "boot.py").write_text(boot)
    board = load_board(board_name).board
    work = tmp_path / "work"
    work.mkdir(exist_ok=True)
    counts = write_counts(work / "counts.bin", imu_counts(duration_s + 1, 200.0))
    gps = write_stream(work / "gps.txt", [(t, nmea_epoch(t, 40.0, -105.0)) for t in range(int(duration_s) + 1)])
    scenario = breadboard_world(board, work, counts, gps, duration_s, pins=pins)
    scenario["circuitpython"] = circuitpython_world(board)
    run = run_circuitpython(micropython, app, scenario, work, timeout=120)
    assert run.returncode == 0, run.stderr
    return run


def _said(run) -> dict[str, str]:
    return {line.split(" ", 1)[0]: line.split(" ", 1)[1] for line in run.stdout.splitlines() if " " in line}


def test_i2c_needs_the_lock_and_meets_the_worlds_chips(tmp_path):
    run = _run(tmp_path, """
        import board, busio
        i2c = busio.I2C(board.GP5, board.GP4, frequency=400000)
        try:
            i2c.scan()
        except RuntimeError as e:
            print("nolock", e)
        while not i2c.try_lock():
            pass
        print("scan", [hex(a) for a in i2c.scan()])
        who = bytearray(1)
        i2c.writeto_then_readfrom(0x68, bytes([0x75]), who)
        print("who", hex(who[0]))
        try:
            i2c.writeto(0x3D, b"\\x00")
        except OSError as e:
            print("nack", e.args[0])
        i2c.unlock()
        other = busio.I2C(board.GP9, board.GP8)  # wired to nothing
        other.try_lock()
        print("other", other.scan())
    """)
    said = _said(run)
    assert said["nolock"] == "Function requires lock"
    assert said["scan"] == "['0x3c', '0x68']"
    assert said["who"] == "0x68"
    assert said["nack"] == "19"
    assert said["other"] == "[]"


def test_pins_are_claimed_and_names_are_the_boards(tmp_path):
    run = _run(tmp_path, """
        import board, busio, digitalio
        i2c = busio.I2C(board.GP5, board.GP4)
        try:
            digitalio.DigitalInOut(board.GP4)
        except ValueError as e:
            print("claimed", e)
        led = digitalio.DigitalInOut(board.LED)
        led.switch_to_output(value=True)
        led.value = False
        led.deinit()
        again = digitalio.DigitalInOut(board.GP25)
        print("again", again.value)
        print("same", board.LED == board.GP25, repr(board.GP26_A0))
        print("id", board.board_id)
    """)
    said = _said(run)
    assert said["claimed"] == "board.GP4 in use"
    assert said["same"] == "True board.GP26"
    assert said["id"] == "raspberry_pi_pico"
    assert [(e["pin"], e["v"]) for e in run.events("pin")][:2] == [(25, 1), (25, 0)]


def test_buttons_and_uart_are_the_worlds(tmp_path):
    run = _run(tmp_path, """
        import board, busio, digitalio, time
        button = digitalio.DigitalInOut(board.GP14)
        button.switch_to_input(pull=digitalio.Pull.UP)
        levels = []
        for _ in range(6):
            levels.append(int(button.value))
            time.sleep(0.25)
        print("levels", levels)
        gps = busio.UART(board.GP0, board.GP1, baudrate=9600, timeout=0, receiver_buffer_size=1024)
        time.sleep(1.2)
        print("gps", gps.read(gps.in_waiting)[:6])
    """, pins={"14": [[0.5, 0], [1.0, 1]]})
    said = _said(run)
    assert said["levels"] == "[1, 1, 0, 0, 1, 1]"
    assert said["gps"] == "b'$GPRMC'"


def test_the_clock_is_circuitpythons(tmp_path):
    run = _run(tmp_path, """
        import supervisor, time
        first = supervisor.ticks_ms()
        t0 = time.monotonic_ns()
        time.sleep(0.5)
        t1 = time.monotonic_ns()
        print("first", first)
        print("step", t0 % 30518, t1 % 30518, (t1 - t0) // 1000000)
        print("ticks_us", hasattr(time, "ticks_us"), hasattr(time, "ticks_ms"))
        try:
            import machine
        except ImportError:
            print("machine", "missing")
    """)
    said = _said(run)
    assert int(said["first"]) == (0x1FFF0000) % (1 << 29)  # wraps 65.5 s after power-on, as the firmware's does
    assert said["step"] == "0 0 500"
    assert said["ticks_us"] == "False False"
    assert said["machine"] == "missing"


def test_the_drive_is_read_only_until_boot_py_remounts_it(tmp_path):
    code = """
        try:
            with open("/logs/f.txt", "w") as f:
                f.write("x")
            print("write", "ok")
        except OSError as e:
            print("write", e.args[0])
        import storage
        try:
            storage.remount("/", readonly=False)
        except RuntimeError as e:
            print("remount", e)
    """
    assert _said(_run(tmp_path / "a", code, boot=None))["write"] == "30"  # EROFS
    said = _said(_run(tmp_path / "b", code))
    assert said["write"] == "ok"
    assert said["remount"] == "Cannot remount path when visible via USB."


def test_a_reset_boots_again_from_boot_py(tmp_path):
    run = _run(tmp_path, """
        import microcontroller, os
        boots = len(os.listdir("/logs"))
        with open("/logs/boot%d" % boots, "w") as f:
            f.write("")
        print("boot", boots, microcontroller.cpu.reset_reason == microcontroller.ResetReason.SOFTWARE)
        if boots == 0:
            microcontroller.reset()
        print("done", boots)
    """)
    assert run.console("boot") == ["boot 0 False", "boot 1 True"]
    assert run.console("done") == ["done 1"]


def test_rp2040_watchdog_limit(tmp_path):
    run = _run(tmp_path, """
        import microcontroller, watchdog
        wdt = microcontroller.watchdog
        try:
            wdt.timeout = 8.5
        except ValueError:
            print("limit", "refused")
        wdt.timeout = 5
        wdt.mode = watchdog.WatchDogMode.RESET
        wdt.feed()
        print("fed", wdt.timeout)
    """)
    said = _said(run)
    assert said["limit"] == "refused" and said["fed"] == "5"


@pytest.mark.parametrize("board_name, pins", [("esp32s3-devkitc-gy521-circuitpython", ("IO9", "IO8"))])
def test_the_esp32s3_board_names(tmp_path, board_name, pins):
    run = _run(tmp_path, f"""
        import board, busio
        i2c = busio.I2C(board.{pins[0]}, board.{pins[1]})
        i2c.try_lock()
        print("scan", i2c.scan())
        print("neopixel", repr(board.NEOPIXEL))
    """, board_name=board_name)
    said = _said(run)
    assert said["scan"] == "[60, 104]"
    assert said["neopixel"] == "board.IO48"


def test_a_watchdog_not_fed_resets_the_board(tmp_path):
    run = _run(tmp_path, """
        import microcontroller, time, watchdog
        reason = microcontroller.cpu.reset_reason
        print("boot", reason == microcontroller.ResetReason.WATCHDOG)
        if reason != microcontroller.ResetReason.WATCHDOG:
            microcontroller.watchdog.timeout = 1
            microcontroller.watchdog.mode = watchdog.WatchDogMode.RESET
            while True:
                time.sleep(0.1)
        print("after", "watchdog")
    """, duration_s=4.0)
    assert run.console("boot") == ["boot False", "boot True"]
    assert run.console("after") == ["after watchdog"]
    assert [e["cause"] for e in run.events("boot")] == ["watchdog"]
