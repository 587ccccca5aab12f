"""Whole-board rules for `target: circuitpython` (phase two of validation, beside codegen.board.rules).

CircuitPython runs the same chips, so the chip's pin rules still hold (codegen.board.rules checks the GPIO behind
each board.* name). What differs is what the firmware decides itself, and what it does not have:

- the board: `circuitpython.board` fixes the chip, the flash size and the PSRAM; the YAML must agree with it;
- peripherals: busio.I2C and busio.UART take pins, not bus ids. CircuitPython picks the peripheral from the pins
  (on the RP2040 the pins must belong to one peripheral, and two buses cannot share one), so a written `id` is
  not used (a warning);
- MicroPython's firmware settings (`micropython:` release, partitions, filesystem) do not exist: the CIRCUITPY
  drive is the board's filesystem (an error when written, with what to do instead);
- the release: the app uses supervisor.ticks_ms, microcontroller.watchdog and storage.remount as 9.0 has them.
"""

from __future__ import annotations

from typing import Iterator

from codegen.board.chips import ChipPins
from codegen.board.circuitpython import MIN_CIRCUITPYTHON, WATCHDOG_MAX_S, find_board
from codegen.board.diagnostics import Diagnostic, error, warning
from codegen.board.flashlayout import version_tuple
from codegen.board.model import Board
from codegen.board.yamlsource import SourceMap


def check_circuitpython(board: Board, chip: ChipPins, source: SourceMap) -> list[Diagnostic]:
    """Every finding about a CircuitPython board (the loader has already resolved its pin names)."""
    found: list[Diagnostic] = []
    found += _check_board_matches(board, source)
    found += _check_not_micropython(source)
    found += _check_algorithm_runs(board, source)
    found += _check_peripherals(board, chip, source)
    found += _check_version(board, source)
    found += _check_watchdog(board, source)
    return found


def _check_board_matches(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    cp = find_board(board.circuitpython.board)
    where = source.value(("circuitpython", "board"))
    if board.chip != cp.chip:
        yield error(f"chip: the {cp.title} ({cp.board_id}) is an {cp.chip.upper()}, not an {board.chip.upper()}",
                    source.value(("chip",)), f"write `chip: {cp.chip}`, or name the CircuitPython board you have")
    if board.flash_size != cp.flash_size:
        yield error(f"flash_size: the {cp.title} has {cp.flash_size} of flash, not {board.flash_size}",
                    source.value(("flash_size",)) if ("flash_size",) in source.values else where,
                    f"write `flash_size: {cp.flash_size}`")
    if board.psram != cp.psram:
        yield error(
            f"psram: the {cp.title} {'has' if cp.psram else 'has no'} PSRAM (psram: {str(board.psram).lower()})",
            source.value(("psram",)) if ("psram",) in source.values else where,
            f"write `psram: {str(cp.psram).lower()}`, or name the board variant you have",
        )


def _check_algorithm_runs(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    if board.algorithm.mode == "eskf":
        # the filter exists as float32 C only (native_ext/dr_eskf.c); the app's pure-Python kernels are the seed's
        # and the fused method's (dr_fallback), and CircuitPython loads no native module
        yield error(
            "algorithm.mode: eskf runs in the native module only, and CircuitPython loads no native module",
            source.value(("algorithm", "mode")),
            "use `mode: fused` (the pure-Python kernel runs it), or `target: micropython` to run the eskf",
        )


def _check_not_micropython(source: SourceMap) -> Iterator[Diagnostic]:
    if ("micropython",) in source.keys:
        yield error(
            "micropython: describes MicroPython's firmware (release, flash partitions, filesystem); a CircuitPython "
            "board has its own layout and the CIRCUITPY drive",
            source.key(("micropython",)),
            "remove the micropython: section; the CircuitPython release goes in circuitpython.version",
        )


def _check_peripherals(board: Board, chip: ChipPins, source: SourceMap) -> Iterator[Diagnostic]:
    for kind, buses, table, signals in (
        ("i2c", board.i2c, chip.i2c_pins, ("sda", "scl")),
        ("uart", board.uart, chip.uart_pins, ("tx", "rx")),
    ):
        taken: dict[int, str] = {}
        for name, bus in buses.items():
            if (kind, name, "id") in source.keys:
                yield warning(
                    f"{kind}.{name}.id: busio.{kind.upper()} picks the peripheral from the pins; the id is not used "
                    "on CircuitPython",
                    source.key((kind, name, "id")),
                    "remove the id",
                )
            if not table:
                continue  # any pin reaches any peripheral through the chip's GPIO matrix
            pins = {signal: getattr(bus, signal) for signal in signals if getattr(bus, signal) is not None}
            fitting = [peripheral for peripheral, allowed in sorted(table.items())
                       if all(pin.pin in allowed[signal] for signal, pin in pins.items())]
            if not fitting:
                described = " and ".join(f"{signal.upper()} {pin.label}" for signal, pin in pins.items())
                pairs = "; ".join(
                    f"{kind.upper()}{peripheral}: " + ", ".join(
                        f"{signal.upper()} GPIO {'/'.join(map(str, sorted(allowed[signal])))}" for signal in signals)
                    for peripheral, allowed in sorted(table.items()))
                yield error(
                    f"{kind}.{name}: no {kind.upper()} peripheral of the {chip.name} has {described}",
                    source.value((kind, name, signals[0])),
                    f"the pins of one bus must belong to one peripheral ({pairs})",
                )
                continue
            peripheral = fitting[0]
            if peripheral in taken:
                yield error(
                    f"{kind}.{name}: its pins are on {kind.upper()}{peripheral}, which {kind}.{taken[peripheral]} "
                    "already uses",
                    source.value((kind, name, signals[0])),
                    f"move one bus to the pins of another {kind.upper()} peripheral",
                )
            taken[peripheral] = name


def _check_version(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    version = board.circuitpython.version
    if version_tuple(version) < MIN_CIRCUITPYTHON:
        minimum = ".".join(map(str, MIN_CIRCUITPYTHON))
        yield error(
            f"circuitpython.version: the app needs CircuitPython {minimum} or newer, not {version}",
            source.value(("circuitpython", "version")),
            "install a current CircuitPython (the board's page on circuitpython.org) and set this to its release",
        )


def _check_watchdog(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    limit = WATCHDOG_MAX_S.get(board.chip)
    if limit is not None and board.circuitpython.watchdog_s > limit:
        yield error(
            f"circuitpython.watchdog_s: CircuitPython on the {board.chip.upper()} takes a watchdog timeout of at most "
            f"{limit:g} s, not {board.circuitpython.watchdog_s:g}",
            source.value(("circuitpython", "watchdog_s")),
            f"use watchdog_s <= {limit:g}",
        )
