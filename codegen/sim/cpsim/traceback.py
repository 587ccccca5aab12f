"""Emulated CircuitPython `traceback` (CircuitPython has no sys.print_exception): print_exception."""

import sys


def print_exception(exc, value=None, tb=None, limit=None, file=None, chain=True):
    exc = exc if value is None else value
    show = getattr(sys, "print_exception", None)
    if show is not None:
        show(exc)
    else:  # CircuitPython's unix port has neither, nor a traceback to walk: the exception itself
        print("Traceback (most recent call last):\n%s: %s" % (type(exc).__name__, exc))
