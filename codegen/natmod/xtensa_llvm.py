"""ESP32 (xtensawin) objects from Debian's LLVM, laid out as MicroPython's natmod linker expects GCC's.

No registry ships xtensa-esp32-elf-gcc; Debian's clang-22, llc-22 and llvm-mc-22 emit ESP32 code (`-mcpu=esp32`:
windowed ABI, single-precision FPU, MUL32/DIV32). MicroPython's `py/dynruntime.mk` runs `$(CROSS)gcc`, so this module
is installed as the command `deadreckon-xtensa-llvm-gcc` and `deadreckon build` passes
`CROSS=<that folder>/deadreckon-xtensa-llvm-`. It answers the two questions dynruntime.mk asks (`-dumpmachine`,
`-c SOURCE -o OBJECT`) and refuses the rest plainly.

One source becomes one object in four steps:
  1. clang-22 --target=xtensa: C -> LLVM IR, freestanding (clang's own headers, picolibc's for string.h), the
     CFLAGS dynruntime.mk gives (-I, -D, -U, -std, -O, -W), and -ffp-contract=off: GCC in -std=c99 mode does not
     fuse a*b+c either, and the host build the tests compare with rounds every product;
  2. llc-22 -mcpu=esp32 -function-sections: IR -> assembly (without -function-sections llc stops at "fixup value
     must be 4-byte aligned");
  3. the assembly reshaped into GNU as's layout (`reshape`): literal pools (`.literal_position`, `.literal X, v`,
     which LLVM keeps inside .text, giving R_XTENSA_32 relocations mpy_ld rejects) move into one `.literal`
     section; every `.text.*` becomes one `.text.<object>` (padded by one word before mpy_init, so its offset is
     never 0: mpy_ld's first pass computes the entry jump as offset - 4); `.rodata` (the function objects, which
     hold pointers) becomes `.data.rel.ro.<object>`, where GCC puts it (named per object: see `reshape`);
  4. llvm-mc-22 assembles it, and the object is fixed where llvm-mc's output differs from GNU as's (`fix_object`):
     a `.literal` word that points into a section carries its offset in the data with addend 0 (GNU as style, the
     form mpy_ld's literal table reads), and every relocated L32R has imm16 = 0. llvm-mc leaves 0xffff there when
     the instruction is not 4-byte aligned, and mpy_ld adds its PC-relative value to the field as unsigned, so
     such an L32R would load from 0x30000 bytes below its literal (mpy_ld only reads the RELA addend for the
     literal's identity, never the field).
`codegen.natmod.verify` checks every relocated instruction of the linked .mpy afterwards.
"""

from __future__ import annotations

import re
import struct
import subprocess
import sys
from pathlib import Path
from typing import Optional, Sequence

from codegen.tools import find_tool

LLVM_VERSION = "22"
TOOLS = (f"clang-{LLVM_VERSION}", f"llc-{LLVM_VERSION}", f"llvm-mc-{LLVM_VERSION}")
COMMAND = "deadreckon-xtensa-llvm-gcc"
CROSS_SUFFIX = "gcc"
MACHINE = "xtensa-esp32-elf"  # what `-dumpmachine` answers, as xtensa-esp32-elf-gcc does
LIBC_HEADERS = Path("/usr/lib/picolibc/arm-none-eabi/include")  # string.h etc.: target-neutral declarations
KEPT_FLAGS = ("-I", "-D", "-U", "-std", "-O", "-W")
INSTALL_HINT = (f"install Debian's LLVM {LLVM_VERSION}: `apt-get install clang-{LLVM_VERSION} llvm-{LLVM_VERSION} "
                "picolibc-arm-none-eabi` (or put xtensa-esp32-elf-gcc on PATH)")

SHT_RELA = 4
STT_SECTION = 3
R_XTENSA_32 = 1
R_XTENSA_SLOT0_OP = 20

_TEXT_SECTION = re.compile(r"\s*\.section\s+\.text[.\w]*\s*,")
_RODATA_SECTION = re.compile(r"\s*\.section\s+\.rodata\s*,")
_LITERAL = re.compile(r"\s*\.literal\s+([^,\s]+)\s*,\s*(.+?)\s*$")


