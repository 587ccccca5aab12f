"""MicroPython's QEMU port (ports/qemu) on the ARM cores our boards' natmods target, built once and cached.

    MICROBIT     Cortex-M0 (armv6m, the RP2040's instruction set), nRF51; built with native code loading on
                 (MICROPY_EMIT_THUMB without ARMv7-M, as the rp2 port has it), 256 KiB RAM
    MPS2_AN385   Cortex-M3 (armv7m)
    MPS2_AN500   Cortex-M7 with FPU, built with single-precision floats (armv7emsp natmods): the benchmark's stand-in
                 for a core with hardware float, as the ESP32 has

The firmware is built (Debian gcc-arm-none-eabi + picolibc) by codegen/portbuild.py from a copy of a MicroPython
tree, keyed by the tree's content, the board, the flags and the compiler, in $DEADRECKON_CACHE/qemu-arm/KEY/
firmware.elf; the copy is removed after the build. `Session` runs it under qemu-system-arm with `-icount shift=0` (one instruction per virtual
nanosecond: a virtual clock is an exact instruction counter) and talks MicroPython's raw REPL over the emulated UART;
files (the .mpy) are sent in chunks into a RAM filesystem mounted at /mem. `CLOCK_SOURCE[board]` is MicroPython code
defining `clock()`, a hardware timer of the emulated SoC read through machine.mem32, and `CLOCK_NS[board]`
the virtual nanoseconds (= instructions) per count.
"""

from __future__ import annotations

import base64
import os
import select
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from codegen import portbuild
from codegen.errors import UserError

HEAP = "MICROPY_HEAP_SIZE=196608"  # 192 KiB, about what MicroPython has on an RP2040 or an ESP32 without PSRAM
BOARDS = {
    "MICROBIT": dict(arch="armv6m", make=[HEAP], machine=["microbit", "-global", "nrf51-soc.flash-size=1048576",
                                             "-global", "nrf51-soc.sram-size=262144"],
                     cflags="-DMICROPY_EMIT_THUMB=1 -DMICROPY_EMIT_THUMB_ARMV7M=0 -DMICROPY_EMIT_INLINE_THUMB=1 "
                            "-DMICROPY_EMIT_INLINE_THUMB_FLOAT=0"),
    "MPS2_AN385": dict(arch="armv7m", machine=["mps2-an385"], cflags="", make=[HEAP]),
    # Cortex-M7 with its FPU, MicroPython floats in single precision as on the ESP32: the nearest QEMU core to the
    # ESP32's (hardware float for both the natmod and the interpreter)
    "MPS2_AN500": dict(arch="armv7emsp", machine=["mps2-an500"], cflags="", make=[HEAP, "MICROPY_FLOAT_IMPL=float"]),
}
# a free-running 32-bit timer of each SoC as QEMU models it: nRF51 TIMER0 at 16 MHz (counts up), CMSDK APB timer 0
# at the AN385's 25 MHz peripheral clock (counts down)
CLOCK_SOURCE = {
    "MICROBIT": ("import machine\n_m = machine.mem32\n_m[0x40008504] = 0\n_m[0x40008508] = 3\n_m[0x40008510] = 0\n"
                 "_m[0x40008000] = 1\ndef clock():\n    _m[0x40008040] = 1\n    return _m[0x40008540]\n"),
    "MPS2_AN385": ("import machine\n_m = machine.mem32\n_m[0x40000008] = 0xFFFFFFFF\n_m[0x40000004] = 0xFFFFFFFF\n"
                   "_m[0x40000000] = 1\ndef clock():\n    return (0xFFFFFFFF - _m[0x40000004]) & 0xFFFFFFFF\n"),
}
CLOCK_SOURCE["MPS2_AN500"] = CLOCK_SOURCE["MPS2_AN385"]
CLOCK_NS = {"MICROBIT": 1e9 / 16e6, "MPS2_AN385": 1e9 / 25e6, "MPS2_AN500": 1e9 / 25e6}
PORT_DIRS = ("py", "extmod", "shared", "lib", "drivers", "ports/qemu", "tools")  # what the port's build reads
CHUNK = 6000  # bytes of a file per raw-REPL command (base64 in the command text)
MEM_FS = """
import io, sys, vfs
class _MemFile(io.IOBase):
    def __init__(self, data):
        self.data = data
        self.pos = 0
    def readinto(self, buf):
        n = min(len(buf), len(self.data) - self.pos)
        buf[:n] = memoryview(self.data)[self.pos:self.pos + n]
        self.pos += n
        return n
    def ioctl(self, request, arg):
        return 0
class _MemFs:
    def __init__(self):
        self.files = {}
    def mount(self, readonly, mkfs):
        pass
    def umount(self):
        pass
    def chdir(self, path):
        pass
    def stat(self, path):
        name = path.strip('/')
        if not name:
            return (0x4000, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        if name in self.files:
            return (0x8000, 0, 0, 0, 0, 0, len(self.files[name]), 0, 0, 0)
        raise OSError(2)
    def open(self, path, mode):
        return _MemFile(self.files[path.strip('/')])
_memfs = _MemFs()
vfs.mount(_memfs, '/mem')
sys.path.insert(0, '/mem')
"""


