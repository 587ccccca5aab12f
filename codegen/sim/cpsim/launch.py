"""Start a CircuitPython program on the emulated board: `micropython launch.py MPSIM_DIR APP_DIR`.

The emulated firmware boots as CircuitPython does. The world loads first (mpsim: the scenario, the chips, the
filesystem), then the firmware's own modules (board, busio, digitalio, microcontroller, supervisor, storage,
watchdog, and CircuitPython's `time`), bound to the world's clock; then mpsim's `machine` and `time` are hidden from
the program, which sees only what a CircuitPython board has, and the program gets the board's heap (all that was
loaded so far is the firmware's, as it is C on a board). At power-on the filesystem is read-only to the program,
boot.py runs once (it may storage.remount it), then code.py, metered by the board's clock and with the scenario's
faults, as mpsim's launcher does for MicroPython. supervisor.reload() runs code.py again; a reset
(microcontroller.reset(), the watchdog) boots again from boot.py, with the world as it is. When code.py ends or
stops with an exception (printed as the firmware prints it), the board idles until the world's time is up.
"""

import builtins
import gc
import sys

_mpsim, _app = sys.argv[1], sys.argv[2]
sys.path.insert(0, _mpsim)
import simworld  # noqa: E402

simworld.load(hold_heap=True)
import time  # noqa: E402  (mpsim's clock: the world's)

import boardclock  # noqa: E402
import faults  # noqa: E402
import machine  # noqa: E402,F401  (the world's chips)

sys.path.pop(0)

import board  # noqa: E402,F401
import busio  # noqa: E402,F401
import cptime  # noqa: E402
import digitalio  # noqa: E402,F401
import firmware  # noqa: E402
import microcontroller  # noqa: E402,F401
import storage  # noqa: E402
import supervisor  # noqa: E402
import traceback  # noqa: E402
import watchdog  # noqa: E402,F401

del sys.modules["machine"]
sys.modules["time"] = cptime
_firmware = set(sys.modules)
_scenario = simworld.scenario()
_clock = _scenario.get("clock")
if _clock:
    simworld.at_end(lambda: simworld.trace("clock", charged=boardclock.totals()))
_real_import = builtins.__import__
simworld.leave_heap()


def _start_program():
    """Nothing of the last program stays (its modules go, and the heap they held); the board's clock and the
    scenario's faults take hold of the app's modules as soon as code.py has imported `app` (code.py imports its
    modules in the order the heap needs: the launcher must not import them first, as mpsim's does)."""
    for name in [name for name in sys.modules if name not in _firmware]:
        del sys.modules[name]
    gc.collect()
    builtins.__import__ = _metering_import


def _metering_import(name, *args):
    module = _real_import(name, *args)
    if name == "app":
        builtins.__import__ = _real_import
        if _clock:
            boardclock.install(_clock["costs"])
        faults.install(_scenario.get("faults", {}))
    return module


def _run(name):
    """Run APP_DIR/name as the firmware runs boot.py and code.py; False when there is no such file."""
    path = _app + "/" + name
    try:
        with open(path) as handle:
            source = handle.read()
    except OSError:
        return False
    exec(compile(source, path, "exec"), {"__name__": "__main__", "__file__": path})
    return True


def _idle():
    simworld.trace("code_done")
    print("\nCode done running.")
    while True:
        time.advance(100000)


while True:
    cause = None
    try:
        firmware.release_all()
        storage.power_on()
        try:
            _run("boot.py")
        except Exception as problem:  # the firmware prints it and carries on with code.py
            traceback.print_exception(problem)
        storage.boot_done()
        while True:
            _start_program()
            try:
                _run("code.py")
                break
            except supervisor.ReloadRequested:
                firmware.release_all()
            except Exception as problem:
                traceback.print_exception(problem)
                break
        _idle()
    except time.Reset as reset:
        cause = str(reset)
    simworld.trace("boot", cause=cause)
    time.disarm_watchdog()
    time.halted = False
