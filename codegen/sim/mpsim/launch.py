"""Start the generated app (its main.py, or a test's script) on the emulated board: `micropython launch.py TARGET`.

The target is compiled first, then the world loads (machine: the scenario, the file system, the heap the board
leaves the app), then the board's clock meters the app (boardclock.py), then the target runs. Everything loaded
before the world is the emulated board's own and stays out of the app's heap.
"""

import sys

_target = sys.argv[1]
with open(_target) as _f:
    _code = compile(_f.read(), _target, "exec")

import machine  # noqa: E402,F401  (the world, and the heap it leaves the app)
import simworld  # noqa: E402

_clock = simworld.scenario().get("clock")
if _clock:
    import boardclock

    boardclock.install(_clock["costs"])
    simworld.at_end(lambda: simworld.trace("clock", charged=boardclock.totals()))

exec(_code, {"__name__": "__main__", "__file__": _target})
