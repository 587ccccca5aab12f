"""Faults the emulated board injects into the app's own work (the peripherals' faults are in simworld.py).

    "faults": {"memory_error_at_s": t,   the kernel calls on samples at or after t raise MemoryError (a fragmented
               "memory_error_count": n}  heap inside a window), n of them in a row (default 1)
"""

import time

import simworld

_left = []  # MemoryErrors still to raise: a fault happens once in the run, not again at every boot


def install(spec):
    at = spec.get("memory_error_at_s")
    if at is None:
        return
    import app

    dr = app.dr
    if not _left:
        _left.append(spec.get("memory_error_count", 1))
    left = _left
    for name in ("fused_process", "process"):
        fn = getattr(dr, name, None)
        if fn is not None:
            setattr(dr, name, _failing(fn, int(at * 1000000), left))


def _failing(fn, at_us, left):
    def call(*args):
        if left[0] and time.now() >= at_us:
            left[0] -= 1
            simworld.trace("fault", kind="MemoryError in a window")
            raise MemoryError("memory allocation failed (injected)")
        return fn(*args)

    return call
