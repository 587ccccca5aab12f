"""The emulated board's cost model (codegen/sim/boardclock.py): print it per board, or measure it again in QEMU.

    python3 benchmarks/board_clock.py                        # the checked-in table, per bundled board's chip
    python3 benchmarks/board_clock.py --calibrate [--write]  # measure in QEMU (minutes); --write updates the table

--calibrate builds ../shared/micropython's mpy-cross and its QEMU port for MPS2-AN500 (Cortex-M7,
MICROPY_FLOAT_IMPL=float, a 2 MiB heap), once per content into $DEADRECKON_CACHE (default ~/.cache/deadreckon; by
codegen/portbuild.py and codegen.natmod.qemu_arm.firmware), and the default board's native module for armv7emsp
(hardware float: no runtime linked), then runs (codegen.natmod.qemu_arm.Session, without its /mem file system) under
`qemu-system-arm -icount shift=0` (one virtual nanosecond per instruction, so ticks_us() counts thousands of
instructions):
- MicroPython's tests/perf_bench (N=100 M=100, the benchmarks whose parameters have not changed since the pyboard
  v1.0 times of micropython#4858), giving R_pyb, the pyboard's Thumb-2 instructions per microsecond;
- the generated app's operations (default board, seed and fused kernels), each repeated, with stub peripherals
  whose own cost is measured and taken out: a sample read, a FIFO record, an idle loop pass, NMEA per byte and per
  sentence, a fix, a screen, a display page, the kernels per call and per sample (fallback and native);
- the app's heap footprint after import and start-up, against the same on the host (host_heap_scale).
Needs qemu-system-arm, arm-none-eabi-gcc with picolibc, make, and the `ar` and pyelftools packages (natmod link).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from codegen.board.loader import bundled_boards, load_board  # noqa: E402
from codegen.sim import boardclock  # noqa: E402
from codegen.tools import SHARED_MICROPYTHON, find_tool, tool_env  # noqa: E402

# pyboard v1.0 (STM32F405 at 168 MHz), MicroPython's tests/perf_bench at N=100 M=100, microseconds: micropython#4858
# (dpgeorge, 2019-06-19). Only the benchmarks whose bm_params are unchanged up to v1.28.0.
PYBOARD_US = {"bm_chaos": 172991.88, "bm_float": 53790.38, "bm_hexiom": 291988.25, "misc_aes": 95260.00,
              "misc_mandel": 138049.00, "misc_pystone": 162376.12, "misc_raytrace": 343353.88}
QEMU_BOARD = "MPS2_AN500"
GUEST_HEAP = 2 * 1024 * 1024  # bytes: the whole app with its log and the probes
GUEST_ICOUNT = "shift=0,align=off,sleep=off"  # one instruction per virtual ns; idle time does not follow the host's
GUEST_TIMEOUT_S = 1800.0


def build_firmware(log) -> Path:
    """MicroPython's QEMU port for QEMU_BOARD with a GUEST_HEAP heap, built once per content into the cache
    (codegen.natmod.qemu_arm.firmware, codegen/portbuild.py)."""
    from codegen.natmod import qemu_arm

    return qemu_arm.firmware(SHARED_MICROPYTHON, QEMU_BOARD, log=log, heap_bytes=GUEST_HEAP)


def build_mpy_cross(log) -> str:
    """The MicroPython tree's own mpy-cross (the compiler of the app's .mpy the table was measured with), built once
    per content into the cache (codegen/portbuild.py)."""
    from codegen import portbuild

    product = portbuild.Product(name="micropython-mpy-cross", dirs=("py", "mpy-cross", "shared", "extmod", "lib",
                                                                     "tools"),
                                make_dir="mpy-cross", make_args=(), built="build/mpy-cross", hint="apt-get install gcc make")
    return str(portbuild.build(product, SHARED_MICROPYTHON, log=log))


def session(elf: Path):
    """MicroPython in qemu-system-arm counting instructions, driven through its raw REPL (codegen.natmod.qemu_arm's
    Session, a context manager), the clock never waiting for the host's."""
    from codegen.natmod import qemu_arm

    return qemu_arm.Session(elf, QEMU_BOARD, timeout=GUEST_TIMEOUT_S, icount=GUEST_ICOUNT, mem_fs=False)