class QemuError(UserError):
    pass


def firmware(tree: Path, board: str, log=None, heap_bytes: Optional[int] = None) -> Path:
    """The QEMU port's firmware.elf for `board`, built from `tree` into the cache on first use (codegen/portbuild.py:
    keyed by the tree's content, the board, the flags and the compiler); heap_bytes: the MicroPython heap instead of
    HEAP's (benchmarks/board_clock.py runs the whole app)."""
    spec = BOARDS[board]
    make = [f"MICROPY_HEAP_SIZE={heap_bytes}" if heap_bytes and arg == HEAP else arg for arg in spec.get("make", [])]
    product = portbuild.Product(
        name="qemu-arm",
        dirs=PORT_DIRS,
        make_dir="ports/qemu",
        make_args=(f"BOARD={board}", "FROZEN_MANIFEST=", f"CFLAGS_EXTRA={spec['cflags']}", *make),
        built=f"build-{board}/firmware.elf",
        needs="arm-none-eabi-gcc",
        hint="apt-get install gcc-arm-none-eabi picolibc-arm-none-eabi",
    )
    return portbuild.build(product, Path(tree), log=log)


@dataclass
class Result:
    stdout: str
    error: str


class Session:
    """One qemu-system-arm running the firmware, driven over the raw REPL; a context manager. icount: QEMU's
    -icount option (shift=0 at the least: the virtual clock counts instructions); mem_fs: mount /mem for put_file
    (False leaves the heap as the firmware starts, for a caller that measures it)."""

    def __init__(self, elf: Path, board: str, timeout: float = 120.0, icount: str = "shift=0", mem_fs: bool = True):
        qemu = shutil.which("qemu-system-arm")
        if qemu is None:
            raise QemuError("qemu-system-arm is not installed", hint="apt-get install qemu-system-arm")
        self.board, self.timeout = board, timeout
        self.process = subprocess.Popen(
            [qemu, "-machine", *BOARDS[board]["machine"], "-nographic", "-monitor", "null", "-semihosting",
             "-serial", "stdio", "-icount", icount, "-kernel", str(elf)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.buffer = b""
        self._send(b"\r\x03\x03\x01")
        self._until(b"raw REPL; CTRL-B to exit\r\n>")
        if mem_fs:
            self.exec(MEM_FS)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        for stream in (self.process.stdin, self.process.stdout, self.process.stderr):
            stream.close()

    def _send(self, data: bytes) -> None:
        self.process.stdin.write(data)
        self.process.stdin.flush()

    def _until(self, token: bytes, timeout: Optional[float] = None) -> bytes:
        deadline = time.monotonic() + (timeout or self.timeout)
        while token not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise QemuError(f"QEMU {self.board}: no answer within {timeout or self.timeout:.0f} s; last output: "
                                f"{self.buffer[-500:]!r}")
            ready, _, _ = select.select([self.process.stdout], [], [], min(left, 1.0))
            if ready:
                chunk = os.read(self.process.stdout.fileno(), 65536)
                if not chunk:
                    raise QemuError(f"QEMU {self.board} exited: {self.process.stderr.read()[-500:]!r}")
                self.buffer += chunk
        head, _, self.buffer = self.buffer.partition(token)
        return head

    def exec(self, code: str, timeout: Optional[float] = None) -> str:
        """Run `code` (MicroPython source) and return what it printed; QemuError with the traceback if it raised."""
        self._send(code.encode() + b"\x04")
        self._until(b"OK", timeout)
        out = self._until(b"\x04", timeout)
        err = self._until(b"\x04", timeout)
        self._until(b">", timeout)
        if err.strip():
            raise QemuError(f"MicroPython on QEMU {self.board} raised:\n{err.decode(errors='replace')}")
        return out.decode(errors="replace").replace("\r\n", "\n")

    def send_array(self, name: str, typecode: str, data: bytes) -> None:
        """Make the global `name` an array(typecode) holding the raw bytes `data` (sent in base64 chunks small
        enough to compile on the device; a bytearray or array initialiser is copied byte for byte)."""
        self.exec(f"import binascii\nfrom array import array\n{name} = array({typecode!r}, bytearray({len(data)}))\n"
                  f"_mv = memoryview({name})")
        size = 1 if typecode in "bB" else 2 if typecode in "hH" else 4
        for start in range(0, len(data), CHUNK):
            piece = data[start:start + CHUNK]
            self.exec(f"_mv[{start // size}:{(start + len(piece)) // size}] = array({typecode!r}, "
                      f"bytearray(binascii.a2b_base64({base64.b64encode(piece).decode()!r})))")
        self.exec("del _mv")

    def put_file(self, name: str, data: bytes) -> None:
        """Make /mem/NAME hold `data` (importable when NAME is a module)."""
        self.send_array("_buf", "B", data)
        self.exec(f"_memfs.files[{name!r}] = _buf\ndel _buf")
