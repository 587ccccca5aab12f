"""The native-module ABI of a MicroPython source tree, read from its headers, and the check that a .mpy matches the
firmware release a board declares.

MicroPython's loader (py/persistentcode.c) accepts a native .mpy only when its header carries the firmware's
MPY_VERSION and MPY_SUB_VERSION and an arch the firmware runs; MicroPython bumps MPY_SUB_VERSION whenever the
native ABI changes (the layout of `mp_fun_table_t` in py/nativeglue.h, through which a natmod calls the runtime),
so a .mpy whose header equals the firmware's was compiled against the same table. `TreeAbi.fun_table` lists that
table's fields in order: a natmod's relocation "entry k of mp_fun_table" means field k.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

from codegen.errors import UserError
from codegen.natmod.mpyfile import Header

SMALL_INT_BITS_32 = 31  # MP_SMALL_INT_BITS of the 32-bit ports (ESP32, RP2040): the loader rejects more
SMALL_INT_BITS_64 = 63  # the unix port on x64
# mpy_ld's names for the objects a natmod may reference through mp_fun_table, and the field each one is
_FUN_TABLE_SYMBOLS = {"mp_type_": "type_", "mp_stream_": "stream_"}


@dataclass(frozen=True)
class TreeAbi:
    version: str  # MicroPython release of the tree, "1.28.0"
    mpy_version: int
    mpy_sub_version: int
    fun_table: tuple  # mp_fun_table_t field names in order

    @property
    def mpy_format(self) -> str:
        return f"{self.mpy_version}.{self.mpy_sub_version}"

    @property
    def fun_table_digest(self) -> str:
        return hashlib.sha256("\n".join(self.fun_table).encode()).hexdigest()[:16]

    def fun_table_index(self, symbol: str) -> int:
        """The mp_fun_table word an external symbol (mp_type_str, mp_stream_read_obj, ...) lives in."""
        for prefix, field_prefix in _FUN_TABLE_SYMBOLS.items():
            if symbol.startswith(prefix):
                name = field_prefix + symbol[len(prefix):]
                if name in self.fun_table:
                    return self.fun_table.index(name)
        raise KeyError(symbol)


def _define(text: str, name: str, source: str) -> int:
    found = re.search(rf"^#define {name} \(?(\d+)\)?", text, re.M)
    if not found:
        raise UserError(f"{source} does not define {name}: not a MicroPython source tree this deadreckon knows")
    return int(found.group(1))


def _fun_table_fields(text: str) -> tuple:
    body = re.search(r"typedef struct _mp_fun_table_t \{(.*?)\} mp_fun_table_t;", text, re.S)
    if not body:
        raise UserError("py/nativeglue.h has no mp_fun_table_t: not a MicroPython source tree this deadreckon knows")
    fields = []
    for line in body.group(1).splitlines():
        line = line.split("//")[0].strip()
        if not line.endswith(";"):
            continue
        pointer = re.search(r"\(\*(\w+)\)", line)
        fields.append(pointer.group(1) if pointer else re.search(r"(\w+)\s*;$", line).group(1))
    return tuple(fields)


def tree_abi(tree: Path) -> TreeAbi:
    """The release and native ABI of the MicroPython source tree at `tree`."""
    tree = Path(tree)
    mpconfig = (tree / "py" / "mpconfig.h").read_text()
    persistent = (tree / "py" / "persistentcode.h").read_text()
    version = ".".join(str(_define(mpconfig, f"MICROPY_VERSION_{part}", "py/mpconfig.h"))
                       for part in ("MAJOR", "MINOR", "MICRO"))
    return TreeAbi(version=version, mpy_version=_define(persistent, "MPY_VERSION", "py/persistentcode.h"),
                   mpy_sub_version=_define(persistent, "MPY_SUB_VERSION", "py/persistentcode.h"),
                   fun_table=_fun_table_fields((tree / "py" / "nativeglue.h").read_text()))


def check_header(header: Header, release_format: str, arch: str, release: str, name: str = "dr_native.mpy") -> None:
    """Raise UserError unless MicroPython `release` (which loads native .mpy `release_format`, "6.3") loads a
    native .mpy with `header` for `arch`: the loader's own test (version, sub-version, arch, small-int bits)."""
    problems = []
    if header.format != release_format:
        problems.append(f".mpy {header.format}, MicroPython {release} loads native .mpy {release_format} only")
    if header.arch != arch:
        problems.append(f"built for {header.arch}, the board runs {arch}")
    small_int_bits = SMALL_INT_BITS_64 if arch == "x64" else SMALL_INT_BITS_32
    if header.small_int_bits > small_int_bits:
        problems.append(f"small ints of {header.small_int_bits} bits, more than the port's {small_int_bits}")
    if problems:
        raise UserError(f"{name} does not match the board's firmware: {'; '.join(problems)}",
                        hint="build against the MicroPython release the board runs (MPY_DIR, or the board's "
                             "micropython.version)")
