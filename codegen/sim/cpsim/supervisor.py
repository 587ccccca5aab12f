"""Emulated CircuitPython `supervisor`: ticks_ms() as the firmware computes it, runtime, reload().

ticks_ms() is the firmware's 1/1024 s tick counter in milliseconds, offset so that it wraps (at 2**29 ms) 65 s
after power-on (shared-bindings/supervisor: (ms + 0x1fff0000) % 2**29), on the world's virtual clock.
"""

import time

import simworld

TICKS_PERIOD = 1 << 29
_OFFSET_MS = 0x1FFF0000


def _raw_ticks():
    """The firmware's 1/1024 s ticks since power-on (the world's clock)."""
    return time.now() * 1024 // 1000000


def ticks_ms():
    time.advance(time.READ_COST_US)
    return (_raw_ticks() * 1000 // 1024 + _OFFSET_MS) % TICKS_PERIOD


class _Runtime:
    @property
    def usb_connected(self):
        return simworld.scenario().get("circuitpython", {}).get("usb_connected", True)

    @property
    def serial_connected(self):
        return self.usb_connected

    @property
    def serial_bytes_available(self):
        return 0

    autoreload = True


runtime = _Runtime()


class ReloadRequested(BaseException):
    """supervisor.reload(): the launcher runs code.py again (not boot.py), as the firmware's soft reload does."""


def reload():
    simworld.trace("reload")
    raise ReloadRequested()


_traceback = None


def get_previous_traceback():
    return _traceback
