"""Emulated CircuitPython `time` (the launcher installs it as `time` for the program): monotonic(),
monotonic_ns(), sleep(), time(), localtime(), on the world's virtual clock. There is no ticks_*: CircuitPython has
supervisor.ticks_ms and monotonic_ns instead, and a program that reaches for ticks_us fails here as on a board.

monotonic_ns() advances in the steps of the board's clock (the scenario's circuitpython.monotonic_ns_step: 1/32768 s
on the RP2040, whose firmware counts 1/1024 s ticks and 1/32 subticks; 1 us on the ESP32-S3). monotonic() is the
firmware's millisecond count in seconds.
"""

import time as _clock

import simworld

_STEP_NS = simworld.scenario().get("circuitpython", {}).get("monotonic_ns_step", 1000)


class struct_time(tuple):
    pass


def monotonic_ns():
    _clock.advance(_clock.READ_COST_US)
    ns = _clock.now() * 1000
    return ns - ns % _STEP_NS


def monotonic():
    _clock.advance(_clock.READ_COST_US)
    return (_clock.now() * 1024 // 1000000) * 1000 // 1024 / 1000


def sleep(seconds):
    """Whole milliseconds, rounded, as the firmware sleeps (shared-bindings/time: 1000 * seconds + 0.5)."""
    ms = int(1000 * seconds + 0.5)
    if ms < 0:
        raise ValueError("seconds must be >= 0")
    _clock.advance(ms * 1000)


def time():
    return _clock.time()


def localtime(secs=None):
    return struct_time(_clock.gmtime(secs) + (-1,))


def mktime(t):
    raise NotImplementedError("mktime is not modelled")
