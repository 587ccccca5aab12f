"""Emulated CircuitPython `digitalio`: DigitalInOut on mpsim's machine.Pin (the same buttons and LED)."""

import machine

import firmware


class Direction:
    INPUT = 0
    OUTPUT = 1


class Pull:
    UP = 1
    DOWN = 2


class DriveMode:
    PUSH_PULL = 0
    OPEN_DRAIN = 1


class DigitalInOut:
    def __init__(self, pin):
        firmware.claim(pin, self)
        self._board_pin = pin
        self._pin = machine.Pin(pin._gpio, machine.Pin.IN)
        self._direction = Direction.INPUT
        self._pull = None

    def deinit(self):
        firmware.release(self._board_pin)
        self._pin = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.deinit()

    def _live(self):
        if self._pin is None:
            raise ValueError("Object has been deinitialized and can no longer be used. Create a new object.")
        return self._pin

    def switch_to_output(self, value=False, drive_mode=DriveMode.PUSH_PULL):
        self._live().init(machine.Pin.OUT, value=1 if value else 0)
        self._direction = Direction.OUTPUT
        self._pull = None

    def switch_to_input(self, pull=None):
        self._live().init(machine.Pin.IN, {Pull.UP: machine.Pin.PULL_UP, Pull.DOWN: machine.Pin.PULL_DOWN,
                                           None: None}[pull])
        self._direction = Direction.INPUT
        self._pull = pull

    @property
    def direction(self):
        return self._direction

    @direction.setter
    def direction(self, direction):
        if direction == Direction.OUTPUT:
            self.switch_to_output()
        else:
            self.switch_to_input()

    @property
    def value(self):
        return bool(self._live().value())

    @value.setter
    def value(self, value):
        if self._direction != Direction.OUTPUT:
            raise AttributeError("Cannot set value when direction is input.")
        self._live().value(1 if value else 0)

    @property
    def pull(self):
        return self._pull

    @pull.setter
    def pull(self, pull):
        if self._direction == Direction.OUTPUT:
            raise AttributeError("Pull not used when direction is output.")
        self.switch_to_input(pull)
