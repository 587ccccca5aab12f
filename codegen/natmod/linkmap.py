"""What MicroPython's natmod linker (tools/mpy_ld.py) says it did, read from its `-vvv` log: where each input
section went, and its GOT and literal tables. The verifier checks the bytes of the .mpy against these statements
and against the objects, never against mpy_ld's arithmetic.

    sections:
      00000004 GOT size=220                   <- region text: GOT, LIT, then every object's .text in link order
      000001dc .text size=2536
      00000000 .data.rel.ro size=128          <- region rodata (xtensawin keeps rodata apart)
    GOT: 00000004
      00000008 .text+0x290 -> .text+0000046c  <- GOT offset, entry name, section + link address
    LIT: 000000e0
      00000000 = 00000fa1                     <- literal table offset, value

The sections are listed without their file; they are matched to the objects by walking the objects in link order
with the linker's own rule for which sections it loads, and every name and size must agree.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

from codegen.errors import UserError

LOADED_PREFIXES = (".text", ".rodata", ".data.rel.ro", ".bss")  # mpy_ld's load_object_file, besides .literal
_SECTION = re.compile(r"^\s+([0-9a-f]{8}) (\S+) size=(\d+)$")
_GOT = re.compile(r"^\s+([0-9a-f]{8}) (\S+) -> (\S+)\+([0-9a-f]{8})$")
_LIT = re.compile(r"^\s+([0-9a-f]{8}) = ([0-9a-f]{8})$")


class LinkMapError(UserError):
    pass


@dataclass(frozen=True)
class Placement:
    """One input section in the output: its object, name, region (text, rodata, bss) and offset there."""

    obj: Path
    name: str
    region: str
    addr: int
    size: int


@dataclass
class LinkMap:
    objects: list
    placements: list = field(default_factory=list)
    got_addr: int = 0
    got_size: int = 0
    lit_addr: int = 0
    lit_size: int = 0
    got: dict = field(default_factory=dict)  # offset -> (name, section name, link address)
    lit: dict = field(default_factory=dict)  # offset -> value

    def placement(self, obj: Path, name: str) -> Placement:
        for p in self.placements:
            if p.obj == obj and p.name == name:
                return p
        raise LinkMapError(f"the linker did not place {obj.name}:{name}")


def region_of(name: str, separate_rodata: bool = True) -> str:
    if name.startswith(".bss"):
        return "bss"
    if separate_rodata and name.startswith((".rodata", ".data.rel.ro")):
        return "rodata"
    return "text"


def link_objects(log: str) -> list[Path]:
    """The objects of the link step, in order, from the mpy_ld command line that `make V=1` echoes."""
    for line in log.splitlines():
        if "mpy_ld.py" in line and "--preprocess" not in line and ".o" in line:
            args = shlex.split(line)
            return [Path(a) for a in args if a.endswith(".o")]
    raise LinkMapError("the build log has no mpy_ld link command (make must run with V=1)")


def loaded_sections(obj_path: Path) -> list[tuple[str, int]]:
    """(name, size) of the sections mpy_ld loads from one object, in its order (literal sections excepted)."""
    from elftools.elf.elffile import ELFFile

    with open(obj_path, "rb") as f:
        elf = ELFFile(f)
        return [(s.name, s.data_size) for s in elf.iter_sections()
                if s.header.sh_type in ("SHT_PROGBITS", "SHT_NOBITS") and s.data_size
                and s.name.startswith(LOADED_PREFIXES)]


def parse(log: str, workdir: Path) -> LinkMap:
    """The link map of the build whose `make V=1` output (with mpy_ld -vvv) is `log`, run in `workdir`."""
    objects = [workdir / p for p in link_objects(log)]
    lines = log.splitlines()
    link = LinkMap(objects=objects)
    listed = _block(lines, "sections:", _SECTION)
    if len(listed) < 2 or listed[0][1] != "GOT" or listed[1][1] != "LIT":
        raise LinkMapError("the linker log does not start its section list with GOT and LIT (not xtensawin?)")
    link.got_addr, link.got_size = int(listed[0][0], 16), int(listed[0][2])
    link.lit_addr, link.lit_size = int(listed[1][0], 16), int(listed[1][2])
    rest = iter(listed[2:])
    for obj in objects:
        for name, size in loaded_sections(obj):
            entry = next(rest, None)
            if entry is None or entry[1] != name or int(entry[2]) != size:
                raise LinkMapError(f"the linker's section list does not match {obj.name}:{name} ({size} bytes); "
                                   f"it lists {entry}")
            link.placements.append(Placement(obj, name, region_of(name), int(entry[0], 16), size))
    if next(rest, None) is not None:
        raise LinkMapError("the linker lists more sections than the objects hold")
    for offset, name, section, addr in _block(lines, "GOT:", _GOT):
        link.got[int(offset, 16)] = (name, section, int(addr, 16))
    for offset, value in _block(lines, "LIT:", _LIT):
        link.lit[int(offset, 16)] = int(value, 16)
    if len(link.got) * 4 != link.got_size or len(link.lit) * 4 != link.lit_size:
        raise LinkMapError("the linker's GOT/LIT listings do not fill their sections")
    return link


def _block(lines: list[str], title: str, pattern: re.Pattern) -> list[tuple]:
    """The lines matching `pattern` right after the line that starts with `title`."""
    for i, line in enumerate(lines):
        if line.startswith(title):
            found = []
            for follow in lines[i + 1:]:
                match = pattern.match(follow)
                if not match:
                    break
                found.append(match.groups())
            return found
    raise LinkMapError(f"the linker log has no '{title}' listing (mpy_ld must run with -vvv)")
