"""Start the generated app (its main.py, or a test's script) on the emulated board: `micropython launch.py TARGET`.

The target is compiled first, then the world loads (machine: the scenario, the file system, the heap the board
leaves the app), then the board's clock meters the app (boardclock.py) and the scenario's faults go in (faults.py),
then the target runs. Everything loaded before the world is the emulated board's own and stays out of the app's
heap. When the board resets (machine.reset(), the watchdog), the app's modules are dropped and it boots again, with
the world (the chips, the GPS stream, the file system, the clock) as it is.
"""

import gc
import sys

_target = sys.argv[1]
with open(_target) as _f:
    _code = compile(_f.read(), _target, "exec")

import time  # noqa: E402

import boardclock  # noqa: E402
import faults  # noqa: E402
import machine  # noqa: E402,F401  (the world, and the heap it leaves the app)
import simworld  # noqa: E402

_own = set(sys.modules)
_scenario = simworld.scenario()
time.interrupt_at([t * 1000000 for t in _scenario.get("interrupts_s", ())])  # Ctrl-C at these moments
_clock = _scenario.get("clock")
if _clock:
    simworld.at_end(lambda: simworld.trace("clock", charged=boardclock.totals()))

while True:
    if _clock:
        boardclock.install(_clock["costs"])
    faults.install(_scenario.get("faults", {}))
    cause = None
    try:
        exec(_code, {"__name__": "__main__", "__file__": _target})
        break
    except time.Reset as reset:
        cause = str(reset)
    # the board resets: nothing of the old app stays (its modules go, and the heap they held)
    simworld.trace("boot", cause=cause)
    time.disarm_watchdog()
    time.clear_timers()
    time.halted = False
    for name in list(sys.modules):
        if name not in _own:
            del sys.modules[name]
    gc.collect()
