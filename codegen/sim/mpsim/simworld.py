"""The emulated world behind mpsim/machine.py: scenario, trace and peripheral models.

The scenario is a JSON file named by the MPSIM_SCENARIO environment variable (written by the test on the host):

    duration_s        how long the run lasts in virtual time (the clock then ends it)
    ticks_start_us    initial ticks_us() value (put it just below 2**30 to cross the wrap)
    trace             host path of the JSON-lines trace this world writes (screens, LED, PMU writes, ...)
    i2c               {"<bus id>": [device, ...]}; a device is {"kind": "mpu6050"|"ssd1306"|"sh1106"|"axp192"|
                      "axp2101", "address": int, ...kind options}
    uart              {"<uart id>": {"stream": host path of "t_us<TAB>sentence" lines, "power": rail or null}}
    pins              {"<gpio>": [[t_s, level], ...]} level changes of input pins (buttons)
    fs                {"mount": "/logs", "bytes": int, "block": int, "dump": host dir} a LittleFS RAM disk
    epoch_s           time.time() at the start

Every model answers on the bus the way the chip does; none of them knows anything about the app.
"""

import json
import os
import struct
import time

_scenario = {}
_trace = None
_finishers = []


def scenario():
    return _scenario


def trace(event, **fields):
    if _trace is None:
        return
    fields["t_us"] = time.now()
    fields["ev"] = event
    _trace.write(json.dumps(fields))
    _trace.write("\n")


def at_end(fn):
    _finishers.append(fn)


def _finish():
    global _ballast
    _ballast = None  # the app is done: the finalisers may use its heap
    for fn in _finishers:
        try:
            fn()
        except Exception as e:  # a broken finaliser must not hide the others
            trace("finish_error", error=repr(e))
    trace("end")
    if _trace is not None:
        _trace.flush()


_loaded = False


def load(hold_heap=False):
    """Load the scenario named by MPSIM_SCENARIO (once: machine.py calls it at import). With hold_heap the heap
    stays whole until leave_heap() (a firmware loads its own modules first: codegen/sim/cpsim/launch.py)."""
    global _scenario, _trace, _loaded
    if _loaded:
        return
    _loaded = True
    path = os.getenv("MPSIM_SCENARIO")
    if not path:
        raise RuntimeError("MPSIM_SCENARIO is not set")
    with open(path) as f:
        _scenario = json.load(f)
    if _scenario.get("trace"):
        _trace = open(_scenario["trace"], "w")
    duration = _scenario.get("duration_s", 10)
    time._configure(_scenario.get("ticks_start_us", 0), int(duration * 1000000), _scenario.get("epoch_s", 0), _finish)
    fs = _scenario.get("fs")
    if fs:
        _mount_disk(fs)
    for bus, devices in _scenario.get("i2c", {}).items():  # the chips, and their models' data, before the app
        for opts in devices:
            device(int(bus), opts)
    if not hold_heap:
        leave_heap()


def leave_heap():
    """Give the app the board's heap (the scenario's heap_bytes), no more."""
    heap = _scenario.get("heap_bytes")
    if heap:
        _leave_heap(heap)


_ballast = None


def _leave_heap(free_bytes):
    """Take the heap beyond `free_bytes` away from the app: the emulated board's own modules and buffers stay
    outside the figure the board's firmware gives (the process runs with a heap a little larger than it)."""
    global _ballast
    import gc

    gc.collect()
    extra = gc.mem_free() - free_bytes
    if extra < 0:
        raise RuntimeError("the heap is %d bytes short of the board's %d" % (-extra, free_bytes))
    if extra > 64:
        _ballast = bytearray(extra - 64)  # its own header and the allocation unit round it
        gc.collect()


# ---------------------------------------------------------------- rails (power gating of the GPS)

_rails = {}  # rail name -> on?


def rail_on(name):
    if name is None:
        return True
    return _rails.get(name, False)


def set_rail(name, on):
    if _rails.get(name) != on:
        _rails[name] = on
        trace("rail", rail=name, on=on)


# ---------------------------------------------------------------- filesystem