# ------------------------------------------------------------------------------------------------ guest code
# A read-only/writable file system in RAM for the app's modules and its log, written here for the calibration.
GUEST_FS = r'''
import io, os

class _File(io.IOBase):
    def __init__(self, fs, name, data, writing):
        self.fs, self.name, self.data, self.pos, self.writing = fs, name, data, 0, writing
    def readinto(self, buf):
        n = min(len(buf), len(self.data) - self.pos)
        buf[:n] = self.data[self.pos:self.pos + n]
        self.pos += n
        return n
    def read(self, n=-1):
        n = len(self.data) - self.pos if n < 0 else n
        out = bytes(self.data[self.pos:self.pos + n])
        self.pos += len(out)
        return out
    def write(self, buf):
        self.data.extend(buf)
        self.fs.files[self.name] = self.data
        return len(buf)
    def flush(self):
        pass
    def ioctl(self, req, arg):
        return 0
    def close(self):
        pass
    def __enter__(self):
        return self
    def __exit__(self, *a):
        pass

class RamFS:
    def __init__(self, files):
        self.files = files
    def mount(self, readonly, mkfs):
        pass
    def umount(self):
        pass
    def chdir(self, path):
        pass
    def mkdir(self, path):
        pass
    def remove(self, path):
        self.files.pop(path.lstrip("/"), None)
    def statvfs(self, path):
        return (4096, 4096, 512, 400, 400, 0, 0, 0, 0, 255)
    def ilistdir(self, path):
        for name in list(self.files):
            yield (name, 0x8000, 0, len(self.files[name]))
    def stat(self, path):
        name = path.lstrip("/")
        if name == "":
            return (0x4000, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        if name in self.files:
            return (0x8000, 0, 0, 0, 0, 0, len(self.files[name]), 0, 0, 0)
        raise OSError(2)
    def open(self, path, mode):
        name = path.lstrip("/")
        if "w" in mode:
            self.files[name] = bytearray()
            return _File(self, name, self.files[name], True)
        if name not in self.files:
            raise OSError(2)
        return _File(self, name, self.files[name], False)
'''

# Stub peripherals: registers that answer like the chips at rest, a UART fed by the measurement.
GUEST_MACHINE = r'''
class Pin:
    IN = 1
    OUT = 3
    PULL_UP = 2
    PULL_DOWN = 1
    def __init__(self, id, mode=-1, pull=-1, value=None):
        self.v = 1
    def value(self, v=None):
        if v is None:
            return 1
        self.v = v
    def init(self, *a, **k):
        pass

REGS = {0x68: {0x75: 0x68, 0x3A: 1, 0x40: 0x40}, 0x34: {0x03: 0x03}}
SAMPLE = bytes([1, 0x01, 0x20, 0xFF, 0xE0, 0x40, 0x10, 0xF1, 0x80, 0x00, 0x25, 0xFF, 0xC8, 0x00, 0x0C])

class I2C:
    def __init__(self, id=0, scl=None, sda=None, freq=400000, timeout=50000):
        pass
    def readfrom_mem_into(self, addr, reg, buf):
        if addr == 0x68 and reg == 0x3A:
            buf[:] = SAMPLE[:len(buf)]
        elif addr == 0x68 and reg == 0x72:
            buf[0] = 0
            buf[1] = 120
        elif addr == 0x68 and reg == 0x74:
            buf[:] = SAMPLE[1:1 + len(buf)]
        else:
            buf[0] = REGS.get(addr, {}).get(reg, 0)
    def readfrom_mem(self, addr, reg, n):
        return bytes([REGS.get(addr, {}).get(reg, 0)]) * n
    def writeto_mem(self, addr, reg, buf):
        pass
    def writeto(self, addr, buf, stop=True):
        return len(buf)
    def writevto(self, addr, vector, stop=True):
        return 0
    def scan(self):
        return [0x34, 0x3C, 0x68]

class UART:
    def __init__(self, id, **kw):
        self.pending = b""
    def any(self):
        return len(self.pending)
    def read(self, n=-1):
        out = self.pending
        self.pending = b""
        return out or None
    def write(self, buf):
        return len(buf)

class WDT:
    def __init__(self, id=0, timeout=5000):
        pass
    def feed(self):
        pass

def freq(hz=None):
    return 240000000

def reset():
    raise SystemExit

def reset_cause():
    return 1

PWRON_RESET = 1
WDT_RESET = 3
'''