class RouteError(Exception):
    """A step of the route failed; the message says which and what the tool printed."""


def missing_tools() -> list[str]:
    """The LLVM commands this route needs that are not installed."""
    missing = [tool for tool in TOOLS if find_tool(tool) is None]
    if not LIBC_HEADERS.is_dir():
        missing.append(f"{LIBC_HEADERS} (Debian package picolibc-arm-none-eabi)")
    return missing


def cross_prefix() -> Optional[str]:
    """The CROSS value for dynruntime.mk (`$(CROSS)gcc` is this module's command), or None if not installed."""
    command = find_tool(COMMAND)
    if command is None or not command.endswith(CROSS_SUFFIX):
        return None
    return command[: -len(CROSS_SUFFIX)]


def reshape(assembly: str, unit: str) -> str:
    """llc's assembly with GNU as's section layout (see the module docstring, step 3). `unit` names this object's
    sections (.text.UNIT, .data.rel.ro.UNIT): mpy_ld takes a literal that points into a section for the same GOT
    entry as any other object's literal with the same section name and offset, so a static function of dr_fused.o
    at .text+0xbb8 and one of dr_kernel.o at the same offset once shared one entry, and half their callers called
    the wrong function (codegen.natmod.verify caught it). Every name still starts with what mpy_ld looks for."""
    tag = re.sub(r"\W", "_", unit)
    text = f'\t.section\t.text.{tag},"ax",@progbits'
    rodata = f'\t.section\t.data.rel.ro.{tag},"aw",@progbits'
    out = []
    for line in assembly.splitlines():
        literal = _LITERAL.match(line)
        if _TEXT_SECTION.match(line):
            out.append(text)
        elif _RODATA_SECTION.match(line):
            out.append(rodata)
        elif line.strip() == ".literal_position":
            continue
        elif literal:
            label, value = literal.groups()
            out += ['\t.section\t.literal,"a",@progbits', "\t.p2align\t2", f"{label}:", f"\t.4byte\t{value}", text]
        else:
            out.append(line)
    if any(line.startswith("mpy_init:") for line in out):
        out[1:1] = [text, "\t.p2align\t2", "\t.4byte\t0"]
    return "\n".join(out) + "\n"


def _sections(data: bytes) -> list[tuple]:
    """ELF32 little-endian section headers: (name, type, offset, size, link, info, entsize) per section."""
    if data[:4] != b"\x7fELF" or data[4] != 1 or data[5] != 1:
        raise RouteError("llvm-mc did not write a 32-bit little-endian ELF object")
    shoff = struct.unpack_from("<I", data, 0x20)[0]
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x2E)
    raw = [struct.unpack_from("<IIIIIIIIII", data, shoff + i * shentsize) for i in range(shnum)]
    names = raw[shstrndx][4]

    def name(offset):
        start = names + offset
        return data[start:data.index(b"\0", start)].decode()

    return [(name(h[0]), h[1], h[4], h[5], h[6], h[7], h[9]) for h in raw]


