"""An emulated `machine` module for running the generated app on the unix-port MicroPython.

Put this folder (codegen/sim/mpsim) first on MICROPYPATH: `machine` and `time` here replace the unix port's own. The peripherals
(see simworld.py) come from the scenario named by MPSIM_SCENARIO.
"""

import errno
import time

import simworld

simworld.load()
_S = simworld.scenario()

_pins = {}


def freq(hz=None):
    return 240000000


def unique_id():
    return b"\x24\x0a\xc4\x00\x00\x01"


def reset():
    simworld.trace("reset", cause="machine.reset")
    time.reset_cause = SOFT_RESET
    raise time.signal_reset("machine.reset")


def soft_reset():
    reset()


def idle():
    time.advance(100)


def lightsleep(ms=0):
    time.advance(ms * 1000)


def reset_cause():
    return time.reset_cause


PWRON_RESET = 1
HARD_RESET = 2
WDT_RESET = 3
DEEPSLEEP_RESET = 4
SOFT_RESET = 5


class Pin:
    IN = 1
    OUT = 3
    OPEN_DRAIN = 7
    PULL_UP = 2
    PULL_DOWN = 1
    IRQ_FALLING = 2
    IRQ_RISING = 1

    def __init__(self, id, mode=-1, pull=-1, value=None):
        self.id = id
        self.mode = mode
        self.pull = pull
        self.level = 0
        self.events = [(int(t * 1000000), v) for t, v in _S.get("pins", {}).get(str(id), [])]
        _pins[id] = self
        if value is not None:
            self.value(value)

    def init(self, mode=-1, pull=-1, value=None):
        if mode != -1:
            self.mode = mode
        if pull != -1:
            self.pull = pull
        if value is not None:
            self.value(value)

    def value(self, v=None):
        if v is None:
            if self.mode == Pin.OUT:
                return self.level
            level = 1 if self.pull == Pin.PULL_UP else 0
            if self.events:
                now = time.now()
                for t, lv in self.events:
                    if t <= now:
                        level = lv
                    else:
                        break
            return level
        v = 1 if v else 0
        if v != self.level or self.mode != Pin.OUT:
            simworld.trace("pin", pin=self.id, v=v)
        self.level = v

    __call__ = value

    def on(self):
        self.value(1)

    def off(self):
        self.value(0)

    def irq(self, handler=None, trigger=3):
        return None


