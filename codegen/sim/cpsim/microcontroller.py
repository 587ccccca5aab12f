"""Emulated CircuitPython `microcontroller`: Pin, pin (GPIOn names), cpu, reset(), watchdog.

Pins are the chip's GPIOs; board.* names are aliases of them (board.py). reset() restarts the board (mpsim's
machine.reset: the launcher runs boot.py and code.py again, with the world as it is). The watchdog is the world's (mpsim's machine.WDT): in
RESET mode, not fed for its timeout, it resets the board.
"""

import machine
import time

import firmware
import simworld


class Pin:
    """A microcontroller pin; the number is the emulation's, the firmware's pins have no public one."""

    def __init__(self, gpio, name):
        self._gpio = gpio
        self._name = name

    def __repr__(self):
        return "board." + self._name if self._name else "microcontroller.pin.GPIO%d" % self._gpio

    __str__ = __repr__

    def __eq__(self, other):
        return isinstance(other, Pin) and other._gpio == self._gpio

    def __hash__(self):
        return self._gpio


class _PinModule:
    pass


pin = _PinModule()
_by_gpio = {}
for _name, _gpio in sorted(firmware.settings().get("pins", {}).items()):
    if _gpio not in _by_gpio or _name.lstrip("GPIO") == str(_gpio):
        _by_gpio[_gpio] = Pin(_gpio, _name)
for _gpio, _pin in _by_gpio.items():
    setattr(pin, "GPIO%d" % _gpio, _pin)


def board_pin(name, gpio):
    """The Pin object of a GPIO, named as the board module first names it."""
    found = _by_gpio.get(gpio)
    return found if found is not None else Pin(gpio, name)


class RunMode:
    NORMAL = 0
    SAFE_MODE = 1
    BOOTLOADER = 2
    UF2 = 3


class ResetReason:
    POWER_ON = 0
    BROWNOUT = 1
    SOFTWARE = 2
    DEEP_SLEEP_ALARM = 3
    RESET_PIN = 4
    WATCHDOG = 5
    UNKNOWN = 6
    RESCUE_DEBUG = 7


class _Cpu:
    frequency = 125000000

    @property
    def reset_reason(self):
        return {machine.PWRON_RESET: ResetReason.POWER_ON, machine.WDT_RESET: ResetReason.WATCHDOG,
                machine.SOFT_RESET: ResetReason.SOFTWARE}.get(machine.reset_cause(), ResetReason.UNKNOWN)

    @property
    def temperature(self):
        return 25.0


cpu = _Cpu()
cpus = (cpu,)


def reset():
    firmware.release_all()
    machine.reset()


def on_next_reset(run_mode):
    pass


def delay_us(delay):
    time.advance(delay)


def disable_interrupts():
    pass


def enable_interrupts():
    pass


class WatchDogTimer:
    """microcontroller.watchdog: set timeout, then mode (RESET starts it), feed() from the loop."""

    def __init__(self):
        self._timeout = None
        self._mode = None
        self._wdt = None

    @property
    def timeout(self):
        return self._timeout

    @timeout.setter
    def timeout(self, seconds):
        limit = firmware.settings().get("watchdog_max_s")
        if seconds <= 0 or (limit is not None and seconds > limit):
            raise ValueError("timeout must be <= %s" % limit)
        self._timeout = seconds
        if self._wdt is not None:
            self._start()

    @property
    def mode(self):
        return self._mode

    @mode.setter
    def mode(self, mode):
        import watchdog

        if mode is None:
            self.deinit()
            return
        if self._timeout is None:
            raise ValueError("watchdog timeout must be set first")
        if mode != watchdog.WatchDogMode.RESET:
            raise NotImplementedError("the emulated board resets; WatchDogMode.RAISE is not modelled")
        self._mode = mode
        self._start()

    def _start(self):
        self._wdt = machine.WDT(timeout=int(self._timeout * 1000))
        simworld.trace("watchdog", timeout_s=self._timeout)

    def feed(self):
        if self._wdt is None:
            raise ValueError("watchdog not started")
        self._wdt.feed()

    def deinit(self):
        self._mode = None
        self._wdt = None


watchdog = WatchDogTimer()
