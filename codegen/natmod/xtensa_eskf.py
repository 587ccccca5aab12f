"""The error-state filter's C (native_ext/dr_eskf.c) as ESP32 code on qemu-system-xtensa, instructions counted.

The filter is measured alone, not inside dr_native.mpy (which carries it for eskf boards): dr_eskf.c, dr_kernel.c (for
dr_config_init), dr_median.c and xtensa_sim/eskf_harness.c are each compiled by the LLVM route
(codegen.natmod.xtensa_llvm) with the flags MicroPython's dynruntime.mk gives a natmod (-std=c99 -Os), linked into
one image by mpy_ld, relocated as MicroPython's loader would and run after codegen.natmod.qemu_xtensa's start-up
(xtensa_sim/boot.s: register windows, FPU, ICOUNT). Each step's count is exact (ICOUNT at interrupt level 0).

    steps: ("C", counts) | ("P", counts, dt_us) | ("G", t_s, e, n, u, ve, vn) | ("Q",) | ("K",) | ("U",) | ("N",)
    (Q: one covariance propagation, K: one covariance check, U: one scalar update with the constraint's row and its
    set-up, N: the constraint's rows alone; each on the state as it is and undone after)
    answers = run(build(native_dir, tree, work), steps)   # one EskfAnswer per step
"""

from __future__ import annotations

import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codegen.natmod import mpyfile, qemu_xtensa, xtensa_llvm
from codegen.tools import find_tool

SOURCES = ("dr_eskf.c", "dr_kernel.c", "dr_median.c")
NATMOD_FLAGS = ("-std=c99", "-Os", "-Wall", "-Werror", "-DNDEBUG")  # py/dynruntime.mk's
MAGIC = 0x31455244  # "DRE1"
HEADER_WORDS = 8
RECORD_WORDS = 2 + 8
ALONE = ("Q", "K", "U", "N")  # single steps on the state as it is, undone after: see eskf_harness.c


@dataclass
class EskfImage:
    boot: bytes
    mpy: mpyfile.NativeMpy
    text_bytes: int  # the linked code (harness included), bytes
    filter_text_bytes: int  # dr_eskf.o's code alone, bytes


@dataclass
class EskfAnswer:
    instructions: float
    code: int
    position: np.ndarray  # m, ENU
    velocity: np.ndarray  # m/s, ENU
    repairs: float
    started: bool


def _text_size(obj: Path) -> int:
    from elftools.elf.elffile import ELFFile

    with open(obj, "rb") as f:
        return sum(s.data_size for s in ELFFile(f).iter_sections() if s.name.startswith((".text", ".literal")))


def build(native_dir: Path, tree: Path, work: Path) -> EskfImage:
    """Compile the filter, its helpers and the harness for the ESP32 against the headers in native_dir (a rendered
    OUT/native), link them with mpy_ld from the MicroPython tree `tree`."""
    work.mkdir(parents=True, exist_ok=True)
    boot = work / "boot.o"
    done = subprocess.run([qemu_xtensa._llvm("llvm-mc"), "-triple=xtensa", "-mcpu=esp32", "-filetype=obj",
                           str(qemu_xtensa.SIM / "boot.s"), "-o", str(boot)], capture_output=True, text=True)
    if done.returncode:
        raise qemu_xtensa.XtensaSimError(f"boot.s does not assemble:\n{done.stderr}")
    flags = ["-I", str(native_dir), *NATMOD_FLAGS]
    objects = []
    for source in ("eskf_harness.c",) + SOURCES:  # the harness first: its mpy_init is the image's entry
        path = qemu_xtensa.SIM / source if source == "eskf_harness.c" else native_dir / source
        obj = work / (Path(source).stem + ".o")
        xtensa_llvm.compile_object(path, obj, flags)
        objects.append(obj)
    linked = work / "eskf.mpy"
    done = subprocess.run([sys.executable, str(tree / "tools" / "mpy_ld.py"), "--arch", "xtensawin", "-o",
                           str(linked), *map(str, objects)], capture_output=True, text=True, cwd=work)
    if done.returncode:
        raise qemu_xtensa.XtensaSimError(f"mpy_ld did not link the filter:\n{done.stdout[-2000:]}"
                                         f"{done.stderr[-2000:]}")
    mpy = mpyfile.parse(linked.read_bytes(), "eskf.mpy")
    return EskfImage(qemu_xtensa._text_of(boot), mpy, len(mpy.text), _text_size(work / "dr_eskf.o"))


