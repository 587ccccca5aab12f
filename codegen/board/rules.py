"""Phase two of validation: rules over the whole board (each part already passed its own schema).

Pins are checked against the chip's capability table in `codegen.board.chips`; buses, addresses, power rails and the
algorithm's numbers against each other. Every finding is a located `Diagnostic`.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Iterator, Optional

from codegen.board.chips import CHIPS, PMU_RAILS, WATCHDOG_MAX_S, ChipPins
from codegen.board.circuitpython import find_board
from codegen.board.circuitpython_rules import check_circuitpython
from codegen.board.diagnostics import Diagnostic, error, warning
from codegen.board.flashlayout import FlashLayout, check_flash_layout, version_tuple
from codegen.board.model import DLPF_BANDWIDTH_HZ, FUSED, FUSED_MEDIAN_MAX, Board, PinSpec
from codegen.board.yamlsource import KeyPath, SourceMap

MPU6050_ADDRESSES = (0x68, 0x69)
MPU6050_MAX_ACCEL_RATE_HZ = 1000.0
RESERVED_I2C_ADDRESSES = set(range(0x00, 0x08)) | set(range(0x78, 0x80))
# The oldest MicroPython the app runs on. `deadreckon build` links dr_native.mpy against a v1.28 tree, which writes
# .mpy 6.3; a release before 1.23 (6.2 and older) refuses native code of another sub-version with ValueError
# ("incompatible .mpy file"), not the ImportError the app's fallback catches, so the app would stop at boot.
MIN_MICROPYTHON = (1, 23)
# algorithm.mode eskf (the native filter) on the emulated board (tests/test_app_boards.py -k eskf: 32-bit unix
# MicroPython with the board's heap, esp32-devkitc-gy521 with mode eskf, its x86 dr_native, a simulated drive with
# an outage), with that board's 24,000-byte calibration buffer (10 s at 200 Hz) and two 4 KiB log blocks: it failed
# at boot (MemoryError on a log block) in 102 KiB in every run, in 104 KiB in some runs (its low-water mark there moves
# from 1 to 10 KB with the heap's fragmentation and the machine's load), and ran in 108 KiB. Before the start on the
# move added its yaw fit's sums and the calibration's fix to the app it ran in 104 KiB and failed in 96. A board is
# refused below the heap the app ran in: that less the buffers it had, plus the board's (its keys size them).
ESKF_FAILED_HEAP_BYTES = 102 * 1024
ESKF_MEASURED_BUFFERS_BYTES = 12 * 2000 + 2 * 4096
ESKF_MEASURED_OK_HEAP_BYTES = 108 * 1024


@dataclass(frozen=True)
class PinUse:
    pin: PinSpec
    role: str  # what the user wrote, e.g. "i2c.main.sda"
    path: KeyPath
    output: bool
    pull: bool = False
    reserved: bool = False


def _pin_uses(board: Board) -> Iterator[PinUse]:
    """Reserved pins first, so a clash names the reservation before the use that breaks it."""
    for group, pins in board.reserved.items():
        for index, number in enumerate(pins):
            yield PinUse(PinSpec(pin=number), f"reserved.{group}", ("reserved", group, index), False, reserved=True)
    for name, bus in board.i2c.items():
        yield PinUse(bus.sda, f"i2c.{name}.sda", ("i2c", name, "sda"), output=True)
        yield PinUse(bus.scl, f"i2c.{name}.scl", ("i2c", name, "scl"), output=True)
    for name, uart in board.uart.items():
        yield PinUse(uart.rx, f"uart.{name}.rx", ("uart", name, "rx"), output=False)
        if uart.tx is not None:
            yield PinUse(uart.tx, f"uart.{name}.tx", ("uart", name, "tx"), output=True)
    for role in ("calibrate", "test_mode"):
        button = getattr(board.buttons, role)
        if button is not None:
            yield PinUse(
                button.pin, f"buttons.{role}.pin", ("buttons", role, "pin"), output=False, pull=button.pull != "none"
            )
    if board.led is not None:
        yield PinUse(board.led.pin, "led.pin", ("led", "pin"), output=True)


def _check_pins(board: Board, chip: ChipPins, source: SourceMap) -> Iterator[Diagnostic]:
    first_use: dict[int, PinUse] = {}
    for use in _pin_uses(board):
        number = use.pin.pin
        where = source.value(use.path)
        if number not in chip.existing:
            yield error(f"{use.role}: {use.pin.label} does not exist on the {chip.name}", where)
            continue
        if number in chip.flash:
            yield error(
                f"{use.role}: {use.pin.label} is wired to the SPI flash on the {chip.name}",
                where,
                "using it stops the chip from reading its own firmware; pick another pin",
            )
        if board.psram and number in chip.psram:
            yield error(f"{use.role}: {use.pin.label} is wired to the PSRAM on this board (psram: true)", where)
        if number in chip.input_only and use.output:
            yield error(
                f"{use.role}: {use.pin.label} is input-only on the {chip.name} and cannot drive an output",
                where,
                f"GPIO{min(chip.input_only)}..{max(chip.input_only)} can only be inputs (a UART rx, a button)",
            )
        if number in chip.input_only and use.pull:
            yield error(
                f"{use.role}: {use.pin.label} has no internal pull resistor on the {chip.name}",
                where,
                "set `pull: none` and fit an external pull-up, or use another pin",
            )
        if number in chip.strapping and not use.reserved:
            if not use.pin.strapping_by_design:
                yield warning(
                    f"{use.role}: {use.pin.label} is a strapping pin: the level at reset selects the boot mode",
                    where,
                    "if the board is designed this way, write `{pin: %s, strapping_by_design: true}`"
                    % (use.pin.name or number),
                )
        elif use.pin.strapping_by_design:
            yield error(
                f"{use.role}: `strapping_by_design` on {use.pin.label}, which is not a strapping pin of the "
                f"{chip.name}",
                source.value(use.path + ("strapping_by_design",)),
                f"strapping pins are {', '.join(f'GPIO{p}' for p in sorted(chip.strapping)) or 'none'}",
            )
        if number in chip.board_taken and not use.reserved:
            yield warning(f"{use.role}: {use.pin.label} is used by the board ({chip.board_taken[number]})", where)
        previous = first_use.get(number)
        if previous is not None:
            yield error(
                f"{use.pin.label} is used twice: by {previous.role} and by {use.role}",
                where,
                f"{previous.role} is at {source.value(previous.path)}",
            )
        else:
            first_use[number] = use


def _check_fixed_muxing(board: Board, chip: ChipPins, source: SourceMap) -> Iterator[Diagnostic]:
    for kind, buses, ids, table in (
        ("i2c", board.i2c, chip.i2c_ids, chip.i2c_pins),
        ("uart", board.uart, chip.uart_ids, chip.uart_pins),
    ):
        seen_ids: dict[int, str] = {}
        for name, bus in buses.items():
            if bus.id not in ids:
                yield error(
                    f"{kind}.{name}.id: the {chip.name} has no {kind.upper()}{bus.id}",
                    source.value((kind, name, "id")),
                    f"valid ids: {', '.join(map(str, sorted(ids)))}",
                )
            if bus.id in seen_ids:
                yield error(
                    f"{kind}.{name}.id: {kind.upper()}{bus.id} is already used by {kind}.{seen_ids[bus.id]}",
                    source.value((kind, name, "id")),
                )
            seen_ids[bus.id] = name
            if kind == "uart" and chip.console_uart is not None and bus.id == chip.console_uart:
                yield warning(
                    f"uart.{name}.id: UART{bus.id} carries MicroPython's REPL console",
                    source.value(("uart", name, "id")),
                    "use UART1 or UART2 for the GPS",
                )
            for signal, allowed in table.get(bus.id, {}).items():
                pin = getattr(bus, signal)
                if pin is not None and pin.pin not in allowed:
                    yield error(
                        f"{kind}.{name}.{signal}: GPIO{pin.pin} cannot be {kind.upper()}{bus.id} {signal.upper()} "
                        f"on the {chip.name}",
                        source.value((kind, name, signal)),
                        f"{kind.upper()}{bus.id} {signal.upper()} is on GPIO {', '.join(map(str, sorted(allowed)))}",
                    )


def _bus_reference(
    name: Optional[str], kind: str, buses: dict, path: KeyPath, source: SourceMap
) -> Iterator[Diagnostic]:
    if name is None or name in buses:
        return
    close = difflib.get_close_matches(name, list(buses), n=1)
    yield error(
        f"{'.'.join(map(str, path))}: there is no {kind} bus named {name!r}",
        source.value(path),
        f"did you mean `{close[0]}`?" if close else (f"defined: {', '.join(buses)}" if buses else f"add {kind}:"),
    )


def _check_i2c_devices(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    devices = [("imu", board.imu, "MPU-6050")]
    if board.display is not None:
        devices.append(("display", board.display, board.display.model.upper()))
    if board.power.chip != "none":
        devices.append(("power", board.power, board.power.chip.upper()))
    taken: dict[tuple[str, int], str] = {}
    for key, device, label in devices:
        bus = device.bus
        if key == "power" and bus is None:
            yield error(f"power.bus: the {label} needs the I2C bus it sits on", source.key(("power", "chip")))
            continue
        yield from _bus_reference(bus, "i2c", board.i2c, (key, "bus"), source)
        where = source.value((key, "address"))
        address = device.address
        if address > 0x7F:
            yield error(
                f"{key}.address: {address:#04x} is an 8-bit address: I2C addresses here are 7-bit",
                where,
                f"{address:#04x} >> 1 = {address >> 1:#04x}"
                + (": the MPU-6050 is 0x68" if key == "imu" and address >> 1 in MPU6050_ADDRESSES else ""),
            )
            continue
        if address in RESERVED_I2C_ADDRESSES:
            yield error(f"{key}.address: {address:#04x} is reserved by the I2C specification", where)
        if key == "imu" and address not in MPU6050_ADDRESSES:
            yield error(
                f"imu.address: the MPU-6050 answers only at 0x68 (AD0 low) or 0x69 (AD0 high), not {address:#04x}",
                where,
            )
        other = taken.get((bus, address))
        if other is not None:
            yield error(f"{key}.address: {address:#04x} on bus {bus!r} is already taken by {other}", where)
        taken[(bus, address)] = key


def _wired_part_label(board: Board, key: str) -> str:
    if key == "power":
        return f"{board.power.chip.upper()} power chip" if board.power.chip != "none" else "power chip"
    if key == "display":
        return f"{board.display.model.upper()} display" if board.display is not None else "display"
    return {"imu": "MPU-6050", "gps": f"{board.gps.model.upper()} GPS"}[key]


def _check_wired(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    """A part the PCB wires to fixed pins stays on them: its bus must use exactly those pins."""
    wired = board.wired
    second_bus = "`i2c: {extra: {id: 1, sda: 13, scl: 14}}` with `imu: {bus: extra}`"
    for key in ("power", "display", "imu"):
        pins = getattr(wired, key)
        if pins is None:
            continue
        label = _wired_part_label(board, key)
        fixed = f"SDA {pins.sda.label} / SCL {pins.scl.label}"
        if key == "power" and board.power.chip == "none" or key == "display" and board.display is None:
            if key == "power":
                yield error(f"power.chip: none, but this board has its power chip soldered on I2C {fixed}",
                            source.value(("power", "chip")),
                            "the GPS and the sensors get their supply through it: keep the board's power: section")
            continue  # a display left out is only not driven
        device = getattr(board, key)
        bus = board.i2c.get(device.bus)
        if bus is None:
            continue  # an unknown bus name is reported by the I2C device check
        for signal in ("sda", "scl"):
            mine, theirs = getattr(bus, signal), getattr(pins, signal)
            if mine.pin == theirs.pin:
                continue
            yield error(
                f"i2c.{device.bus}.{signal}: {mine.label}, but this board's {label} ({key}.bus: {device.bus}) is "
                f"soldered to {fixed}",
                source.value(("i2c", device.bus, signal)),
                f"the board's own wiring does not move with the YAML; keep i2c.{device.bus} on {fixed} and put "
                f"a part you added on another bus, e.g. {second_bus}",
            )
            break
    pins = wired.gps
    uart = board.uart.get(board.gps.uart)
    if pins is not None and uart is not None:
        for signal in ("rx", "tx"):
            mine, theirs = getattr(uart, signal), getattr(pins, signal)
            if theirs is None or mine is None or mine.pin == theirs.pin:
                continue
            fixed = f"RX {pins.rx.label}" + (f" / TX {pins.tx.label}" if pins.tx is not None else "")
            yield error(
                f"uart.{board.gps.uart}.{signal}: {mine.label}, but this board's {_wired_part_label(board, 'gps')} "
                f"is soldered to {fixed}",
                source.value(("uart", board.gps.uart, signal)),
                f"the GPS on the board cannot be moved; keep uart.{board.gps.uart} on {fixed}",
            )


def _check_power(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    power = board.power
    known = PMU_RAILS.get(power.chip, {})
    for rail in power.rails:
        if rail not in known:
            close = difflib.get_close_matches(rail, list(known), n=1)
            yield error(
                f"power.rails.{rail}: the {power.chip} has no rail {rail!r}"
                if known
                else f"power.rails.{rail}: rails need a power chip (power.chip is none)",
                source.key(("power", "rails", rail)),
                f"did you mean `{close[0]}`?" if close else (f"rails: {', '.join(known)}" if known else None),
            )
    gps_power = board.gps.power
    if gps_power == "always_on":
        return
    where = source.value(("gps", "power"))
    if gps_power not in power.rails:
        yield error(
            f"gps.power: the GPS is powered from rail {gps_power!r}, which the board does not enable",
            where,
            f"add power.rails.{gps_power} with enable: true" if gps_power in known else "or write `always_on`",
        )
    elif not power.rails[gps_power].enable:
        yield error(
            f"gps.power: the GPS rail {gps_power!r} is switched off (power.rails.{gps_power}.enable: false)",
            source.value(("power", "rails", gps_power, "enable")),
            "the GPS would never get a fix",
        )


def _check_algorithm(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    algorithm, imu = board.algorithm, board.imu
    if algorithm.window % algorithm.block:
        divisors = [d for d in range(1, algorithm.window + 1) if algorithm.window % d == 0]
        nearest = min(divisors, key=lambda d: abs(d - algorithm.block))
        yield error(
            f"algorithm.block: b = {algorithm.block} does not divide n = {algorithm.window}",
            source.value(("algorithm", "block")),
            f"the nearest b that divides {algorithm.window} is {nearest}",
        )
    if algorithm.fused_median and algorithm.block > FUSED_MEDIAN_MAX:
        yield error(
            f"algorithm.block: b = {algorithm.block} is longer than the {FUSED_MEDIAN_MAX} samples the fused "
            "median option (fused_median: true) keeps",
            source.value(("algorithm", "block")),
            f"use b <= {FUSED_MEDIAN_MAX}, or fused_median: false",
        )
    for p in FUSED.params:  # a fused parameter declared at most another (codegen/kernel/layout.py)
        if p.at_most is None:
            continue
        key, other = FUSED.board_key(p), FUSED.param(p.at_most)
        value, limit = getattr(algorithm, key), getattr(algorithm, FUSED.board_key(other))
        if value > limit:
            why = p.at_most_why or "{value:g} {unit} is above {other} ({limit:g} {unit})"
            yield error(
                f"algorithm.{key}: " + why.format(value=value, limit=limit, unit=p.unit, other=FUSED.board_key(other)),
                source.value(("algorithm", key)),
                f"use {key} <= {FUSED.board_key(other)} (the defaults are {p.default:g} and {other.default:g})",
            )
    if algorithm.mode == "fused" and algorithm.fused_platform == "auto":
        # steps or a vehicle: the vehicle's shaking above fused_vibration_hz must reach the kernel (docs/fused.md)
        band = DLPF_BANDWIDTH_HZ.get(imu.dlpf, imu.gyro_output_rate_hz / 2)
        seen = min(band, imu.sample_rate_hz / 2)
        if seen < 2 * algorithm.fused_vibration_hz:
            limit = "imu.dlpf's" if band <= imu.sample_rate_hz / 2 else "imu.sample_rate_hz's"
            yield warning(
                f"algorithm.fused_platform: auto tells a vehicle from a walker by the shaking above "
                f"fused_vibration_hz ({algorithm.fused_vibration_hz:g} Hz), but the IMU passes only up to "
                f"{seen:g} Hz ({limit} limit): every shaken vehicle will look like a walker",
                source.value(("imu", "dlpf") if limit == "imu.dlpf's" else ("imu", "sample_rate_hz")),
                f"keep {2 * algorithm.fused_vibration_hz:g} Hz and more (imu.dlpf <= 4 at >= "
                f"{4 * algorithm.fused_vibration_hz:g} Hz sampling), or set fused_platform: pedestrian or vehicle",
            )
    if algorithm.mode == "eskf" and board.target == "micropython":
        yield from _check_eskf_heap(board, source)
    if algorithm.deadband_g >= imu.accel_range_g:
        yield error(
            f"algorithm.deadband_g: l = {algorithm.deadband_g} g is not below the accelerometer range "
            f"±{imu.accel_range_g} g",
            source.value(("algorithm", "deadband_g")),
        )
    rate_where = source.value(("imu", "sample_rate_hz"))
    if imu.sample_rate_hz > MPU6050_MAX_ACCEL_RATE_HZ:
        yield error(
            f"imu.sample_rate_hz: {imu.sample_rate_hz:g} Hz is above the MPU-6050's 1 kHz accelerometer rate",
            rate_where,
        )
    elif imu.sample_rate_hz < imu.gyro_output_rate_hz / 256:
        yield error(
            f"imu.sample_rate_hz: {imu.sample_rate_hz:g} Hz is below the slowest rate "
            f"({imu.gyro_output_rate_hz / 256:.2f} Hz, SMPLRT_DIV = 255)",
            rate_where,
        )
    else:
        achieved = imu.achieved_sample_rate_hz
        if abs(achieved - imu.sample_rate_hz) > 0.01 * imu.sample_rate_hz:
            yield warning(
                f"imu.sample_rate_hz: the MPU-6050 can run at {achieved:g} Hz, not {imu.sample_rate_hz:g} Hz",
                rate_where,
                f"its rates are {imu.gyro_output_rate_hz} Hz / (1 + SMPLRT_DIV)",
            )
    if board.logging.imu_rate_hz > imu.sample_rate_hz:
        yield error(
            f"logging.imu_rate_hz: {board.logging.imu_rate_hz:g} Hz is faster than the IMU samples "
            f"({imu.sample_rate_hz:g} Hz)",
            source.value(("logging", "imu_rate_hz")),
        )


def _check_eskf_heap(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    """An eskf board whose heap is smaller than the one the eskf app ran in (its calibration and log buffers counted
    as this board sizes them) is not known to run it."""
    buffers = 12 * board.calibration_samples + (2 * board.logging.block_bytes if board.logging.enabled else 0)
    floor = ESKF_MEASURED_OK_HEAP_BYTES - ESKF_MEASURED_BUFFERS_BYTES + buffers
    if board.heap_bytes >= floor:
        return
    written = ("micropython", "heap_kb") in source.values
    yield error(
        f"algorithm.mode: eskf does not fit in this board's {board.heap_bytes // 1024} KiB heap "
        f"({'micropython.heap_kb' if written else 'the ' + board.chip + ' firmware default'}): the eskf app with "
        f"{buffers} bytes of calibration and log buffers needs {floor / 1024:g} KiB (measured on the emulated "
        f"board: it ran in {ESKF_MEASURED_OK_HEAP_BYTES // 1024} KiB and failed in "
        f"{ESKF_FAILED_HEAP_BYTES // 1024} KiB with {ESKF_MEASURED_BUFFERS_BYTES} bytes of them)",
        source.value(("micropython", "heap_kb") if written else ("algorithm", "mode")),
        "use `mode: fused`, a shorter algorithm.calibration_s, smaller logging.block_bytes, or a board with more "
        "heap (PSRAM)",
    )


def _check_micropython_version(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    version = board.micropython.version
    if version_tuple(version) < MIN_MICROPYTHON:
        minimum = ".".join(map(str, MIN_MICROPYTHON))
        yield error(
            f"micropython.version: the app does not run on MicroPython {version}; it needs {minimum} or newer",
            source.value(("micropython", "version")),
            f"{minimum} is the first release that loads the native module `deadreckon build` makes (.mpy 6.3); "
            "on older ones `import dr_native` raises ValueError, which the app's fallback does not catch, and "
            "before 1.19 none of the app's .mpy files load. Flash a newer MicroPython and set this to its release",
        )


def _check_watchdog(board: Board, source: SourceMap) -> Iterator[Diagnostic]:
    limit = WATCHDOG_MAX_S.get(board.chip)
    if limit is not None and board.micropython.watchdog_s > limit:
        yield error(
            f"micropython.watchdog_s: {board.micropython.watchdog_s:g} s is longer than the {CHIPS[board.chip].name}'s "
            f"watchdog can count ({limit:g} s)",
            source.value(("micropython", "watchdog_s")),
            f"use watchdog_s <= {limit:g}",
        )


def check_board(board: Board, source: SourceMap, own_layout: Optional[FlashLayout] = None) -> list[Diagnostic]:
    """Every whole-board finding, errors and warnings; `own_layout` is the partition table the board names."""
    # a CircuitPython board's pin names stand for its own chip's GPIOs, whatever `chip:` says (that is checked)
    chip = CHIPS[find_board(board.circuitpython.board).chip if board.target == "circuitpython" else board.chip]
    found: list[Diagnostic] = []
    found += _check_pins(board, chip, source)
    found += _check_i2c_devices(board, source)
    found += _bus_reference(board.gps.uart, "uart", board.uart, ("gps", "uart"), source)
    found += _check_power(board, source)
    found += _check_wired(board, source)
    found += _check_algorithm(board, source)
    if board.target == "circuitpython":
        found += check_circuitpython(board, chip, source)
        return found
    if board.circuitpython is not None:
        found.append(warning("circuitpython: applies to `target: circuitpython` only; this board is generated for "
                             "MicroPython", source.key(("circuitpython",)),
                             "add `target: circuitpython`, or remove the section"))
    found += _check_fixed_muxing(board, chip, source)
    found += _check_micropython_version(board, source)
    found += check_flash_layout(board, source, own_layout)
    found += _check_watchdog(board, source)
    return found