GUEST_TOOLS = r'''
import time, gc, json

def per_call(fn, n):
    """Instructions per call of fn (one virtual ns each), the loop's own cost taken out; from a collected heap."""
    gc.collect()
    t0 = time.ticks_us()
    for _ in range(n):
        fn()
    t = time.ticks_diff(time.ticks_us(), t0)
    t0 = time.ticks_us()
    for _ in range(n):
        _nothing()
    t -= time.ticks_diff(time.ticks_us(), t0)
    return t * 1000.0 / n

def _nothing():
    pass

def alloc_per_call(fn, n):
    """Bytes the heap gives out per call of fn (gc.mem_alloc deltas with the collector held off)."""
    gc.collect()
    gc.disable()
    a0 = gc.mem_alloc()
    for _ in range(n):
        fn()
    a1 = gc.mem_alloc()
    gc.enable()
    gc.collect()
    return (a1 - a0) / n

ALLOC = {}

def report_alloc(name, value):
    print("ALLOC " + json.dumps([name, value]))

class Clock:
    # the app's time module without its sleeps (the board sleeps; QEMU would count a busy wait)
    ticks_us = time.ticks_us
    ticks_ms = time.ticks_ms
    ticks_diff = time.ticks_diff
    ticks_add = time.ticks_add
    def sleep_us(us):
        pass
    def sleep_ms(ms):
        pass

def report(name, value):
    print("OP " + json.dumps([name, value]))
'''


def guest_files(app_dir: Path, mpy_cross: str) -> dict[str, bytes]:
    """The app's modules as bytecode .mpy (as `deadreckon build` ships them), and the stub machine."""
    files = {}
    for path in sorted(app_dir.glob("*.py")):
        if path.name == "main.py":
            continue
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / (path.stem + ".mpy")
            subprocess.run([mpy_cross, "-o", str(out), str(path)], check=True, capture_output=True)
            files[path.stem + ".mpy"] = out.read_bytes()
    files["machine.py"] = GUEST_MACHINE.encode()
    return files


def mount_code(files: dict[str, bytes], where: str) -> str:
    lines = [GUEST_FS, "_files = {}"]
    for name, data in files.items():
        lines.append(f"_files[{name!r}] = {data!r}")
    lines.append(f"os.mount(RamFS(_files), {where!r})")
    lines.append("os.mount(RamFS({}), '/logs')")
    lines.append(f"import sys\nsys.path.insert(0, {where!r})")
    return "\n".join(lines)


def perf_bench(firmware: Path, log) -> dict:
    bench = SHARED_MICROPYTHON / "tests" / "perf_bench"
    runner = (bench / "benchrun.py").read_text()
    out = {}
    for name in PYBOARD_US:
        with session(firmware) as guest:
            text = guest.exec((bench / f"{name}.py").read_text() + "\n" + runner + "\nbm_run(100, 100)\n")
        us = int(text.split()[0])
        out[name] = {"instructions": us * 1000, "pyboard_us": PYBOARD_US[name]}
        log(f"  {name}: {us * 1000 / 1e6:.1f} M instructions, pyboard {PYBOARD_US[name] / 1000:.1f} ms")
    return out


def walk_counts(n: int, seed: int = 3) -> np.ndarray:
    """Raw counts of a simulated walk (default board), n samples from its moving part."""
    from codegen.sim import mpu6050, trajectory

    board = load_board(None).board
    traj = trajectory.make_scenario("walk", seed=seed, duration=40.0)
    _, counts = mpu6050.simulate_imu(traj, board, seed=seed)
    return counts[int(20 * 200) : int(20 * 200) + n]


