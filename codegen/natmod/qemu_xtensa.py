"""The ESP32 code of dr_native.mpy run on qemu-system-xtensa (`-M sim -cpu de233_fpu -semihosting`): the relocated
text of the .mpy itself, placed and relocated as MicroPython's loader does (codegen.natmod.mpyfile.relocate), its
kernel functions called by a small bare-metal harness (xtensa_sim/harness.c, built by the same LLVM route and linked
by mpy_ld) after a start-up that sets up the register windows, the FPU and the instruction counter (xtensa_sim/boot.s).
assemble_boot, link_objects and run_images serve every harness (codegen.natmod.xtensa_eskf's too); the steps' format
and ICOUNT reader the harnesses share are xtensa_sim/sim_steps.h.

de233_fpu is an LX7 with windowed registers, MUL32, DIV32, loops, booleans and a single-precision FPU, as the ESP32's
LX6; it lacks one option the ESP32 has, MUL32_HIGH (MULUH/MULSH). llc -mcpu=esp32 emits those only in the binding
(dr_native.c's divisions of a buffer length by a constant), which needs MicroPython's runtime anyway: the harness
calls the kernel's functions, the binding is run on the ARM ports. `MISSING_ON_DE233` names them; `uses_missing`
checks the kernel's code is free of them.

Memory (the sim machine's RAM from 0): boot at the reset VECBASE 0x2000, harness 0x10000, dr_native text 0x40000 and
rodata 0x60000, input 0x100000, workspace 0x280000, output 0x300000, stack below 0x7f0000. ICOUNT counts every
instruction at interrupt level 0: each step's count is exact.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codegen.errors import UserError
from codegen.natmod import linkmap, mpyfile, xtensa, xtensa_llvm
from codegen.natmod.windows import OUT_FLOATS, Answer
from codegen.tools import find_tool

SIM = Path(__file__).with_name("xtensa_sim")
VECBASE, START = 0x2000, 0x2400
HARNESS_TEXT, HARNESS_RODATA = 0x10000, 0x30000
MODULE_TEXT, MODULE_RODATA, MODULE_BSS = 0x40000, 0x60000, 0x70000
FUN_TABLE, QSTR_TABLE = 0x80000, 0x90000  # zero-filled stand-ins: the kernel never touches them
INPUT, WORKSPACE, OUTPUT = 0x100000, 0x280000, 0x300000
MAGIC = 0x31585244  # "DRX1"
HEADER_WORDS = 16
FUNCTIONS = ("dr_config_init", "dr_state_init", "dr_calibrate", "dr_process", "dr_fused_config_init",
             "dr_fused_state_init", "dr_fused_calibrate", "dr_fused_process", "dr_fused_position", "dr_fused_gps")
MISSING_ON_DE233 = ("muluh", "mulsh")  # the MUL32_HIGH option: RRR, op0 = 0, op1 = 2, op2 = 0xa / 0xb
EXCCAUSE = {0: "IllegalInstruction", 3: "LoadStoreError", 6: "IntegerDivideByZero", 9: "LoadStoreAlignment",
            20: "InstFetchProhibited", 28: "LoadProhibited", 29: "StoreProhibited", 32: "Coprocessor0Disabled"}


class XtensaSimError(UserError):
    pass


@dataclass
class Harness:
    boot: bytes
    mpy: mpyfile.NativeMpy


def _llvm(tool: str) -> str:
    path = find_tool(f"{tool}-{xtensa_llvm.LLVM_VERSION}")
    if path is None:
        raise XtensaSimError(f"{tool}-{xtensa_llvm.LLVM_VERSION} is not installed", hint=xtensa_llvm.INSTALL_HINT)
    return path


def _text_of(obj: Path) -> bytes:
    from elftools.elf.elffile import ELFFile

    with open(obj, "rb") as f:
        return bytes(ELFFile(f).get_section_by_name(".text").data())


def assemble_boot(work: Path) -> bytes:
    """The start-up every harness runs after (xtensa_sim/boot.s: register windows, FPU, ICOUNT), assembled for the
    ESP32 in `work`: its text, to be loaded at VECBASE."""
    work.mkdir(parents=True, exist_ok=True)
    boot = work / "boot.o"
    done = subprocess.run([_llvm("llvm-mc"), "-triple=xtensa", "-mcpu=esp32", "-filetype=obj", str(SIM / "boot.s"),
                           "-o", str(boot)], capture_output=True, text=True)
    if done.returncode:
        raise XtensaSimError(f"boot.s does not assemble:\n{done.stderr}")
    return _text_of(boot)


def link_objects(objects: list[Path], tree: Path, out: Path, what: str) -> mpyfile.NativeMpy:
    """The objects (the first holds the image's mpy_init) linked by the MicroPython tree's mpy_ld into `out` as
    xtensawin code, parsed; `what` names the image in an error."""
    done = subprocess.run([sys.executable, str(tree / "tools" / "mpy_ld.py"), "--arch", "xtensawin", "-o", str(out),
                           *map(str, objects)], capture_output=True, text=True, cwd=out.parent)
    if done.returncode:
        raise XtensaSimError(f"mpy_ld did not link {what}:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
    return mpyfile.parse(out.read_bytes(), out.name)


def build_harness(native_dir: Path, tree: Path, work: Path) -> Harness:
    """Assemble boot.s and build harness.c against the kernel headers in native_dir (a generated OUT/native)."""
    boot = assemble_boot(work)
    obj = work / "harness.o"
    xtensa_llvm.compile_object(SIM / "harness.c", obj, ["-I", str(native_dir), "-I", str(SIM), "-std=c99", "-O2",
                                                        "-Wall", "-Werror"])
    return Harness(boot, link_objects([obj], tree, work / "harness.mpy", "the harness"))


def function_offsets(link: linkmap.LinkMap) -> dict:
    """Text offset of every function the objects define, from the linker's placements."""
    from elftools.elf.elffile import ELFFile

    offsets = {}
    for obj in link.objects:
        with open(obj, "rb") as f:
            elf = ELFFile(f)
            for sym in elf.get_section_by_name(".symtab").iter_symbols():
                if sym["st_info"]["type"] == "STT_FUNC" and isinstance(sym["st_shndx"], int):
                    section = elf.get_section(sym["st_shndx"]).name
                    offsets[sym.name] = link.placement(obj, section).addr + sym["st_value"]
    return offsets


def uses_missing(module: mpyfile.NativeMpy, start: int, end: int) -> list:
    """(offset, mnemonic) of MULUH/MULSH in text[start:end], found by a linear decode of 2- and 3-byte
    instructions (a function's own bytes: no data inside)."""
    found, pc, code = [], start, module.text
    while pc < end:
        op0 = code[pc] & 0xF
        if op0 >= 8:  # narrow (density) instruction
            pc += 2
            continue
        insn = xtensa.word24(code, pc)
        op1, op2 = (insn >> 16) & 0xF, (insn >> 20) & 0xF
        if op0 == 0 and op1 == 2 and op2 in (0xA, 0xB):
            found.append((pc, MISSING_ON_DE233[op2 - 0xA]))
        pc += 3
    return found


def sample_step(item: tuple) -> bytes:
    """A calibration ("C", counts) or window ("P", counts, dt_us) step as xtensa_sim/sim_steps.h reads it."""
    samples = np.ascontiguousarray(item[1], dtype="<i2").reshape(-1, 6)
    step = struct.pack("<II", ord(item[0]), len(samples)) + samples.tobytes()
    if item[0] == "P":
        step += np.ascontiguousarray(item[2], dtype="<i4").tobytes()
    return step


def _input(steps: list, algorithm: str, state_floats: int, functions: list[int]) -> bytes:
    body = bytearray()
    for item in steps:
        kind = item[0]
        if kind in ("C", "P"):
            body += sample_step(item)
        else:
            body += struct.pack("<IIffff", ord("G"), 4, *item[1:5])
    header = struct.pack("<6I", MAGIC, 1 if algorithm == "fused" else 0, len(steps), state_floats, WORKSPACE, OUTPUT)
    header += struct.pack(f"<{len(functions)}I", *functions)
    return header + bytes(4 * HEADER_WORDS - len(header)) + bytes(body)


def run(module: mpyfile.NativeMpy, link: linkmap.LinkMap, harness: Harness, steps: list, algorithm: str,
        state_floats: int, timeout: float = 600) -> list[Answer]:
    """Run `steps` (codegen.natmod.windows' format) through `algorithm` in the module's own code."""
    offsets = function_offsets(link)
    missing = [name for name in FUNCTIONS if name not in offsets]
    if missing:
        raise XtensaSimError(f"the module defines no {', '.join(missing)}")
    bases = {"text": MODULE_TEXT, "rodata": MODULE_RODATA, "bss": MODULE_BSS, "mp_fun_table": FUN_TABLE,
             "qstr_table": QSTR_TABLE, "obj_table": QSTR_TABLE}
    text, rodata = mpyfile.relocate(module, bases)
    h_text, h_rodata = mpyfile.relocate(harness.mpy, dict(bases, text=HARNESS_TEXT, rodata=HARNESS_RODATA))
    blob = _input(steps, algorithm, state_floats, [MODULE_TEXT + offsets[name] for name in FUNCTIONS])
    data = run_images({"boot.bin": (harness.boot, VECBASE), "harness.bin": (bytes(h_text), HARNESS_TEXT),
                       "harness-rodata.bin": (bytes(h_rodata), HARNESS_RODATA), "text.bin": (bytes(text), MODULE_TEXT),
                       "rodata.bin": (bytes(rodata), MODULE_RODATA), "input.bin": (blob, INPUT)},
                      "the ESP32 code", timeout)
    words = 2 + OUT_FLOATS + state_floats
    if len(data) != 4 * words * len(steps):
        raise XtensaSimError(f"the harness wrote {len(data)} bytes, expected {4 * words * len(steps)}")
    answers = []
    for k in range(len(steps)):
        record = data[4 * words * k:4 * words * (k + 1)]
        took, code = struct.unpack_from("<Ii", record)
        values = np.frombuffer(record[8:], dtype="<f4")
        out = values[:OUT_FLOATS].copy()
        if steps[k][0] == "C":
            out[0] = float(code)  # the verdict, where the MicroPython driver puts it
        answers.append(Answer(float(took), out, values[OUT_FLOATS:].copy()))
    return answers



def run_images(images: dict[str, tuple[bytes, int]], what: str, timeout: float) -> bytes:
    """Load each image (name -> (bytes, address); an empty one is skipped) raw into qemu-system-xtensa's sim
    machine (de233_fpu, semihosting), start at START (boot.s) and return what the harness wrote to stdout; an
    exception stop is an XtensaSimError naming its cause, `what` naming the code that stopped."""
    qemu = find_tool("qemu-system-xtensa")
    if qemu is None:
        raise XtensaSimError("qemu-system-xtensa is not installed", hint="apt-get install qemu-system-misc")
    with tempfile.TemporaryDirectory(prefix="dr-xtensa-") as tmp:
        command = [qemu, "-M", "sim", "-cpu", "de233_fpu", "-semihosting", "-nographic", "-monitor", "none",
                   "-serial", "none"]
        for name, (data, address) in images.items():
            if not data:
                continue
            (Path(tmp) / name).write_bytes(data)
            command += ["-device", f"loader,file={Path(tmp) / name},addr={address:#x},force-raw=on"]
        command += ["-device", f"loader,addr={START:#x},cpu-num=0"]
        done = subprocess.run(command, capture_output=True, timeout=timeout)
    if done.returncode:
        cause = done.returncode - 64
        stop = EXCCAUSE.get(cause, f"exception cause {cause}") if 0 <= cause < 64 else f"exit {done.returncode}"
        raise XtensaSimError(f"{what} stopped on qemu-system-xtensa: {stop}\n"
                             f"{done.stderr.decode(errors='replace')[-1000:]}")
    return done.stdout
