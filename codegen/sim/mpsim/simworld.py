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
    for fn in _finishers:
        try:
            fn()
        except Exception as e:  # a broken finaliser must not hide the others
            trace("finish_error", error=repr(e))
    trace("end")
    if _trace is not None:
        _trace.flush()


def load():
    global _scenario, _trace
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
        _mount_ramdisk(fs)


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


class RamDisk:
    """A block device in RAM for a LittleFS filesystem the size of the board's partition (or smaller)."""

    def __init__(self, block, count):
        self.block = block
        self.data = bytearray(block * count)

    def readblocks(self, n, buf, off=0):
        a = n * self.block + off
        buf[:] = self.data[a : a + len(buf)]

    def writeblocks(self, n, buf, off=0):
        a = n * self.block + off
        self.data[a : a + len(buf)] = buf

    def ioctl(self, op, arg):
        if op == 4:
            return len(self.data) // self.block
        if op == 5:
            return self.block
        return 0


_filesystem = None  # (block device, mount point) of the board's filesystem, for firmwares that remount it (cpsim)


def filesystem():
    return _filesystem


def _mount_ramdisk(fs):
    global _filesystem
    disk = RamDisk(fs.get("block", 4096), fs["bytes"] // fs.get("block", 4096))
    os.VfsLfs2.mkfs(disk)
    mount = fs.get("mount", "/logs")
    os.mount(os.VfsLfs2(disk), mount)
    _filesystem = (disk, mount)
    dump = fs.get("dump")
    if dump:

        def copy_out():
            for name in os.listdir(mount):
                with open(mount + "/" + name, "rb") as src:
                    data = src.read()
                with open(dump + "/" + name, "wb") as dst:
                    dst.write(data)
            st = os.statvfs(mount)
            trace("fs", files=sorted(os.listdir(mount)), free=st[0] * st[3], total=st[0] * st[2])

        at_end(copy_out)


# ---------------------------------------------------------------- I2C devices


class Mpu6050:
    """Register model of the MPU-6050 answering from a count stream.

    Options: who_am_i (0x68; clones answer 0x70, 0x72, 0x98...), counts (host path of little-endian int16
    records ax ay az gx gy gz), rate_hz (the stream's sample rate), accel_range_g / gyro_range_dps (the range the
    stream's counts are in; the model rescales to the range the app configures and saturates like the chip).
    Samples come every 1/(gyro_rate/(1+SMPLRT_DIV)) s of virtual time after the app wakes the chip.
    """

    FIFO_BYTES = 1024

    def __init__(self, opts):
        self.regs = bytearray(128)
        self.who = opts.get("who_am_i", 0x68)
        self.reset()
        path = opts.get("counts")
        self.stream = b""
        if path:
            with open(path, "rb") as f:
                self.stream = f.read()
        self.nsamples = len(self.stream) // 12
        self.stream_rate = opts.get("rate_hz", 200.0)
        self.stream_ag = opts.get("accel_range_g", 2)
        self.stream_gd = opts.get("gyro_range_dps", 250)
        self.temp = opts.get("temp_counts", -3920)  # 25 C
        self.k = 0  # index of the next sample the chip produces
        self.t0 = None  # virtual us when sampling started
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
        base = 8000 if (self.regs[0x1A] & 7) in (0, 7) else 1000
        return base / (1 + self.regs[0x19])

    def _sample(self, t_s):
        if self.nsamples == 0:
            return (0, 0, 0, 0, 0, 0)
        i = int(t_s * self.stream_rate)
        if i >= self.nsamples:
            i = self.nsamples - 1
        raw = struct.unpack_from("<6h", self.stream, 12 * i)
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
        if self.t0 is None:
            self.t0 = now
            self.k = 0
        rate = self._rate()
        due = int((now - self.t0) * rate / 1000000) + 1  # samples produced so far
        if due - self.k > 2000:  # long stall: skip ahead, the chip keeps only the newest
            self.k = due - 2000
        fifo_on = self.regs[0x6A] & 0x40
        fifo_sel = self.regs[0x23]
        while self.k < due:
            t_s = self.k / rate
            self.latest = self._sample(t_s)
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
    if opts.get("nack"):
        return Nacker()
    dev = KINDS[opts["kind"]](opts)
    if "nack_after_s" in opts:
        dev.nack_after_us = int(opts["nack_after_s"] * 1000000)
    return dev


# ---------------------------------------------------------------- UART streams


class NmeaStream:
    """Bytes of a GPS receiver: chunks "t_us<TAB>text" delivered at the line rate, only while the rail is on."""

    def __init__(self, opts, baud):
        self.chunks = []
        path = opts.get("stream")
        if path:
            with open(path, "rb") as f:
                for line in f:
                    tab = line.find(b"\t")
                    if tab < 0:
                        continue
                    data = line[tab + 1 :].rstrip(b"\n").replace(b"\\r\\n", b"\r\n")
                    self.chunks.append((int(line[:tab]), data))
        self.power = opts.get("power")
        self.idx = 0
        self.sent = 0  # bytes of chunks[idx] already delivered
        self.us_per_byte = 10 * 1000000 / baud
        self.lost_unpowered = 0

    def pull(self, now, room):
        """Return the bytes that arrived until `now`, at most `room`; the rest beyond the buffer are lost."""
        out = b""
        lost = 0
        while self.idx < len(self.chunks):
            t, data = self.chunks[self.idx]
            if t > now:
                break
            if not rail_on(self.power):
                self.lost_unpowered += len(data)
                self.idx += 1
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
            self.idx += 1
            self.sent = 0
        return out, lost