KERNEL_PROBE = r'''
from array import array
import {module} as dr
walk = array('h', {walk!r})
cal = array('h', bytes(12 * 2000))
for k in range(2000):
    for j in range(6):
        cal[6 * k + j] = walk[6 * (k % 64) + j] // 64 + (16384 if j == 2 else 0)
dt = array('i', [5000] * 512)
out = array('f', bytes(24))
mv = memoryview(walk)
dv = memoryview(dt)
st = array('f', bytes(4 * dr.FUSED_STATE_LEN))
dr.fused_init(st)
dr.fused_calibrate(st, cal)
report("{kind}.fused_calibrate", [per_call(lambda: dr.fused_calibrate(st, mv[:6 * 64]), 20),
                                  per_call(lambda: dr.fused_calibrate(st, cal), 3)])
for m in (64, 512):
    report("{kind}.fused_process_%d" % m, per_call(lambda: dr.fused_process(st, mv[:6 * m], dv[:m], out), 8))
report_alloc("{kind}.fused_process", alloc_per_call(lambda: dr.fused_process(st, mv[:6 * 64], dv[:64], out), 2) / 64)
report("{kind}.fused_fix", per_call(lambda: (dr.fused_position(st, 1.2, 0.4, 1.2, 0.4), dr.fused_gps(st, 1.2, 0.4)), 50))
ss = array('f', bytes(4 * dr.STATE_LEN))
dr.init(ss)
dr.calibrate(ss, cal)
report("{kind}.calibrate", [per_call(lambda: dr.calibrate(ss, mv[:6 * 64]), 20), per_call(lambda: dr.calibrate(ss, cal), 3)])
for m in (64, 512):
    report("{kind}.process_%d" % m, per_call(lambda: dr.process(ss, mv[:6 * m], dv[:m], out), 8))
report_alloc("{kind}.process", alloc_per_call(lambda: dr.process(ss, mv[:6 * 64], dv[:64], out), 2) / 64)
report("{kind}.set_velocity", per_call(lambda: dr.set_velocity(ss, 1.0, 0.5, 0.0), 200))
report("{kind}.offset_latlon", per_call(lambda: dr.offset_latlon(400350855, -755200937, 12.5, -3.25), 200))
'''

APP_PROBE = r'''
import gc
gc.collect()
heap0 = gc.mem_alloc()
import app
gc.collect()
heap_import = gc.mem_alloc() - heap0
a = app.App()
gc.collect()
report("heap", [heap_import, gc.mem_alloc() - heap0])
app.time = Clock
i2c = a.imu.i2c
buf15 = bytearray(15)
stub_i2c = per_call(lambda: i2c.readfrom_mem_into(0x68, 0x3A, buf15), 300)
stub_write = per_call(lambda: i2c.writeto(0x3C, b"ab"), 300)
stub_writev = per_call(lambda: i2c.writevto(0x3C, (b"@", b"abc")), 300)
stub_any = per_call(a.uart.any, 300)
report("stub_i2c", stub_i2c)
# a data-ready sample (its log record every log_every samples included), without the stub's read
a.state_id = 1
def one_sample():
    a.k = 0
    a._sample()
report("sample", per_call(one_sample, 400) - stub_i2c)
report_alloc("sample", alloc_per_call(one_sample, 200) - alloc_per_call(lambda: i2c.readfrom_mem_into(0x68, 0x3A, buf15), 200))
# a FIFO record
a.imu.use_fifo = True
a.fifo_pending = 1 << 30
report("fifo_record", per_call(one_sample, 400) - stub_i2c)
report_alloc("fifo_record", alloc_per_call(one_sample, 200))
a.imu.use_fifo = False
# an idle pass of the loop (nothing due: it would sleep)
now_ms = app.time.ticks_ms()
def idle():
    a.next_due = app.time.ticks_add(app.time.ticks_us(), 1000000)
    a.next_button_ms = app.time.ticks_add(now_ms, 1000000)
    a.next_screen_ms = app.time.ticks_add(now_ms, 1000000)
    a.diag_ms = now_ms
    a.step()
report("step", per_call(idle, 300) - stub_any)
report_alloc("step", alloc_per_call(idle, 200))
# NMEA: per byte and per sentence, from two epochs of different shape
from nmea import Nmea
full = {full!r}
short = {short!r}
p = Nmea()
c_full = per_call(lambda: p.feed(full), 100)
c_short = per_call(lambda: p.feed(short), 100)
# the checksum and field work run per character: one cost per byte, from a whole epoch (the short one checks it)
report("nmea", [0.0, c_full / len(full)])
report_alloc("nmea", alloc_per_call(lambda: p.feed(full), 20) / len(full))
report("nmea_check", [c_short / len(short), c_full / len(full)])
# a fix taken (the app's part: its record, velocity, anchor), kernels and NMEA taken out
epochs = {epochs!r}
a.k = 0
fixes = []
q = Nmea(fixes.append)
for e in epochs:
    q.feed(e)
todo = list(fixes)
def fix():
    a._on_fix(todo.pop())
n_fix = len(fixes)
report("gps_fix", per_call(fix, n_fix))
todo = list(fixes)
report_alloc("gps_fix", alloc_per_call(fix, n_fix))
# a screen: its lines, drawn into the frame buffer; a page sent (the bus write is the stub's)
lines_a = a.screen_lines(now_ms)
report("screen_lines", per_call(lambda: a.screen_lines(now_ms), 100))
report_alloc("screen_lines", alloc_per_call(lambda: a.screen_lines(now_ms), 50))
flip = [0]
def show():
    flip[0] ^= 1
    a.oled.show(lines_a if flip[0] else lines_a[1:] + lines_a[:1])
report("screen_show", per_call(show, 100))
report_alloc("screen_show", alloc_per_call(show, 50))
def page():
    if not a.oled.busy():
        a.oled.next_page = 0
        a.oled.first = True
    a.oled.step()
cmds = 3 if a.oled.sh1106 else 6
report("page", per_call(page, 200) - stub_writev - cmds * stub_write)
# the window's own work around the kernel (the kernel is charged apart)
dr = app.dr
real = dr.fused_process if app.FUSED else dr.process
def nokernel(*args):
    pass
if app.FUSED:
    dr.fused_process = nokernel
else:
    dr.process = nokernel
def window():
    a.k = dr.WINDOW
    a._window()
report("window", per_call(window, 100) - per_call(lambda: nokernel(1, 2, 3, 4), 100))
report_alloc("window", alloc_per_call(window, 50))
report("diag", per_call(lambda: a._diag(app.time.ticks_add(a.diag_ms, 5000)), 50))
'''


