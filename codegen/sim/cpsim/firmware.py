"""What the emulated CircuitPython firmware knows about the board it runs on, from the scenario's "circuitpython"
entry (written by the host: codegen/sim/cpharness.py):

    circuitpython   {"board_id": str, "chip": str, "pins": {board name: GPIO}, "usb_connected": bool,
                     "monotonic_ns_step": ns, "watchdog_max_s": s or null}

Pins are claimed by the object that uses them (busio, digitalio) until it is deinitialised, as the firmware does:
a second claim raises ValueError("... in use").
"""

import simworld

_S = simworld.scenario().get("circuitpython", {})
_claimed = {}  # GPIO -> what holds it


def settings():
    return _S


def claim(pin, holder):
    gpio = pin._gpio
    if gpio in _claimed:
        raise ValueError("%s in use" % pin)
    _claimed[gpio] = holder


def release(pin):
    if pin is not None:
        _claimed.pop(pin._gpio, None)


def release_all():
    """A reset or reload of the firmware: every object the old program made is gone."""
    _claimed.clear()
