"""The few Xtensa (little-endian) instruction encodings the natmod route and its verifier touch.

L32R  at, label     op0 = 1, imm16 in bits 8..23; loads the word at ((pc + 3) & ~3) + ((imm16 - 0x10000) << 2)
CALLn label         op0 = 5, n = bits 4..5 (CALL0/4/8/12), offset18 in bits 6..23;
                    target = (pc & ~3) + (sext(offset18) << 2) + 4
J     label         op0 = 6, n = 0, offset18 in bits 6..23; target = pc + 4 + sext(offset18)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

OP0_L32R = 1
OP0_CALL = 5
OP0_J = 6


def word24(code: bytes, offset: int) -> int:
    return code[offset] | code[offset + 1] << 8 | code[offset + 2] << 16


def _sext(value: int, bits: int) -> int:
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def is_l32r(code: bytes, offset: int) -> bool:
    return code[offset] & 0xF == OP0_L32R


def l32r_target(code: bytes, pc: int) -> int:
    """The address an L32R at `pc` (relative to a 4-byte aligned base) loads from."""
    imm16 = word24(code, pc) >> 8
    return ((pc + 3) & ~3) + ((imm16 - 0x10000) << 2)


@dataclass(frozen=True)
class Branch:
    """A decoded CALLn or J: its mnemonic and the address it goes to."""

    mnemonic: str
    target: int


def decode_branch(code: bytes, pc: int) -> Optional[Branch]:
    """CALL0/4/8/12 or J at `pc`, or None when the instruction is neither."""
    insn = word24(code, pc)
    op0, n = insn & 0xF, (insn >> 4) & 0x3
    offset = _sext(insn >> 6, 18)
    if op0 == OP0_CALL:
        return Branch(f"call{4 * n}", (pc & ~3) + (offset << 2) + 4)
    if op0 == OP0_J and n == 0:
        return Branch("j", pc + 4 + offset)
    return None
