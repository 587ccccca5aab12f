"""Emulated CircuitPython `busio`: I2C and UART on the same simulated chips as mpsim's `machine`.

busio.I2C takes pins, not a bus id: it finds the world's bus wired to those pins (the scenario's "i2c_pins", or its
only bus) and talks to it through mpsim's machine.I2C, so every transaction costs the same bus time and meets the
same chips. As on the firmware, a transaction needs the lock (try_lock), pins are claimed until deinit(), and a
device that does not answer raises OSError.

busio.UART likewise finds the world's UART by its rx pin (the scenario's uart entry "rx", or its only UART) and
reads mpsim's machine.UART. With timeout > 0, read(n) waits up to the timeout for n bytes, as the firmware does;
with timeout 0 it returns what has arrived.
"""

import machine
import time

import firmware
import simworld

_S = simworld.scenario()


def _check_lock(bus):
    if not bus._locked:
        raise RuntimeError("Function requires lock")
    if bus._bus is None:
        raise ValueError("Object has been deinitialized and can no longer be used. Create a new object.")


class I2C:
    def __init__(self, scl, sda, *, frequency=100000, timeout=255):
        firmware.claim(scl, self)
        try:
            firmware.claim(sda, self)
        except ValueError:
            firmware.release(scl)
            raise
        self._pins = (scl, sda)
        self._locked = False
        self._frequency = frequency
        bus_id = self._world_bus(sda._gpio, scl._gpio)
        self._bus = machine.I2C(bus_id, scl=machine.Pin(scl._gpio), sda=machine.Pin(sda._gpio), freq=frequency)

    @staticmethod
    def _world_bus(sda, scl):
        wired = _S.get("i2c_pins", {})
        for bus_id, pins in wired.items():
            if pins == [sda, scl]:
                return int(bus_id)
        buses = sorted(_S.get("i2c", {}))
        return int(buses[0]) if len(buses) == 1 and not wired else -1  # -1: no chip hangs on these pins

    @property
    def frequency(self):
        return self._frequency

    def try_lock(self):
        if self._locked:
            return False
        self._locked = True
        return True

    def unlock(self):
        self._locked = False

    def deinit(self):
        for pin in self._pins:
            firmware.release(pin)
        self._bus = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.deinit()

    def scan(self):
        _check_lock(self)
        return self._bus.scan()

    def probe(self, address):
        _check_lock(self)
        return address in self._bus.scan()

    def writeto(self, address, buffer, *, start=0, end=None):
        _check_lock(self)
        end = len(buffer) if end is None else end
        self._bus.writeto(address, memoryview(buffer)[start:end])

    def readfrom_into(self, address, buffer, *, start=0, end=None):
        _check_lock(self)
        end = len(buffer) if end is None else end
        self._bus.readfrom_into(address, memoryview(buffer)[start:end])

    def writeto_then_readfrom(self, address, out_buffer, in_buffer, *, out_start=0, out_end=None, in_start=0,
                              in_end=None):
        _check_lock(self)
        out_end = len(out_buffer) if out_end is None else out_end
        in_end = len(in_buffer) if in_end is None else in_end
        target = memoryview(in_buffer)[in_start:in_end]
        if out_end - out_start == 1:  # a register address, then a repeated start and the read
            self._bus.readfrom_mem_into(address, out_buffer[out_start], target)
        else:
            self._bus.writeto(address, memoryview(out_buffer)[out_start:out_end], False)
            self._bus.readfrom_into(address, target)


class UART:
    class Parity:
        ODD = 1
        EVEN = 2

    def __init__(self, tx=None, rx=None, *, rts=None, cts=None, rs485_dir=None, rs485_invert=False,
                 baudrate=9600, bits=8, parity=None, stop=1, timeout=1, receiver_buffer_size=64):
        if timeout > 100:
            raise ValueError("timeout must be 0.0-100.0 seconds")
        for pin in (tx, rx):
            if pin is not None:
                firmware.claim(pin, self)
        self._pins = (tx, rx)
        self.baudrate = baudrate
        self.timeout = timeout
        uarts = _S.get("uart", {})
        uart_id = None
        for key, opts in uarts.items():
            if rx is not None and opts.get("rx") == rx._gpio:
                uart_id = int(key)
        if uart_id is None:
            uart_id = int(sorted(uarts)[0]) if len(uarts) == 1 and "rx" not in uarts[sorted(uarts)[0]] else -1
        self._uart = machine.UART(uart_id, baudrate=baudrate, rxbuf=receiver_buffer_size)

    def deinit(self):
        for pin in self._pins:
            firmware.release(pin)
        self._uart = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.deinit()

    @property
    def in_waiting(self):
        return self._uart.any()

    def _wait_for(self, n):
        """Wait up to the timeout for n bytes (the firmware waits for the first byte and between bytes)."""
        deadline = time.now() + int(self.timeout * 1000000)
        while self._uart.any() < n and time.now() < deadline:
            time.advance(1000)

    def read(self, nbytes=None):
        if nbytes is None:
            self._wait_for(1)
            return self._uart.read()
        self._wait_for(nbytes)
        return self._uart.read(nbytes)

    def readinto(self, buf):
        self._wait_for(len(buf))
        return self._uart.readinto(buf)

    def readline(self):
        self._wait_for(1)
        return self._uart.readline()

    def write(self, buf):
        return self._uart.write(buf)

    def reset_input_buffer(self):
        while self._uart.any():
            self._uart.read()