def run_probe(firmware: Path, files: dict, code: str) -> dict:
    with session(firmware) as guest:
        text = guest.exec(mount_code(files, "/app") + "\n" + GUEST_TOOLS + "\n" + code)
    ops = {}
    for line in text.splitlines():
        if line.startswith("OP "):
            name, value = json.loads(line[3:])
            ops[name] = value
        elif line.startswith("ALLOC "):
            name, value = json.loads(line[6:])
            ops.setdefault("alloc", {})[name] = value
    return ops


def kernel_ops(raw: dict, kind: str) -> dict:
    """{name: instructions or [per call, per sample]} from the probe's two-point measurements."""
    def line(short, long_, m_short, m_long):
        # the long run's garbage collections land in the per-sample cost; a call's own cost is not below zero
        per_sample = (long_ - short) / (m_long - m_short)
        return [max(0.0, short - per_sample * m_short), per_sample]

    k = f"{kind}."
    return {
        "fused_process": line(raw[k + "fused_process_64"], raw[k + "fused_process_512"], 64, 512),
        "process": line(raw[k + "process_64"], raw[k + "process_512"], 64, 512),
        "fused_calibrate": line(raw[k + "fused_calibrate"][0], raw[k + "fused_calibrate"][1], 64, 2000),
        "calibrate": line(raw[k + "calibrate"][0], raw[k + "calibrate"][1], 64, 2000),
        "fused_fix": raw[k + "fused_fix"],
        "set_velocity": raw[k + "set_velocity"],
        "offset_latlon": raw[k + "offset_latlon"],
    }


def host_footprint(app_dir: Path, mpy_cross: str) -> list[int]:
    """The same app's heap after import and after start-up on the host's 64-bit MicroPython (with mpsim)."""
    from codegen.sim import harness

    micropython = find_tool("micropython")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        mpy = tmp / "modules"  # not "app": the probe's folder is on the path, a folder named app would shadow it
        mpy.mkdir()
        for path in app_dir.glob("*.py"):
            subprocess.run([mpy_cross, "-o", str(mpy / (path.stem + ".mpy")), str(path)], check=True,
                           capture_output=True)
        counts = harness.write_counts(tmp / "imu.bin", harness.imu_counts(2, 200.0))
        world = harness.tbeam_scenario(tmp, counts, None, 1.0)
        world["fs"]["image"] = str(tmp / "fs.img")
        world["trace"] = str(tmp / "trace.jsonl")
        (tmp / "scenario.json").write_text(json.dumps(world))
        probe = tmp / "probe.py"
        probe.write_text("import gc\nimport machine, time\ngc.collect()\nh0 = gc.mem_alloc()\nimport app\n"
                         "gc.collect()\nh1 = gc.mem_alloc() - h0\na = app.App()\ngc.collect()\n"
                         "print('HEAP', h1, gc.mem_alloc() - h0)\n")
        env = dict(os.environ, MICROPYPATH=f"{harness.MPSIM}:{mpy}", MPSIM_SCENARIO=str(tmp / "scenario.json"))
        done = subprocess.run([micropython, "-X", "heapsize=8M", str(probe)], env=env, capture_output=True,
                              text=True, cwd=tmp)
        line = [x for x in done.stdout.splitlines() if x.startswith("HEAP")]
        if not line:
            raise RuntimeError(done.stdout[-2000:] + done.stderr[-2000:])
        return [int(x) for x in line[0].split()[1:]]


