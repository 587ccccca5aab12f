"""Emulated CircuitPython `traceback` (CircuitPython has no sys.print_exception): print_exception."""

import sys


def print_exception(exc, value=None, tb=None, limit=None, file=None, chain=True):
    sys.print_exception(exc if value is None else value)
