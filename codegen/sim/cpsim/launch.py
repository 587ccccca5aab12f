"""Start a CircuitPython program on the emulated board: `micropython launch.py MPSIM_DIR APP_DIR`.

The emulated firmware boots as CircuitPython does: the world loads first (mpsim: the scenario, the chips, the
filesystem), then the firmware's modules (board, busio, digitalio, microcontroller, supervisor, storage, watchdog,
and CircuitPython's `time`), bound to the world's clock; then mpsim's `machine` and `time` are hidden from the
program, which sees only what a CircuitPython board has. At power-on the filesystem is read-only to the program,
boot.py runs once (it may storage.remount it), then code.py. supervisor.reload() runs code.py again; a reset
(microcontroller.reset(), the watchdog) boots again from boot.py, with the world as it is. When code.py ends or
stops with an exception (printed as the firmware prints it), the board idles until the world's time is up.
"""

import sys

_mpsim, _app = sys.argv[1], sys.argv[2]
sys.path.insert(0, _mpsim)
import time  # noqa: E402  (mpsim's clock: the world's)
import machine  # noqa: E402,F401  (the world: scenario, chips, filesystem)
import simworld  # noqa: E402

sys.path.pop(0)

import board  # noqa: E402,F401
import busio  # noqa: E402,F401
import cptime  # noqa: E402
import digitalio  # noqa: E402,F401
import firmware  # noqa: E402
import microcontroller  # noqa: E402,F401
import storage  # noqa: E402
import supervisor  # noqa: E402
import watchdog  # noqa: E402,F401

RESET_EXIT = 3  # mpsim's machine.reset() ends with SystemExit(3)

del sys.modules["machine"]
sys.modules["time"] = cptime
_firmware = set(sys.modules)


def _drop_program():
    for name in [name for name in sys.modules if name not in _firmware]:
        del sys.modules[name]


def _run(name):
    """Run APP_DIR/name as the firmware runs boot.py and code.py; False when there is no such file."""
    path = _app + "/" + name
    try:
        with open(path) as handle:
            source = handle.read()
    except OSError:
        return False
    _drop_program()
    exec(compile(source, path, "exec"), {"__name__": "__main__", "__file__": path})
    return True


def _idle():
    simworld.trace("code_done")
    print("\nCode done running.")
    while True:
        time.advance(100000)


while True:
    firmware.release_all()
    storage.power_on()
    try:
        _run("boot.py")
    except Exception as problem:  # the firmware prints it and carries on with code.py
        sys.print_exception(problem)
    storage.boot_done()
    try:
        while True:
            try:
                _run("code.py")
                break
            except supervisor.ReloadRequested:
                firmware.release_all()
        _idle()
    except SystemExit as stop:
        if stop.args and stop.args[0] == RESET_EXIT:
            continue  # the board resets: boot.py again
        raise
    except Exception as problem:
        sys.print_exception(problem)
        _idle()