def calibrate(log) -> dict:
    from codegen.generate import generate
    from codegen.sim import neo6m

    for tool in ("qemu-system-arm", "arm-none-eabi-gcc", "make"):
        if find_tool(tool) is None:
            raise SystemExit(f"{tool} is missing (Debian: qemu-system-arm, gcc-arm-none-eabi, picolibc-arm-none-eabi)")
    firmware = build_firmware(log)
    tree = SHARED_MICROPYTHON
    mpy_cross = build_mpy_cross(log)
    table = {"measured_with": {
        "micropython": "v1.28.0 (../shared/micropython), ports/qemu BOARD=MPS2_AN500 MICROPY_FLOAT_IMPL=float",
        "qemu": subprocess.run(["qemu-system-arm", "--version"], capture_output=True, text=True).stdout.split("\n")[0],
        "counting": "-icount shift=0: ticks_us() * 1000 = Thumb-2 instructions",
        "command": "python3 benchmarks/board_clock.py --calibrate --write"}}
    log("perf_bench (R_pyb)")
    table["perf_bench"] = perf_bench(firmware, log)
    ratios = [v["instructions"] / v["pyboard_us"] for v in table["perf_bench"].values()]
    table["pyboard_instructions_per_us"] = float(np.median(ratios))
    table["pyboard_instructions_per_us_range"] = [float(min(ratios)), float(max(ratios))]
    ops = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for mode in ("fused", "seed"):
            yaml = tmp / f"{mode}.yaml"
            yaml.write_text(f"extends: ttgo-tbeam-v1.1\nname: clock-{mode}\nalgorithm:\n  mode: {mode}\n")
            out = tmp / f"out-{mode}"
            generate(load_board(yaml), out, force=True)
            files = guest_files(out / "app", mpy_cross)
            if mode == "fused":
                log("the native module for armv7emsp")
                native = out / "native"
                # the Makefile's own runtime choice, as `deadreckon build` makes it: armv7emsp has the FPU and
                # needs no libgcc (LINK_RUNTIME=1 pulls libc's memcpy beside natmod_libc.c's: duplicate symbol)
                subprocess.run(["make", f"MPY_DIR={tree}", "ARCH=armv7emsp", f"MPY_CROSS={mpy_cross}",
                                f"PYTHON={sys.executable}"], cwd=native, env=tool_env(), check=True, capture_output=True)
                walk = walk_counts(512).ravel().tolist()
                log("kernels: fallback")
                raw = run_probe(firmware, files, KERNEL_PROBE.format(module="dr_fallback", walk=walk, kind="python"))
                ops["python"] = kernel_ops(raw, "python")
                table.setdefault("alloc_bytes", {}).update(raw.get("alloc", {}))
                log("kernels: native")
                native_files = dict(files, **{"dr_native.mpy": (native / "dr_native.mpy").read_bytes()})
                raw = run_probe(firmware, native_files, KERNEL_PROBE.format(module="dr_native", walk=walk,
                                                                            kind="native"))
                ops["native"] = kernel_ops(raw, "native")
                table.setdefault("alloc_bytes", {}).update(raw.get("alloc", {}))
            track = neo6m.simulate_gps(__import__("codegen.sim.trajectory", fromlist=["x"]).make_scenario(
                "walk", seed=1, duration=30.0), seed=1)
            sentences = neo6m.nmea_sentences(track)
            full = b"".join(sentences[4 * 20 : 4 * 21])
            short = sentences[4 * 21] + sentences[4 * 21 + 2]
            epochs = [b"".join(sentences[4 * i : 4 * i + 4]) for i in range(1, 29)]
            log(f"app operations ({mode})")
            raw = run_probe(firmware, files, APP_PROBE.format(full=full, short=short, epochs=epochs))
            heap_arm32 = raw.pop("heap")
            alloc = raw.pop("alloc", {})
            table.setdefault("alloc_bytes", {}).update({(k if mode == "fused" or k not in ("window", "gps_fix")
                                                          else k + "_seed"): v for k, v in alloc.items()})
            raw.pop("stub_i2c", None)
            raw.pop("nmea_check", None)
            if mode == "fused":
                for name, value in raw.items():
                    ops[name] = value
                table["heap_arm32"] = heap_arm32
                table["heap_x64"] = host_footprint(out / "app", mpy_cross)
            else:
                ops["window_seed"] = raw["window"]
                ops["gps_fix_seed"] = raw["gps_fix"]
    ops["window_fused"] = ops.pop("window")
    table["alloc_bytes"]["window_fused"] = table["alloc_bytes"].pop("window")
    table["alloc_bytes"]["gps_fix_fused"] = table["alloc_bytes"].pop("gps_fix")
    # a fix's own work: the kernel calls it makes are charged apart (fused: position + gps and the metres from the
    # anchor by offset_latlon; seed: set_velocity)
    py = ops["python"]
    ops["gps_fix_fused"] = ops.pop("gps_fix") - py["fused_fix"] - py["offset_latlon"]
    ops["gps_fix_seed"] -= py["set_velocity"]
    table["ops"] = ops
    table["host_heap_scale"] = table["heap_x64"][1] / table["heap_arm32"][1]
    return table


