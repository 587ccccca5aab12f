"""An independent check of an xtensawin dr_native.mpy: every relocated instruction and word decoded from the final
file and compared with what the objects asked for, placed where the linker's map says it placed them.

Inputs: the objects (ELF, read with pyelftools), the linker's map (codegen.natmod.linkmap: section placements, GOT
and literal tables), the .mpy (codegen.natmod.mpyfile) and the tree's mp_fun_table layout (codegen.natmod.abi).
Nothing of mpy_ld's relocation arithmetic is reused. The text is taken at a 4-byte aligned base, as MicroPython
allocates it (L32R addresses depend on the base modulo 4).

For each object:
  - each relocation in .text (R_XTENSA_SLOT0_OP):
      against .literal+k: the instruction is an L32R whose decoded target is a slot of the final GOT or literal
        table that holds what the object's literal k holds: the same 32-bit value (a literal: no load-time
        relocation of that word), or the address of the same symbol (+ addend): a load-time relocation of that
        word to the symbol's region (text, rodata, bss, mp_fun_table, one of its entries, the qstr table) and the
        symbol's offset in that region as the stored word;
      against .text: a CALLn or J whose decoded target is that symbol (+ addend);
  - each R_XTENSA_32 in .data.rel.ro / .rodata*: the final word is relocated to the symbol's region with its offset;
  - every byte of every placed section equals the object's, except inside the fields above.
And for the file: the header is the tree's .mpy version for xtensawin, the entry jump at text 0 lands on mpy_init,
and no load-time relocation is left that no check above asked for. One wrong target fails the build.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

from codegen.errors import UserError
from codegen.natmod import xtensa
from codegen.natmod.abi import TreeAbi
from codegen.natmod.linkmap import LinkMap
from codegen.natmod.mpyfile import NativeMpy

R_XTENSA_NONE = 0
R_XTENSA_32 = 1
R_XTENSA_DIFF = (17, 18, 19)  # DIFF8/16/32: differences inside one section, no effect on placement
R_XTENSA_SLOT0_OP = 20
R_XTENSA_ASM_EXPAND = 11
SPECIAL_TABLES = {"mp_fun_table": "mp_fun_table", "mp_native_qstr_table": "qstr_table",
                  "mp_native_obj_table": "obj_table"}
MAX_REPORTED = 12


class VerifyError(UserError):
    pass


@dataclass
class Report:
    l32r_got: int = 0
    l32r_lit: int = 0
    branches: int = 0
    data_words: int = 0
    relocations: int = 0
    bytes_compared: int = 0
    problems: list = field(default_factory=list)

    def summary(self) -> str:
        return (f"{self.l32r_got + self.l32r_lit} L32R ({self.l32r_got} GOT, {self.l32r_lit} literal), "
                f"{self.branches} CALL/J, {self.data_words} data words, {self.relocations} load-time relocations, "
                f"{self.bytes_compared} bytes compared")


@dataclass(frozen=True)
class Target:
    """Where a pointer must end up: a region ('text', 'rodata', 'bss', 'mp_fun_table', 'mp_fun_table[k]',
    'qstr_table', 'obj_table') and the offset inside it."""

    region: str
    offset: int


@dataclass
class _Object:
    path: Path
    sections: dict  # name -> (data bytes, index)
    by_index: dict  # index -> name
    symbols: list
    relocations: dict  # target section name -> [(offset, type, symbol, addend)]


def _load(path: Path) -> _Object:
    from elftools.elf.elffile import ELFFile

    with open(path, "rb") as f:
        elf = ELFFile(f)
        symtab = elf.get_section_by_name(".symtab")
        symbols = list(symtab.iter_symbols())
        sections, by_index, relocations = {}, {}, {}
        for index, sec in enumerate(elf.iter_sections()):
            by_index[index] = sec.name
            if sec.header.sh_type in ("SHT_PROGBITS", "SHT_NOBITS"):
                sections[sec.name] = (bytes(sec.data()) if sec.header.sh_type == "SHT_PROGBITS"
                                      else bytes(sec.data_size), index)
        for sec in elf.iter_sections():
            if sec.header.sh_type in ("SHT_RELA", "SHT_REL"):
                target = elf.get_section(sec.header.sh_info).name
                relocations[target] = [(r["r_offset"], r["r_info_type"], symbols[r["r_info_sym"]],
                                        r["r_addend"] if r.is_RELA() else 0) for r in sec.iter_relocations()]
    return _Object(path, sections, by_index, symbols, relocations)


class _Verifier:
    def __init__(self, mpy: NativeMpy, link: LinkMap, abi: TreeAbi):
        self.mpy, self.link, self.abi = mpy, link, abi
        self.objects = [_load(p) for p in link.objects]
        self.report = Report()
        self.claimed: set = set()
        self.masked = {}  # region -> offsets of bytes inside relocated fields (not compared with the objects)
        self.globals = {}
        for obj in self.objects:
            for sym in obj.symbols:
                if sym["st_info"]["bind"] in ("STB_GLOBAL", "STB_WEAK") and isinstance(sym["st_shndx"], int):
                    self.globals[sym.name] = (obj, sym)

    def problem(self, text: str) -> None:
        self.report.problems.append(text)

    def where(self, region: str, offset: int) -> str:
        """A text offset named by the function that holds it."""
        if region == "text":
            best = None
            for obj in self.objects:
                for sym in obj.symbols:
                    if sym["st_info"]["type"] != "STT_FUNC" or not isinstance(sym["st_shndx"], int):
                        continue
                    name = obj.by_index[sym["st_shndx"]]
                    p = self.link.placement(obj.path, name)
                    start = p.addr + sym["st_value"]
                    if start <= offset < start + max(sym["st_size"], 1) and (best is None or start > best[0]):
                        best = (start, sym.name, obj.path.name)
            if best:
                return f"text {offset:#06x} ({best[1]}+{offset - best[0]:#x} in {best[2]})"
        return f"{region} {offset:#06x}"

    # ---- what a symbol reference means in the output
    def target(self, obj: _Object, sym, addend: int) -> Target:
        shndx = sym["st_shndx"]
        if shndx == "SHN_UNDEF":
            if sym.name in SPECIAL_TABLES:
                return Target(SPECIAL_TABLES[sym.name], addend)
            if sym.name in self.globals:
                other, defined = self.globals[sym.name]
                return self.target(other, defined, addend)
            try:
                return Target(f"mp_fun_table[{self.abi.fun_table_index(sym.name)}]", addend)
            except KeyError:
                raise VerifyError(f"{obj.path.name}: {sym.name} is defined nowhere (not in the objects, not in "
                                  "mp_fun_table)")
        if not isinstance(shndx, int):
            raise VerifyError(f"{obj.path.name}: symbol {sym.name} in {shndx}: not something a natmod can use")
        name = obj.by_index[shndx]
        p = self.link.placement(obj.path, name)
        return Target(p.region, p.addr + sym["st_value"] + addend)

    def literal_intent(self, obj: _Object, literal: str, offset: int):
        """What word `offset` of the object's literal section holds: ('value', v) or ('pointer', Target)."""
        data, _ = obj.sections[literal]
        stored = struct.unpack_from("<I", data, offset)[0]
        for r_offset, r_type, sym, addend in obj.relocations.get(literal, ()):
            if r_offset == offset:
                if r_type != R_XTENSA_32:
                    raise VerifyError(f"{obj.path.name}:{literal}+{offset:#x}: relocation type {r_type}")
                return "pointer", self.target(obj, sym, addend + stored)
        return "value", stored

    # ---- the checks
    def pointer_word(self, region: str, offset: int, want: Target, what: str) -> None:
        buf = self.mpy.text if region == "text" else self.mpy.rodata
        if offset % 4 or offset + 4 > len(buf):
            self.problem(f"{what}: the pointer word at {region} {offset:#x} is not an aligned word of the {region}")
            return
        dest = self.mpy.relocations.get((region, offset // 4))
        stored = struct.unpack_from("<I", buf, offset)[0]
        want_region = want.region
        if dest != want_region or stored != want.offset:
            self.problem(f"{what}: the word at {region} {offset:#06x} becomes {dest or 'no relocation'}+{stored:#x} "
                         f"at load time, the object asks for {want_region}+{want.offset:#x}")
        self.claimed.add((region, offset // 4))

    def check_text_relocation(self, obj: _Object, base: int, r_offset: int, r_type: int, sym, addend: int):
        pc = base + r_offset
        code = self.mpy.text
        if r_type != R_XTENSA_SLOT0_OP:
            if r_type in (R_XTENSA_NONE, R_XTENSA_ASM_EXPAND, *R_XTENSA_DIFF):
                return
            self.problem(f"{self.where('text', pc)}: relocation type {r_type} in .text is not one this check knows")
            return
        section = obj.by_index.get(sym["st_shndx"]) if isinstance(sym["st_shndx"], int) else None
        if section is not None and section.startswith(".literal"):
            if not xtensa.is_l32r(code, pc):
                found = code[pc:pc + 3].hex()
                self.problem(f"{self.where('text', pc)}: expected an L32R (literal load), found {found}")
                return
            self.masked.setdefault("text", set()).update((pc + 1, pc + 2))  # imm16; the opcode byte stays
            kind, want = self.literal_intent(obj, section, sym["st_value"] + addend)
            loads = xtensa.l32r_target(code, pc)
            if kind == "value":
                self.report.l32r_lit += 1
                in_lit = self.link.lit_addr <= loads < self.link.lit_addr + self.link.lit_size
                got = struct.unpack_from("<I", code, loads)[0] if 0 <= loads <= len(code) - 4 else None
                if not in_lit or got != want or ("text", loads // 4) in self.mpy.relocations:
                    shown = "outside the text" if got is None else f"{got:#010x}"
                    self.problem(f"{self.where('text', pc)}: L32R loads text {loads & 0xFFFFFFFF:#06x} ({shown}), "
                                 f"the literal is {want:#010x} in the linker's literal table")
            else:
                self.report.l32r_got += 1
                in_got = self.link.got_addr <= loads < self.link.got_addr + self.link.got_size
                if not in_got:
                    self.problem(f"{self.where('text', pc)}: L32R loads text {loads & 0xFFFFFFFF:#06x}, outside "
                                 f"the GOT ({self.link.got_addr:#x}..{self.link.got_addr + self.link.got_size:#x}) "
                                 f"where the pointer to {want.region}+{want.offset:#x} must be")
                    return
                self.pointer_word("text", loads, want, self.where("text", pc) + " L32R")
            return
        self.masked.setdefault("text", set()).update((pc, pc + 1, pc + 2))  # the offset spans all 3 bytes
        branch = xtensa.decode_branch(code, pc)
        want = self.target(obj, sym, addend)
        self.report.branches += 1
        if branch is None or want.region != "text" or branch.target != want.offset:
            found = f"{branch.mnemonic} to {branch.target:#x}" if branch else code[pc:pc + 3].hex()
            self.problem(f"{self.where('text', pc)}: {found}, the object calls {sym.name or 'its section'}"
                         f"+{addend:#x} at text {want.offset:#x}")

    def check_data_relocations(self, obj: _Object, name: str, region: str, base: int) -> None:
        data, _ = obj.sections[name]
        for r_offset, r_type, sym, addend in obj.relocations.get(name, ()):
            if r_type != R_XTENSA_32:
                self.problem(f"{obj.path.name}:{name}+{r_offset:#x}: relocation type {r_type} in data")
                continue
            self.report.data_words += 1
            stored = struct.unpack_from("<I", data, r_offset)[0]
            self.masked.setdefault(region, set()).update(range(base + r_offset, base + r_offset + 4))
            self.pointer_word(region, base + r_offset, self.target(obj, sym, addend + stored),
                              f"{obj.path.name}:{name}+{r_offset:#x}")

    def compare_bytes(self, obj: _Object, name: str, region: str, base: int) -> None:
        data, _ = obj.sections[name]
        final = self.mpy.text if region == "text" else self.mpy.rodata if region == "rodata" else None
        if final is None:
            return
        masked = self.masked.get(region, set())
        differ = [i for i in range(len(data)) if base + i not in masked and final[base + i] != data[i]]
        self.report.bytes_compared += len(data)
        for i in differ[:3]:
            self.problem(f"{self.where(region, base + i)}: byte {final[base + i]:#04x}, the object has {data[i]:#04x} "
                         f"({obj.path.name}:{name}+{i:#x}) outside any relocated field")
        if len(differ) > 3:
            self.problem(f"{obj.path.name}:{name}: {len(differ) - 3} more bytes differ")

    def run(self) -> Report:
        header = self.mpy.header
        if header.arch != "xtensawin" or (header.version, header.sub_version) != (self.abi.mpy_version,
                                                                                 self.abi.mpy_sub_version):
            self.problem(f"header: .mpy {header.format} for {header.arch}, expected {self.abi.mpy_format} for "
                         "xtensawin")
        for obj in self.objects:
            for name in obj.sections:
                if not name.startswith((".text", ".rodata", ".data.rel.ro")) or not obj.sections[name][0]:
                    continue
                p = self.link.placement(obj.path, name)
                if name.startswith(".text"):
                    for r_offset, r_type, sym, addend in obj.relocations.get(name, ()):
                        self.check_text_relocation(obj, p.addr, r_offset, r_type, sym, addend)
                else:
                    self.check_data_relocations(obj, name, p.region, p.addr)
        for obj in self.objects:
            for name in obj.sections:
                if name.startswith((".text", ".rodata", ".data.rel.ro")) and obj.sections[name][0]:
                    p = self.link.placement(obj.path, name)
                    self.compare_bytes(obj, name, p.region, p.addr)
        self.check_entry()
        unclaimed = sorted(set(self.mpy.relocations) - self.claimed)
        self.report.relocations = len(self.mpy.relocations)
        for region, index in unclaimed[:MAX_REPORTED]:
            self.problem(f"{region} word at {index * 4:#06x} is relocated at load time "
                         f"(+{self.mpy.relocations[(region, index)]}) but no instruction or pointer asks for it")
        return self.report

    def check_entry(self) -> None:
        if "mpy_init" not in self.globals:
            self.problem("no mpy_init in the objects")
            return
        obj, sym = self.globals["mpy_init"]
        want = self.target(obj, sym, 0)
        branch = xtensa.decode_branch(self.mpy.text, 0)
        self.report.branches += 1
        if branch is None or branch.mnemonic != "j" or branch.target != want.offset:
            self.problem(f"entry: text 0 holds {self.mpy.text[:3].hex()}, not a J to mpy_init at {want.offset:#x}")


def verify(mpy: NativeMpy, link: LinkMap, abi: TreeAbi, name: str = "dr_native.mpy") -> Report:
    """Check `mpy` against the objects and the link map; raise VerifyError listing the wrong targets."""
    report = _Verifier(mpy, link, abi).run()
    if report.problems:
        shown = "\n  ".join(report.problems[:MAX_REPORTED])
        more = len(report.problems) - MAX_REPORTED
        raise VerifyError(
            f"{name} is not what the linker meant: {len(report.problems)} wrong target(s)\n  {shown}"
            + (f"\n  ... and {more} more" if more > 0 else ""),
            hint="the module would load garbage on the board; it was not installed into the app")
    return report

