"""A native-module .mpy as MicroPython's loader reads it (py/persistentcode.c: mp_raw_code_load, load_raw_code,
mp_native_relocate), written independently of MicroPython's tools so the verifier does not trust their code.

    header      'M', version, flags (arch << 2 | sub-version, 0x40 = arch flags follow), small-int bits
    [arch flags uint]  n_qstr uint  n_obj uint  qstrs  (objects: none in a natmod)
    kind_len    uint: text length << 3 | has-children << 2 | kind (2 = viper: a natmod)
    text        machine code: the entry jump, then (xtensa) GOT and literal table, then the code
    scope flags uint (0x10 relocations follow, 0x20 rodata, 0x40 bss)
    [rodata size] [bss size] [rodata]
    relocations bytes until 0xff: each says "add base X to the next n words at this text/rodata word"
"""

from __future__ import annotations

from dataclasses import dataclass, field

from codegen.errors import UserError

ARCH_NAMES = ("none", "x86", "x64", "armv6", "armv6m", "armv7m", "armv7em", "armv7emsp", "armv7emdp", "xtensa",
              "xtensawin", "rv32imc", "rv64imc")
KIND_VIPER = 2
SCOPE_VIPERRELOC = 0x10
SCOPE_VIPERRODATA = 0x20
SCOPE_VIPERBSS = 0x40
# relocation destinations (mp_native_relocate): 0..2 text/rodata/bss, 6 qstr table, 7 object table,
# 8 mp_fun_table itself, 9 + k entry k of mp_fun_table
DEST_NAMES = {0: "text", 1: "rodata", 2: "bss", 6: "qstr_table", 7: "obj_table", 8: "mp_fun_table"}
WORD = 4


@dataclass(frozen=True)
class Header:
    version: int
    sub_version: int
    arch: str
    small_int_bits: int

    @property
    def format(self) -> str:
        return f"{self.version}.{self.sub_version}"


@dataclass
class NativeMpy:
    """The parts of a natmod .mpy the checks need; relocations maps (region, word index) -> destination name
    ("text", "rodata", "bss", "qstr_table", "obj_table", "mp_fun_table" or "mp_fun_table[k]")."""

    header: Header
    qstrs: list
    text: bytes
    text_offset: int  # where text starts in the file
    rodata: bytes
    bss_size: int
    relocations: dict = field(default_factory=dict)


class MpyFormatError(UserError):
    pass


class _Reader:
    def __init__(self, data: bytes, name: str):
        self.data, self.pos, self.name = data, 0, name

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise MpyFormatError(f"{self.name}: ends early at byte {self.pos}")
        self.pos += 1
        return self.data[self.pos - 1]

    def bytes(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise MpyFormatError(f"{self.name}: ends early: {n} bytes wanted at byte {self.pos}")
        self.pos += n
        return self.data[self.pos - n:self.pos]

    def uint(self) -> int:
        value = 0
        while True:
            b = self.byte()
            value = value << 7 | (b & 0x7F)
            if not b & 0x80:
                return value


def read_header(data: bytes, name: str = ".mpy") -> Header:
    if len(data) < 4 or data[0:1] != b"M":
        raise MpyFormatError(f"{name} is not a .mpy file (it does not start with 'M')")
    arch = data[2] >> 2 & 0xF
    return Header(version=data[1], sub_version=data[2] & 3,
                  arch=ARCH_NAMES[arch] if arch < len(ARCH_NAMES) else f"arch{arch}", small_int_bits=data[3])


def parse(data: bytes, name: str = ".mpy") -> NativeMpy:
    """Read a natmod .mpy; MpyFormatError names the byte where it stops making sense."""
    header = read_header(data, name)
    r = _Reader(data, name)
    r.bytes(4)
    if data[2] & 0x40:
        r.uint()  # arch flags
    n_qstr, n_obj = r.uint(), r.uint()
    qstrs = []
    for _ in range(n_qstr):
        ref = r.uint()
        if ref & 1:
            qstrs.append(("static", ref >> 1))
        else:
            qstrs.append(r.bytes(ref >> 1).decode("ascii", "replace"))
            r.byte()  # NUL
    if n_obj:
        raise MpyFormatError(f"{name}: {n_obj} constant objects: not a native module as mpy_ld writes it")
    kind_len = r.uint()
    if kind_len & 3 != KIND_VIPER or kind_len & 4:
        raise MpyFormatError(f"{name}: the top-level code is not native viper code without children")
    text_offset = r.pos
    text = r.bytes(kind_len >> 3)
    scope = r.uint()
    rodata_size = r.uint() if scope & SCOPE_VIPERRODATA else 0
    bss_size = r.uint() if scope & SCOPE_VIPERBSS else 0
    rodata = r.bytes(rodata_size)
    mpy = NativeMpy(header, qstrs, text, text_offset, rodata, bss_size)
    if scope & SCOPE_VIPERRELOC:
        _read_relocations(r, mpy)
    if r.pos != len(data):
        raise MpyFormatError(f"{name}: {len(data) - r.pos} bytes after the relocations")
    return mpy


def _read_relocations(r: _Reader, mpy: NativeMpy) -> None:
    region, index = None, None
    sizes = {"text": len(mpy.text) // WORD, "rodata": len(mpy.rodata) // WORD}
    while True:
        op = r.byte()
        if op == 0xFF:
            return
        if op & 1:
            where = r.uint()
            region, index = ("rodata" if where & 1 else "text"), where >> 1
        if region is None:
            raise MpyFormatError(f"{r.name}: a relocation before any position (byte {r.pos})")
        op >>= 1
        n = 1
        if op <= 5:
            if op & 1:
                n = r.uint()
            dest = DEST_NAMES.get(op >> 1)
            if dest is None:
                raise MpyFormatError(f"{r.name}: relocation destination {op >> 1} unknown (byte {r.pos})")
        else:
            dest = DEST_NAMES[op] if op <= 8 else f"mp_fun_table[{op - 9}]"
        for _ in range(n):
            if index >= sizes[region]:
                raise MpyFormatError(f"{r.name}: relocation of {region} word {index} outside the {region}")
            if (region, index) in mpy.relocations:
                raise MpyFormatError(f"{r.name}: {region} word {index} relocated twice")
            mpy.relocations[(region, index)] = dest
            index += 1


def relocate(mpy: NativeMpy, bases: dict, fun_table_entries=None) -> tuple[bytearray, bytearray]:
    """Text and rodata as MicroPython's loader leaves them (mp_native_relocate): every relocated word gets the
    address of its destination added; `bases` gives the addresses of "text", "rodata", "bss", "mp_fun_table",
    "qstr_table", "obj_table", `fun_table_entries` the words of mp_fun_table (k -> value, 0 when absent)."""
    text, rodata = bytearray(mpy.text), bytearray(mpy.rodata)
    for (region, index), dest in mpy.relocations.items():
        if dest.startswith("mp_fun_table["):
            base = (fun_table_entries or {}).get(int(dest[13:-1]), 0)
        elif dest in bases:
            base = bases[dest]
        else:
            raise MpyFormatError(f"relocation to {dest}: no address given for it")
        buf = text if region == "text" else rodata
        value = int.from_bytes(buf[index * WORD:index * WORD + WORD], "little")
        buf[index * WORD:index * WORD + WORD] = ((value + base) & 0xFFFFFFFF).to_bytes(WORD, "little")
    return text, rodata