def print_table(table: dict) -> None:
    rate = table["pyboard_instructions_per_us"]
    lo, hi = table.get("pyboard_instructions_per_us_range", [rate, rate])
    print(f"R_pyb = {rate:.1f} Thumb-2 instructions per us of a pyboard v1.0 (perf_bench spread {lo:.1f}-{hi:.1f})")
    print(f"host_heap_scale = {table['host_heap_scale']:.3f} (app after start-up: {table['heap_arm32'][1]} B on "
          f"32-bit ARM, {table['heap_x64'][1]} B on the 64-bit host)")
    chips = sorted({load_board(name).board.chip for name, _, _ in bundled_boards()})
    head = f"{'operation':28s}" + "".join(f" {c + ' us':>14s}" for c in chips)
    print(head)
    print("-" * len(head))
    clocks = {c: boardclock.board_clock(c, table).costs_us() for c in chips}
    rows = []
    for name, value in table["ops"].items():
        if isinstance(value, dict):
            for k, v in value.items():
                rows.append((f"{name}.{k}", [clocks[c][name][k] for c in chips]))
        else:
            rows.append((name, [clocks[c][name] for c in chips]))
    for name, per_chip in rows:
        cells = "".join(f" {'%.1f + %.2f/smp' % tuple(v) if isinstance(v, list) else '%.1f' % v:>14s}"
                        for v in per_chip)
        print(f"{name:28s}{cells}")
    alloc = table.get("alloc_bytes", {})
    if alloc:
        print("bytes the heap gives out (32-bit ARM, gc.mem_alloc deltas): " + ", ".join(
            f"{name} {value:.0f}{' per sample' if '.' in name or name == 'nmea' else ''}"
            for name, value in sorted(alloc.items())))
    print("(one 512-sample fused window, kernel only: " + ", ".join(
        f"{c} {clocks[c]['python']['fused_process'][0] + 512 * clocks[c]['python']['fused_process'][1]:.0f} us "
        f"fallback / {clocks[c]['native']['fused_process'][0] + 512 * clocks[c]['native']['fused_process'][1]:.0f} us "
        "native" for c in chips) + ")")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calibrate", action="store_true", help="measure again in QEMU (minutes)")
    parser.add_argument("--write", action="store_true", help="with --calibrate: update codegen/sim/board_clock.json")
    args = parser.parse_args(argv)

    def log(text):
        print(text, file=sys.stderr, flush=True)

    if args.calibrate:
        table = calibrate(log)
        if args.write:
            boardclock.TABLE.write_text(json.dumps(table, indent=1, sort_keys=True) + "\n")
            log(f"wrote {boardclock.TABLE}")
    else:
        table = boardclock.load_table()
    print_table(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