def fix_object(path: Path, clear_l32r: bool = True) -> tuple[int, int]:
    """Rewrite the object at `path` as GNU as would have written it (module docstring, step 4); returns (literal
    addends moved into their data, L32R immediates cleared). `clear_l32r=False` keeps llvm-mc's immediates (the
    tests show the verifier catching what mpy_ld makes of them)."""
    data = bytearray(path.read_bytes())
    sections = _sections(data)
    moved = cleared = 0
    for name, kind, offset, size, link, info, entsize in sections:
        if kind != SHT_RELA or not name.startswith((".rela.literal", ".rela.text")):
            continue
        target_name, _, target_offset, target_size, _, _, _ = sections[info]
        symtab_offset = sections[link][2]
        for k in range(size // 12):
            entry = offset + 12 * k
            r_offset, r_info, r_addend = struct.unpack_from("<IIi", data, entry)
            r_type, r_sym = r_info & 0xFF, r_info >> 8
            if name.startswith(".rela.literal") and r_type == R_XTENSA_32:
                st_info = data[symtab_offset + 16 * r_sym + 12]
                if st_info & 0xF == STT_SECTION and r_addend:
                    struct.pack_into("<I", data, target_offset + r_offset, r_addend & 0xFFFFFFFF)
                    struct.pack_into("<i", data, entry + 8, 0)
                    moved += 1
            elif clear_l32r and target_name.startswith(".text") and r_type == R_XTENSA_SLOT0_OP:
                at = target_offset + r_offset
                if r_offset + 3 <= target_size and data[at] & 0xF == 1 and (data[at + 1] or data[at + 2]):
                    data[at + 1] = data[at + 2] = 0  # L32R imm16: the relocation alone says where it loads from
                    cleared += 1
    path.write_bytes(bytes(data))
    return moved, cleared


def _run(step: str, command: list[str]) -> None:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode:
        raise RouteError(f"{step} failed ({' '.join(command[:2])} ...):\n{(done.stderr or done.stdout).strip()}")


def compile_object(source: Path, output: Path, flags: Sequence[str] = (), clear_l32r: bool = True) -> None:
    """SOURCE (C) -> OUTPUT (an ELF object mpy_ld links for xtensawin); `clear_l32r` as in fix_object."""
    missing = missing_tools()
    if missing:
        raise RouteError(f"the LLVM Xtensa route needs {', '.join(missing)}; {INSTALL_HINT}")
    clang, llc, mc = (find_tool(tool) for tool in TOOLS)
    resource = subprocess.run([clang, "-print-resource-dir"], capture_output=True, text=True).stdout.strip()
    ir, asm = output.with_suffix(".ll"), output.with_suffix(".s")
    _run("clang (C -> LLVM IR)", [
        clang, "--target=xtensa", "-ffreestanding", "-nostdinc", "-isystem", f"{resource}/include",
        "-isystem", str(LIBC_HEADERS), *flags, "-Wno-typedef-redefinition", "-ffp-contract=off",
        "-S", "-emit-llvm", str(source), "-o", str(ir)])
    _run("llc (IR -> ESP32 assembly)", [llc, "-mtriple=xtensa", "-mcpu=esp32", "-O2", "-function-sections",
                                        str(ir), "-o", str(asm)])
    shaped = output.with_suffix(".mpy_ld.s")
    shaped.write_text(reshape(asm.read_text(), output.stem))
    _run("llvm-mc (assembly -> object)", [mc, "-triple=xtensa", "-mcpu=esp32", "-filetype=obj", str(shaped),
                                          "-o", str(output)])
    fix_object(output, clear_l32r)


def _gcc_flags(args: Sequence[str]) -> tuple[Optional[str], Optional[str], list[str]]:
    """(source, output, flags kept for clang) from a gcc command line as dynruntime.mk writes it."""
    source = output = None
    flags: list[str] = []
    items = iter(args)
    for arg in items:
        if arg == "-c":
            source = next(items, None)
        elif arg == "-o":
            output = next(items, None)
        elif arg in ("-I", "-D", "-U"):
            flags += [arg, next(items, "")]
        elif arg.startswith(KEPT_FLAGS):
            flags.append(arg)
    return source, output, flags


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if args == ["-dumpmachine"]:
        print(MACHINE)
        return 0
    if any(a.startswith(("-print-libgcc", "--print-libgcc", "-print-file-name", "--print-file-name")) for a in args):
        print(f"{COMMAND}: the LLVM route has no libgcc/libm for Xtensa: build with LINK_RUNTIME=0 (the kernel "
              "needs no runtime helpers on the ESP32's FPU)", file=sys.stderr)
        return 1
    source, output, flags = _gcc_flags(args)
    if source is None or output is None:
        print(f"{COMMAND}: stands in for xtensa-esp32-elf-gcc in MicroPython's natmod build and only compiles "
              f"(-c SOURCE -o OBJECT) or answers -dumpmachine; got: {' '.join(args) or '(no arguments)'}",
              file=sys.stderr)
        return 2
    try:
        compile_object(Path(source), Path(output), flags)
    except RouteError as exc:
        print(f"{COMMAND}: {source}: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
