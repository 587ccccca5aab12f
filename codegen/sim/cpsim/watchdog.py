"""Emulated CircuitPython `watchdog`: the modes of microcontroller.watchdog and its timeout exception."""


class WatchDogMode:
    RAISE = 1
    RESET = 2


class WatchDogTimeout(Exception):
    pass