class FileDisk:
    """A block device the size of the board's partition (or smaller), kept in a host file so that it takes no
    room in the MicroPython heap the app runs in. LittleFS reads and programs through it (extended block device
    interface: offsets within a block, erase by ioctl 6)."""

    def __init__(self, path, block, count, fresh):
        self.block = block
        self.count = count
        self.file = open(path, "w+b" if fresh else "r+b")
        if fresh:
            chunk = bytearray(block)
            for _ in range(count):
                self.file.write(chunk)
            self.file.flush()
        self.flash = (_scenario.get("clock") or {}).get("flash")  # the chip's times (the CPU waits), or none
        self.erases = 0
        self.programmed = 0

    def readblocks(self, n, buf, off=0):
        self.file.seek(n * self.block + off)
        self.file.readinto(buf)
        if self.flash:
            time.advance(len(buf) * self.flash["read_us_per_byte"])

    def writeblocks(self, n, buf, off=0):
        if time.halted:  # the board is resetting: the old code's writes never reach the flash
            return
        if 0 <= _write_error_us <= time.now():
            raise OSError(5)  # EIO: the flash stopped taking writes (fs.write_error_after_s)
        self.file.seek(n * self.block + off)
        if 0 <= _power_cut_us <= time.now():
            self.file.write(memoryview(buf)[: len(buf) // 2])  # the page program is cut half way
            self.file.flush()
            trace("power_cut", block=n, offset=off, bytes=len(buf))
            power_cut()
        self.file.write(buf)
        self.file.flush()
        self.programmed += len(buf)
        if self.flash:
            page = self.flash["page_bytes"]
            time.advance((len(buf) + page - 1) // page * self.flash["page_program_us"])
        if off == 0 and len(buf) == self.block:  # the basic interface: erase and program a whole block
            self._erase()

    def ioctl(self, op, arg):
        if op == 4:
            return self.count
        if op == 5:
            return self.block
        if op == 6:
            self._erase()
        return 0

    def _erase(self):
        if time.halted:
            return
        self.erases += 1
        if self.flash:
            # per 4 KiB sector; FAT's 512-byte sectors go through the firmware's sector cache, an erase per eight
            time.advance(self.flash["sector_erase_us"] * self.block / 4096)




_filesystem = None  # (block device, mount point) of the board's filesystem, for firmwares that remount it (cpsim)


def filesystem():
    return _filesystem


def filesystem_class():
    """The board's filesystem: LittleFS as MicroPython's ESP32 and RP2040 ports format it, or FAT (fs.format "fat")
    as CircuitPython's CIRCUITPY drive is, the only one CircuitPython has."""
    return os.VfsFat if _scenario["fs"].get("format") == "fat" else os.VfsLfs2


def _mount_disk(fs):
    """The board's log partition: a fresh LittleFS (or FAT), optionally partly taken by a file that is not the app's
    (fs.prefill_bytes: a nearly full filesystem). At the end of the run the files are copied out as the flash holds
    them: through a second, fresh mount of the image, so whatever the app had not written and flushed is gone, as
    after a power cut."""
    global _power_cut_us, _write_error_us, _filesystem
    block = fs.get("block", 4096)
    count = fs["bytes"] // block
    disk = FileDisk(fs["image"], block, count, fresh=True)
    if fs.get("power_cut_s") is not None:
        _power_cut_us = int(fs["power_cut_s"] * 1000000)
    if fs.get("write_error_after_s") is not None:
        _write_error_us = int(fs["write_error_after_s"] * 1000000)
    filesystem_class().mkfs(disk)
    mount = fs.get("mount", "/logs")
    os.mount(filesystem_class()(disk), mount)
    _filesystem = (disk, mount)
    if fs.get("prefill_bytes"):  # the flash as the board finds it at power-on: writing it takes none of the run's time
        flash, disk.flash = disk.flash, None
        chunk = bytearray(block)
        with open("/" + mount.strip("/") + "/user.dat", "wb") as f:
            for _ in range(fs["prefill_bytes"] // block):
                f.write(chunk)
        disk.flash = flash
    dump = fs.get("dump")
    if dump:

        def copy_out():
            flash = FileDisk(fs["image"], block, count, fresh=False)
            os.mount(filesystem_class()(flash), "/flash")
            buf = bytearray(512)
            names = sorted(os.listdir("/flash"))
            for name in names:
                with open("/flash/" + name, "rb") as src:
                    with open(dump + "/" + name, "wb") as dst:
                        while True:
                            n = src.readinto(buf)
                            if not n:
                                break
                            dst.write(buf if n == len(buf) else buf[:n])
            st = os.statvfs("/flash")
            trace("fs", files=names, free=st[0] * st[3], total=st[0] * st[2], erases=disk.erases,
                  programmed=disk.programmed)

        at_end(copy_out)


_power_cut_us = -1  # fs.power_cut_s: the first block write from then on is cut half way and the run ends
_write_error_us = -1  # fs.write_error_after_s: block writes fail from then on


def power_cut():
    """The supply is gone: nothing more reaches the flash; the world's end (copy-out, trace) runs."""
    _finish()
    raise SystemExit(4)


# ---------------------------------------------------------------- I2C devices


class Mpu6050:
    """Register model of the MPU-6050 answering from a count stream.

    Options: who_am_i (0x68; clones answer 0x70, 0x72, 0x98...), counts (host path of little-endian int16
    records ax ay az gx gy gz), rate_hz (the stream's sample rate), accel_range_g / gyro_range_dps (the range the
    stream's counts are in; the model rescales to the range the app configures and saturates like the chip).
    Samples come every 1/(gyro_rate/(1+SMPLRT_DIV)) s of virtual time after the app wakes the chip, each the
    stream's record for its moment of the run (the stream starts with the run: a chip woken again after the board's
    reset goes on with the motion, it does not play it from the start).
    """

    FIFO_BYTES = 1024

    def __init__(self, opts):
        self.regs = bytearray(128)
        self.who = opts.get("who_am_i", 0x68)
        self.reset()
        path = opts.get("counts")
        self.counts = open(path, "rb") if path else None  # read a record at a time: nothing of it in the heap
        self.nsamples = self.counts.seek(0, 2) // 12 if path else 0
        self.rec = bytearray(12)
        self.stream_rate = opts.get("rate_hz", 200.0)
        self.stream_ag = opts.get("accel_range_g", 2)
        self.stream_gd = opts.get("gyro_range_dps", 250)
        self.temp = opts.get("temp_counts", -3920)  # 25 C
        self.k = 0  # index of the next sample the chip produces since it woke
        self.t0 = None  # virtual us when sampling started
        self.k0 = 0  # the chip's samples the run had made before it woke (at the rate it woke to)
        self.latest = (0, 0, 0, 0, 0, 0)
        self.fifo = bytearray()
        self.samples_made = 0

    def reset(self):
        for i in range(len(self.regs)):
            self.regs[i] = 0
        self.regs[0x6B] = 0x40  # asleep after power-up
        self.regs[0x75] = self.who
        self.t0 = None
        self.fifo = bytearray()

    def _rate(self):
        """(base Hz, divider): the chip samples at base / divider (integers: the clock's arithmetic stays exact on
        an interpreter with 30-bit floats, where 1 / 100.0 * 100.0 is 0.99999994)."""
        return (8000 if (self.regs[0x1A] & 7) in (0, 7) else 1000), 1 + self.regs[0x19]

    def _sample(self, k, base, div):
        """The recording's record for the chip's k-th sample (at base / div Hz; the recording at stream_rate)."""
        if self.nsamples == 0:
            return (0, 0, 0, 0, 0, 0)
        ratio = self.stream_rate * div / base
        i = k if abs(ratio - 1.0) < 1e-6 else int(k * ratio + 1e-3)
        if i >= self.nsamples:
            i = self.nsamples - 1
        self.counts.seek(12 * i)
        self.counts.readinto(self.rec)
        raw = struct.unpack_from("<6h", self.rec, 0)
        ag = (2, 4, 8, 16)[(self.regs[0x1C] >> 3) & 3]
        gd = (250, 500, 1000, 2000)[(self.regs[0x1B] >> 3) & 3]
        out = []
        for j in range(6):
            v = raw[j] * (self.stream_ag / ag if j < 3 else self.stream_gd / gd)
            v = int(v + 0.5) if v >= 0 else -int(-v + 0.5)
            out.append(-32768 if v < -32768 else 32767 if v > 32767 else v)
        return out

    def _catch_up(self):
        if self.regs[0x6B] & 0x40:
            return
        now = time.now()
        base, div = self._rate()
        if self.t0 is None:
            self.t0 = now
            self.k = 0
            self.k0 = now * base // (1000000 * div)
        due = (now - self.t0) * base // (1000000 * div) + 1  # samples produced so far
        if due - self.k > 2000:  # long stall: skip ahead, the chip keeps only the newest
            self.k = due - 2000
        fifo_on = self.regs[0x6A] & 0x40
        fifo_sel = self.regs[0x23]
        while self.k < due:
            self.latest = self._sample(self.k0 + self.k, base, div)
            self.k += 1
            self.samples_made += 1
            self.regs[0x3A] |= 0x01
            if fifo_on and fifo_sel:
                rec = b""
                if fifo_sel & 0x08:
                    rec += struct.pack(">3h", *self.latest[:3])
                if fifo_sel & 0x80:
                    rec += struct.pack(">h", self.temp)
                for bit, j in ((0x40, 3), (0x20, 4), (0x10, 5)):
                    if fifo_sel & bit:
                        rec += struct.pack(">h", self.latest[j])
                self.fifo += rec
                if len(self.fifo) > self.FIFO_BYTES:
                    self.fifo = self.fifo[len(self.fifo) - self.FIFO_BYTES :]
                    self.regs[0x3A] |= 0x10
        a = self.latest
        struct.pack_into(">7h", self.regs, 0x3B, a[0], a[1], a[2], self.temp, a[3], a[4], a[5])
        struct.pack_into(">H", self.regs, 0x72, len(self.fifo))

    def write(self, data):
        if not data:
            return
        reg = data[0]
        for b in data[1:]:
            self._write_reg(reg, b)
            reg += 1
        self.ptr = data[0]

    def _write_reg(self, reg, b):
        if reg == 0x6B:
            if b & 0x80:
                trace("mpu_reset")
                self.reset()
                return
            was_asleep = self.regs[0x6B] & 0x40
            self.regs[0x6B] = b
            if was_asleep and not b & 0x40:
                self.t0 = None
                trace("mpu_wake")
            return
        if reg == 0x6A and b & 0x04:
            self.fifo = bytearray()
            b &= ~0x04
        if reg == 0x6A and (b ^ self.regs[0x6A]) & 0x40:
            trace("mpu_fifo", on=bool(b & 0x40))
        if reg in (0x75, 0x3A) or 0x3B <= reg <= 0x48:
            return  # read-only
        self.regs[reg] = b
        if reg in (0x19, 0x1A, 0x1B, 0x1C):
            trace("mpu_config", reg=reg, val=b)

    def read(self, reg, n):
        self._catch_up()
        out = bytearray(n)
        for i in range(n):
            if reg == 0x74:
                if self.fifo:
                    out[i] = self.fifo[0]
                    self.fifo = self.fifo[1:]
                continue
            out[i] = self.regs[reg & 0x7F]
            if reg == 0x3A:
                self.regs[0x3A] = 0  # INT_STATUS clears on read
            reg += 1
        if reg >= 0x72:
            struct.pack_into(">H", self.regs, 0x72, len(self.fifo))
        return bytes(out)


class Oled:
    """SSD1306 / SSD1315 / SH1106 command interpreter with display RAM; decodes the shown text.

    Text is decoded cell by cell (8x8 on the page grid) against MicroPython's own framebuf font, so what the test
    reads is what the pixels say. The text is captured after every data write (a page at a time, as shown).
    """

    def __init__(self, opts):
        self.kind = opts["kind"]
        self.width = opts.get("width", 128)
        self.height = opts.get("height", 64)
        self.ram_w = 132 if self.kind == "sh1106" else 128
        self.offset = 2 if self.kind == "sh1106" and self.width == 128 else 0
        if self.kind != "sh1106":
            self.offset = (128 - self.width) // 2 if self.width < 128 else 0
        self.pages = self.height // 8
        self.ram = bytearray(self.ram_w * 8)
        self.on = False
        self.mode = 2  # page addressing after reset
        self.col0, self.col1, self.page0, self.page1 = 0, 127, 0, 7
        self.col, self.page = 0, 0
        self.pending = []
        self.last_text = None
        self.frames = 0
        self.glyphs = _glyphs()

    def write(self, data):
        if not data:
            return
        ctrl = data[0]
        if ctrl & 0x40:
            self._data(data[1:])
        else:
            for b in data[1:]:
                self._cmd(b)

    def read(self, reg, n):
        return bytes(n)

    def _cmd(self, b):
        if self.pending:
            self.pending[1].append(b)
            if len(self.pending[1]) == self.pending[0]:
                op, args = self.pending[2], self.pending[1]
                self.pending = []
                self._cmd_args(op, args)
            return
        nargs = {0x20: 1, 0x21: 2, 0x22: 2, 0x81: 1, 0xA8: 1, 0xD3: 1, 0xDA: 1, 0xD5: 1, 0xD9: 1, 0xDB: 1, 0x8D: 1,
                 0xAD: 1}
        if b in nargs:
            self.pending = [nargs[b], [], b]
        elif b == 0xAE or b == 0xAF:
            self.on = b == 0xAF
            trace("oled_power", on=self.on)
        elif 0xB0 <= b <= 0xB7:
            self.page = b & 7
        elif b <= 0x0F:
            self.col = (self.col & 0xF0) | b
        elif 0x10 <= b <= 0x1F:
            self.col = (self.col & 0x0F) | ((b & 0x0F) << 4)

    def _cmd_args(self, op, args):
        if op == 0x20:
            self.mode = args[0] & 3
        elif op == 0x21:
            self.col0, self.col1 = args[0], args[1]
            self.col = self.col0
        elif op == 0x22:
            self.page0, self.page1 = args[0] & 7, args[1] & 7
            self.page = self.page0

    def _data(self, data):
        for b in data:
            if self.col < self.ram_w:
                self.ram[self.page * self.ram_w + self.col] = b
            if self.mode == 0 and self.kind != "sh1106":
                if self.col >= self.col1:
                    self.col = self.col0
                    self.page = self.page0 if self.page >= self.page1 else self.page + 1
                else:
                    self.col += 1
            else:
                self.col += 1
        self._capture()

    def text(self):
        lines = []
        for p in range(self.pages):
            row = []
            base = p * self.ram_w + self.offset
            for c in range(self.width // 8):
                cell = bytes(self.ram[base + 8 * c : base + 8 * c + 8])
                row.append(self.glyphs.get(cell, "#"))
            lines.append("".join(row).rstrip())
        return lines

    def _capture(self):
        self.frames += 1
        text = self.text()
        if text != self.last_text:
            self.last_text = text
            trace("screen", lines=text, on=self.on)


def _glyphs():
    """The 8x8 cells the display's text is read back with: the scenario's "display_font" when the app draws with a
    font of its own ({"first": code, "cell": 8, "data": hex of 8 column bytes a glyph}: the CircuitPython app's,
    codegen/font.py), else MicroPython's framebuf font."""
    font = _scenario.get("display_font")
    if font:
        data = bytes.fromhex(font["data"])
        cell = font["cell"]
        table = {}
        for i in range(len(data) // cell):
            table.setdefault(data[i * cell : (i + 1) * cell], chr(font["first"] + i))
        return table
    import framebuf

    table = {}
    buf = bytearray(8)
    fb = framebuf.FrameBuffer(buf, 8, 8, framebuf.MONO_VLSB)
    for code in range(32, 127):
        fb.fill(0)
        fb.text(chr(code), 0, 0, 1)
        table.setdefault(bytes(buf), chr(code))
    return table


class Axp:
    """AXP192 / AXP2101 power chip: register file, chip id at 0x03, records writes, gates rails."""

    # rail -> (enable register, bit)
    RAILS = {
        "axp192": {"dcdc1": (0x12, 0), "dcdc3": (0x12, 1), "ldo2": (0x12, 2), "ldo3": (0x12, 3), "dcdc2": (0x12, 4),
                   "exten": (0x12, 6)},
        "axp2101": {"aldo1": (0x90, 0), "aldo2": (0x90, 1), "aldo3": (0x90, 2), "aldo4": (0x90, 3),
                    "bldo1": (0x90, 4), "bldo2": (0x90, 5), "dldo1": (0x90, 7)},
    }

    def __init__(self, opts):
        self.kind = opts["kind"]
        self.regs = bytearray(256)
        self.regs[0x03] = 0x03 if self.kind == "axp192" else 0x4A
        if self.kind == "axp192":
            self.regs[0x12] = 0x01  # DCDC1 (ESP32 supply) on after power-up; LDO3 off
        else:
            self.regs[0x80] = 0x01
            self.regs[0x90] = 0x00
        self.ptr = 0
        self._update()

    def write(self, data):
        if not data:
            return
        reg = data[0]
        for b in data[1:]:
            self.regs[reg] = b
            trace("pmu_write", chip=self.kind, reg=reg, val=b)
            reg += 1
        self._update()

    def read(self, reg, n):
        return bytes(self.regs[reg : reg + n])

    def _update(self):
        for name, (reg, bit) in self.RAILS[self.kind].items():
            set_rail(name, bool(self.regs[reg] >> bit & 1))


class Nacker:
    """A device that holds the address but never acknowledges (a broken or unpowered chip)."""

    nack = True


KINDS = {"mpu6050": Mpu6050, "ssd1306": Oled, "ssd1315": Oled, "sh1106": Oled, "axp192": Axp, "axp2101": Axp}


def make_device(opts):
    """A device model from its scenario entry, with its faults: nack (never answers), nack_after_s/nack_until_s
    (stops answering, and answers again), hang_at_s/hang_s (holds the bus once)."""
    if opts.get("nack"):
        return Nacker()
    dev = KINDS[opts["kind"]](opts)
    if "nack_after_s" in opts:
        dev.nack_after_us = int(opts["nack_after_s"] * 1000000)
    if "nack_until_s" in opts:
        dev.nack_until_us = int(opts["nack_until_s"] * 1000000)
    if "hang_at_s" in opts:
        dev.hang_at_us = int(opts["hang_at_s"] * 1000000)
        dev.hang_us = int(opts.get("hang_s", 10.0) * 1000000)
    return dev


_devices = {}  # (bus, address) -> model: the chips keep their state when the board resets
_streams = {}  # uart id -> NmeaStream


def device(bus, opts):
    key = (bus, opts["address"])
    if key not in _devices:
        _devices[key] = make_device(opts)
    return _devices[key]


def uart_stream(uart_id, baud):
    if uart_id not in _streams:
        opts = _scenario.get("uart", {}).get(str(uart_id), {})
        _streams[uart_id] = NmeaStream(opts, baud)
    return _streams[uart_id]


# ---------------------------------------------------------------- UART streams


class NmeaStream:
    """Bytes of a GPS receiver: chunks "t_us<TAB>text" delivered at the line rate, only while the rail is on.
    The stream file is read a chunk at a time (it stays out of the heap the app runs in)."""

    def __init__(self, opts, baud):
        path = opts.get("stream")
        self.file = open(path, "rb") if path else None
        self.chunk = None  # (t_us, data) of the chunk being delivered
        self.power = opts.get("power")
        self.sent = 0  # bytes of the chunk already delivered
        self.us_per_byte = 10 * 1000000 / baud
        self.lost_unpowered = 0
        silent = opts.get("silent", [])  # [start s, end s]: the receiver says nothing (a fault), then talks again
        self.silent = (int(silent[0] * 1000000), int(silent[1] * 1000000)) if silent else (-1, -1)
        self._next()

    def _next(self):
        self.chunk = None
        self.sent = 0
        while self.file is not None:
            line = self.file.readline()
            if not line:
                self.file.close()
                self.file = None
                return
            tab = line.find(b"\t")
            if tab >= 0:
                data = line[tab + 1 :].rstrip(b"\n").replace(b"\\r\\n", b"\r\n")
                self.chunk = (int(line[:tab]), data)
                return

    def pull(self, now, room):
        """Return the bytes that arrived until `now`, at most `room`; the rest beyond the buffer are lost."""
        out = b""
        lost = 0
        while self.chunk is not None:
            t, data = self.chunk
            if t > now:
                break
            if not rail_on(self.power) or self.silent[0] <= t < self.silent[1]:
                self.lost_unpowered += len(data)
                self._next()
                continue
            arrived = min(len(data), int((now - t) / self.us_per_byte) + 1)
            if arrived > self.sent:
                piece = data[self.sent : arrived]
                self.sent = arrived
                take = min(len(piece), room - len(out))
                out += piece[:take]
                lost += len(piece) - take
            if self.sent < len(data):
                break
            self._next()
        return out, lost