def _input(steps: list, cov_dt_s: float = 0.0, nhc_dt_s: float = 0.0) -> bytes:
    body = bytearray()
    for item in steps:
        kind = item[0]
        if kind in ("C", "P"):
            samples = np.ascontiguousarray(item[1], dtype="<i2").reshape(-1, 6)
            body += struct.pack("<II", ord(kind), len(samples)) + samples.tobytes()
            if kind == "P":
                body += np.ascontiguousarray(item[2], dtype="<i4").tobytes()
        elif kind in ALONE:
            body += struct.pack("<II", ord(kind), 0)
        elif kind == "G":
            body += struct.pack("<II6f", ord("G"), 6, *item[1:7])
        else:
            raise ValueError(f"unknown step kind {kind!r}")
    header = struct.pack("<4I2f", MAGIC, len(steps), qemu_xtensa.WORKSPACE, qemu_xtensa.OUTPUT, cov_dt_s, nhc_dt_s)
    return header + bytes(4 * HEADER_WORDS - len(header)) + bytes(body)


def run(image: EskfImage, steps: list, cov_dt_s: float = 0.0, nhc_dt_s: float = 0.0,
        timeout: float = 900) -> list[EskfAnswer]:
    """The steps through the filter on qemu-system-xtensa (cov_dt_s, nhc_dt_s: s; 0 keeps dr_eskf_config_init's)."""
    qemu = find_tool("qemu-system-xtensa")
    if qemu is None:
        raise qemu_xtensa.XtensaSimError("qemu-system-xtensa is not installed",
                                         hint="apt-get install qemu-system-misc")
    bases = {"text": qemu_xtensa.HARNESS_TEXT, "rodata": qemu_xtensa.HARNESS_RODATA, "bss": qemu_xtensa.MODULE_BSS,
             "mp_fun_table": qemu_xtensa.FUN_TABLE, "qstr_table": qemu_xtensa.QSTR_TABLE,
             "obj_table": qemu_xtensa.QSTR_TABLE}
    if len(image.mpy.text) > qemu_xtensa.HARNESS_RODATA - qemu_xtensa.HARNESS_TEXT:
        raise qemu_xtensa.XtensaSimError(f"the filter's image ({len(image.mpy.text)} bytes) overlaps its rodata")
    text, rodata = mpyfile.relocate(image.mpy, bases)
    blob = _input(steps, cov_dt_s, nhc_dt_s)
    with tempfile.TemporaryDirectory(prefix="dr-xtensa-eskf-") as tmp:
        images = {"boot.bin": (image.boot, qemu_xtensa.VECBASE), "text.bin": (bytes(text), qemu_xtensa.HARNESS_TEXT),
                  "rodata.bin": (bytes(rodata), qemu_xtensa.HARNESS_RODATA), "input.bin": (blob, qemu_xtensa.INPUT)}
        command = [qemu, "-M", "sim", "-cpu", "de233_fpu", "-semihosting", "-nographic", "-monitor", "none",
                   "-serial", "none"]
        for name, (data, address) in images.items():
            if not data:
                continue
            (Path(tmp) / name).write_bytes(data)
            command += ["-device", f"loader,file={Path(tmp) / name},addr={address:#x},force-raw=on"]
        command += ["-device", f"loader,addr={qemu_xtensa.START:#x},cpu-num=0"]
        done = subprocess.run(command, capture_output=True, timeout=timeout)
    if done.returncode:
        cause = done.returncode - 64
        what = qemu_xtensa.EXCCAUSE.get(cause, f"exception cause {cause}") if 0 <= cause < 64 else \
            f"exit {done.returncode}"
        raise qemu_xtensa.XtensaSimError(f"the filter stopped on qemu-system-xtensa: {what}\n"
                                         f"{done.stderr.decode(errors='replace')[-1000:]}")
    data = done.stdout
    if len(data) != 4 * RECORD_WORDS * len(steps):
        raise qemu_xtensa.XtensaSimError(f"the harness wrote {len(data)} bytes, expected "
                                         f"{4 * RECORD_WORDS * len(steps)}")
    answers = []
    for k in range(len(steps)):
        took, code = struct.unpack_from("<Ii", data, 4 * RECORD_WORDS * k)
        v = np.frombuffer(data[4 * RECORD_WORDS * k + 8:4 * RECORD_WORDS * (k + 1)], dtype="<f4").astype(np.float64)
        answers.append(EskfAnswer(float(took), code, v[0:3], v[3:6], float(v[6]), bool(v[7])))
    return answers
