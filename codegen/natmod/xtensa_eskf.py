"""The error-state filter's C (native_ext/dr_eskf.c) as ESP32 code on qemu-system-xtensa, instructions counted.

The filter is measured alone, not inside dr_native.mpy (which carries it for eskf boards): dr_eskf.c, dr_kernel.c (for
dr_config_init), dr_median.c and xtensa_sim/eskf_harness.c are each compiled by the LLVM route
(codegen.natmod.xtensa_llvm) with the flags MicroPython's dynruntime.mk gives a natmod (-std=c99 -Os), linked into
one image by mpy_ld, relocated as MicroPython's loader would and run by codegen.natmod.qemu_xtensa (its start-up
xtensa_sim/boot.s: register windows, FPU, ICOUNT; its QEMU command line and exit decoding, run_images; the step
format both harnesses read, xtensa_sim/sim_steps.h). Each step's count is exact (ICOUNT at interrupt level 0).

    steps: ("C", counts) | ("P", counts, dt_us) | ("G", t_s, e, n, u, ve, vn) | ("Q",) | ("K",) | ("U",) | ("N",)
    (Q: one covariance propagation, K: one covariance check, U: one scalar update with the constraint's row and its
    set-up, N: the constraint's rows alone; each on the state as it is and undone after)
    answers = run(build(native_dir, tree, work), steps)   # one EskfAnswer per step
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codegen.natmod import mpyfile, qemu_xtensa, xtensa_llvm

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
    boot = qemu_xtensa.assemble_boot(work)
    flags = ["-I", str(native_dir), "-I", str(qemu_xtensa.SIM), *NATMOD_FLAGS]
    objects = []
    for source in ("eskf_harness.c",) + SOURCES:  # the harness first: its mpy_init is the image's entry
        path = qemu_xtensa.SIM / source if source == "eskf_harness.c" else native_dir / source
        obj = work / (Path(source).stem + ".o")
        xtensa_llvm.compile_object(path, obj, flags)
        objects.append(obj)
    mpy = qemu_xtensa.link_objects(objects, tree, work / "eskf.mpy", "the filter")
    return EskfImage(boot, mpy, len(mpy.text), _text_size(work / "dr_eskf.o"))


def _input(steps: list, cov_dt_s: float = 0.0, nhc_dt_s: float = 0.0) -> bytes:
    body = bytearray()
    for item in steps:
        kind = item[0]
        if kind in ("C", "P"):
            body += qemu_xtensa.sample_step(item)
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
    bases = {"text": qemu_xtensa.HARNESS_TEXT, "rodata": qemu_xtensa.HARNESS_RODATA, "bss": qemu_xtensa.MODULE_BSS,
             "mp_fun_table": qemu_xtensa.FUN_TABLE, "qstr_table": qemu_xtensa.QSTR_TABLE,
             "obj_table": qemu_xtensa.QSTR_TABLE}
    if len(image.mpy.text) > qemu_xtensa.HARNESS_RODATA - qemu_xtensa.HARNESS_TEXT:
        raise qemu_xtensa.XtensaSimError(f"the filter's image ({len(image.mpy.text)} bytes) overlaps its rodata")
    text, rodata = mpyfile.relocate(image.mpy, bases)
    blob = _input(steps, cov_dt_s, nhc_dt_s)
    data = qemu_xtensa.run_images({"boot.bin": (image.boot, qemu_xtensa.VECBASE),
                                   "text.bin": (bytes(text), qemu_xtensa.HARNESS_TEXT),
                                   "rodata.bin": (bytes(rodata), qemu_xtensa.HARNESS_RODATA),
                                   "input.bin": (blob, qemu_xtensa.INPUT)}, "the filter", timeout)
    if len(data) != 4 * RECORD_WORDS * len(steps):
        raise qemu_xtensa.XtensaSimError(f"the harness wrote {len(data)} bytes, expected "
                                         f"{4 * RECORD_WORDS * len(steps)}")
    answers = []
    for k in range(len(steps)):
        took, code = struct.unpack_from("<Ii", data, 4 * RECORD_WORDS * k)
        v = np.frombuffer(data[4 * RECORD_WORDS * k + 8:4 * RECORD_WORDS * (k + 1)], dtype="<f4").astype(np.float64)
        answers.append(EskfAnswer(float(took), code, v[0:3], v[3:6], float(v[6]), bool(v[7])))
    return answers
