#!/usr/bin/env python3
"""Stands in for xtensa-esp32-elf-gcc (which no registry ships) in MicroPython's natmod build:
`make ARCH=xtensawin CROSS=<folder>/xtensa-llvm-` with this file installed as <folder>/xtensa-llvm-gcc.

`-c SRC -o OBJ`: clang-22 (Xtensa, freestanding, clang's and picolibc's headers) -> LLVM IR -> llc-22 -mcpu=esp32
assembly -> llvm-mc-22 object, with the assembly reshaped into what MicroPython's linker (tools/mpy_ld.py) knows
from GCC objects:
  - literal pools (`.literal_position` / `.literal X, value`, which LLVM places inside .text, giving R_XTENSA_32
    relocations mpy_ld rejects) move into one `.literal` section, as GNU as does;
  - all `.text.*` sections become one `.text` (llc still needs -function-sections, otherwise it stops at "fixup
    value must be 4-byte aligned"), padded by 4 bytes so that mpy_init is not at offset 0 (mpy_ld's first pass
    computes the entry jump as offset - 4);
  - `.rodata` holding pointers (the function objects) becomes `.data.rel.ro`, where GCC puts it;
  - relocations in .literal against a section symbol carry their offset in the data with addend 0 (GNU as style,
    which mpy_ld's literal table expects) instead of llvm-mc's RELA addend.
"""
import re
import struct
import subprocess
import sys


def reshape(assembly: str) -> str:
    out = []
    for line in assembly.splitlines():
        if re.match(r"\s*\.section\s+\.text", line):
            out.append('\t.section\t.text,"ax",@progbits')
        elif re.match(r"\s*\.section\s+\.rodata,", line):
            out.append('\t.section\t.data.rel.ro,"aw",@progbits')
        elif re.match(r"\s*\.literal_position", line):
            continue
        elif re.match(r"\s*\.literal\s+([^,]+),\s*(.+)$", line):
            label, value = re.match(r"\s*\.literal\s+([^,]+),\s*(.+)$", line).groups()
            out += ['\t.section\t.literal,"a",@progbits', "\t.p2align\t2", f"{label}:", f"\t.4byte\t{value}",
                    '\t.section\t.text,"ax",@progbits']
        else:
            out.append(line)
    if any(line.startswith("mpy_init:") for line in out):
        out.insert(1, '\t.section\t.text,"ax",@progbits\n\t.p2align\t2\n\t.4byte\t0')
    return "\n".join(out) + "\n"


def literal_addends_in_data(path: str) -> None:
    """ELF32 little endian: for .rela.literal entries against STT_SECTION symbols, move the addend into the data."""
    data = bytearray(open(path, "rb").read())
    shoff = struct.unpack_from("<I", data, 0x20)[0]
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x2E)
    sections = [struct.unpack_from("<IIIIIIIIII", data, shoff + i * shentsize) for i in range(shnum)]
    names = sections[shstrndx][4]

    def name(section):
        start = names + section[0]
        return data[start:data.index(b"\0", start)].decode()

    for section in sections:
        if section[1] != 4 or name(section) != ".rela.literal":  # SHT_RELA
            continue
        target, symtab = sections[section[7]], sections[section[6]]
        for k in range(section[5] // 12):
            entry = section[4] + 12 * k
            r_offset, r_info, r_addend = struct.unpack_from("<IIi", data, entry)
            st_info = data[symtab[4] + 16 * (r_info >> 8) + 12]
            if st_info & 0xF == 3 and r_addend:  # STT_SECTION
                struct.pack_into("<I", data, target[4] + r_offset, r_addend & 0xFFFFFFFF)
                struct.pack_into("<i", data, entry + 8, 0)
    open(path, "wb").write(data)


def main(args):
    out = args[args.index("-o") + 1]
    source = args[args.index("-c") + 1]
    keep = [a for a in args if a.startswith(("-I", "-D", "-std", "-O"))]
    resource = subprocess.run(["clang-22", "-print-resource-dir"], capture_output=True, text=True).stdout.strip()
    ir, asm = out + ".ll", out + ".s"
    subprocess.run(["clang-22", "--target=xtensa", "-ffreestanding", "-nostdinc", "-isystem", resource + "/include",
                    "-isystem", "/usr/lib/picolibc/arm-none-eabi/include", *keep, "-Wno-typedef-redefinition",
                    "-S", "-emit-llvm", source, "-o", ir], check=True)
    subprocess.run(["llc-22", "-mtriple=xtensa", "-mcpu=esp32", "-O2", "-function-sections", ir, "-o", asm],
                   check=True)
    with open(asm + ".mpy_ld.s", "w") as f:
        f.write(reshape(open(asm).read()))
    subprocess.run(["llvm-mc-22", "-triple=xtensa", "-mcpu=esp32", "-filetype=obj", asm + ".mpy_ld.s", "-o", out],
                   check=True)
    literal_addends_in_data(out)


if __name__ == "__main__":
    main(sys.argv[1:])