class I2C:
    """Hardware I2C: each transaction costs its bus time (9 bits per byte at the configured frequency)."""

    def __init__(self, id=0, scl=None, sda=None, freq=400000, timeout=50000):
        self.id = id
        self.freq = freq
        self.devices = {}
        wired = _S.get("i2c_pins", {}).get(str(id))  # [sda, scl] the world's devices hang on, when it says
        if wired and [getattr(sda, "id", sda), getattr(scl, "id", scl)] != wired:
            return  # a bus opened on other pins: nothing answers there
        for opts in _S.get("i2c", {}).get(str(id), []):
            self.devices[opts["address"]] = simworld.device(id, opts)
        self.transactions = 0

    def _dev(self, addr, nbytes):
        time.advance(20 + (nbytes + 2) * 9 * 1000000 // self.freq)
        self.transactions += 1
        dev = self.devices.get(addr)
        if dev is None or getattr(dev, "nack", False):
            raise OSError(errno.ENODEV)
        now = time.now()
        if getattr(dev, "nack_after_us", 1 << 62) <= now < getattr(dev, "nack_until_us", 1 << 62):
            raise OSError(errno.ENODEV)  # unplugged (or a loose contact) mid-run
        hang = getattr(dev, "hang_at_us", -1)
        if 0 <= hang <= now:  # the bus hangs (a slave holding SCL low) once, for hang_us
            dev.hang_at_us = -1
            simworld.trace("i2c_hang", address=addr)
            time.advance(dev.hang_us)
        return dev

    def scan(self):
        time.advance(5000)
        return sorted(a for a, d in self.devices.items() if not getattr(d, "nack", False))

    def writeto(self, addr, buf, stop=True):
        self._dev(addr, len(buf)).write(bytes(buf))
        return len(buf)

    def writevto(self, addr, vector, stop=True):
        data = b"".join(bytes(v) for v in vector)
        self._dev(addr, len(data)).write(data)
        return len(data)

    def readfrom(self, addr, n, stop=True):
        return self._dev(addr, n).read(getattr(self.devices[addr], "ptr", 0), n)

    def readfrom_into(self, addr, buf, stop=True):
        buf[:] = self.readfrom(addr, len(buf))

    def writeto_mem(self, addr, mem, buf, addrsize=8):
        self._dev(addr, len(buf) + 1).write(bytes([mem]) + bytes(buf))

    def readfrom_mem(self, addr, mem, n, addrsize=8):
        return self._dev(addr, n + 1).read(mem, n)

    def readfrom_mem_into(self, addr, mem, buf, addrsize=8):
        data = self._dev(addr, len(buf) + 1).read(mem, len(buf))
        for i in range(len(buf)):
            buf[i] = data[i]


SoftI2C = I2C


class UART:
    """A UART receiving a GPS stream; bytes beyond the receive buffer are lost (and counted in the trace)."""

    def __init__(self, id, baudrate=9600, bits=8, parity=None, stop=1, tx=None, rx=None, rxbuf=256, **kw):
        self.id = id
        self.baud = baudrate
        self.rxbuf = max(rxbuf, 32)
        self.buf = bytearray()
        self.lost = 0
        self.stream = simworld.uart_stream(id, baudrate)
        self.written = bytearray()

    def init(self, baudrate=9600, **kw):
        self.baud = baudrate

    def _fill(self):
        data, lost = self.stream.pull(time.now(), self.rxbuf - len(self.buf))
        self.buf += data
        if lost:
            self.lost += lost
            simworld.trace("uart_overflow", uart=self.id, lost=lost)

    def any(self):
        time.advance(5)
        self._fill()
        return len(self.buf)

    def read(self, n=-1):
        self._fill()
        if not self.buf:
            return None
        if n is None or n < 0:
            n = len(self.buf)
        out = bytes(self.buf[:n])
        self.buf = self.buf[n:]
        time.advance(5 + len(out) // 8)
        return out

    def readinto(self, buf, n=-1):
        data = self.read(len(buf) if n < 0 else n)
        if not data:
            return None
        buf[: len(data)] = data
        return len(data)

    def readline(self):
        self._fill()
        i = self.buf.find(b"\n")
        if i < 0:
            return self.read()
        return self.read(i + 1)

    def write(self, buf):
        self.written += buf
        simworld.trace("uart_write", uart=self.id, data=bytes(buf).decode())
        return len(buf)


class Timer:
    """machine.Timer: periodic or one-shot callbacks on virtual time, run as the clock passes their time (the
    board's soft timers run between bytecodes). The scenario's "timers": false makes a board without timers."""

    ONE_SHOT = 0
    PERIODIC = 1

    def __init__(self, id=-1, **kw):
        if not _S.get("timers", True):
            raise ValueError("no timer on this board")
        self.id = id
        if kw:
            self.init(**kw)

    def init(self, mode=PERIODIC, period=-1, callback=None, freq=None):
        if freq is not None:
            period = 1000 // freq
        if period <= 0 or callback is None:
            raise ValueError("period and callback are needed")
        simworld.trace("timer", period_ms=period)
        if mode == Timer.ONE_SHOT:
            def once(t, callback=callback):
                time.remove_timer(t)
                callback(t)
            time.add_timer(period * 1000, once, self)
        else:
            time.add_timer(period * 1000, callback, self)

    def deinit(self):
        time.remove_timer(self)


class WDT:
    """The watchdog: not fed for `timeout` ms of virtual time, the board resets (time.Reset)."""

    def __init__(self, id=0, timeout=5000):
        simworld.trace("wdt", timeout_ms=timeout)
        time.arm_watchdog(timeout * 1000)

    def feed(self):
        time.feed_watchdog()


_rtc_memory = b""  # the RTC's user memory: a reset leaves it (this module outlives the app's), a power-on clears it
RTC_MEMORY_MAX = 2048  # bytes, the ESP32 port's MICROPY_HW_RTC_USER_MEM_MAX


class RTC:
    """The RTC, for its user memory only (the ESP32's RTC slow memory, which survives the watchdog's and
    machine.reset()'s resets): memory() reads it back, memory(data) stores at most RTC_MEMORY_MAX bytes; OSError
    where the scenario says the port has none."""

    def memory(self, data=None):
        global _rtc_memory
        if not _S.get("rtc_memory", True):  # a port without it (the scenario's "rtc_memory": false)
            raise OSError(errno.ENODEV)
        if data is None:
            return _rtc_memory
        if len(data) > RTC_MEMORY_MAX:
            raise ValueError("buffer too long")
        _rtc_memory = bytes(data)
        simworld.trace("rtc_memory", length=len(data), data=_rtc_memory.hex())
