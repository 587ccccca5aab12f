"""Hostile board files: what `deadreckon validate` (and every command that reads a board) does with them.

Huge, endless and bomb-shaped inputs are refused before they cost time or memory; reader errors carry the line
and a caret; mistakes a new user makes (a pin in quotes, an old MicroPython, a filesystem the app does not fit) are
named in their own terms. Each case: exit 2, a clear message, no traceback, within the bound, nothing changed.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hostilekit import assert_refused, run_cli, snapshot, user_files

BASE = "extends: ttgo-tbeam-v1.1\n"


def alias_bomb(levels: int = 9, fanout: int = 9) -> str:
    """The issue's "billion laughs": each level lists the previous one `fanout` times (9^8 values from 2 KB)."""
    lines = [f"l0: &l0 [{', '.join(['lol'] * fanout)}]"]
    for level in range(1, levels):
        lines.append(f"l{level}: &l{level} [{', '.join([f'*l{level - 1}'] * fanout)}]")
    return "\n".join(lines) + "\n"


def merge_bomb(levels: int = 12) -> str:
    """Merge keys doubling at every level: 2^12 copies of a mapping."""
    lines = ["m0: &m0 {a: 1, b: 2, c: 3, d: 4}"]
    for level in range(1, levels):
        lines.append(f"m{level}: &m{level} {{x: [*m{level - 1}, *m{level - 1}]}}")
    return "\n".join(lines) + "\n"


def fifo(path: Path) -> None:
    os.mkfifo(path)


def sparse_gigabyte(path: Path) -> None:
    """A 1 GiB file that takes no disk: its size is all a reader that checks first ever sees."""
    with open(path, "wb") as handle:
        handle.truncate(1 << 30)


# (id, files to create {name: text | bytes | callable(path)}, the board argument, phrases the message must hold)
CASES = [
    ("alias-bomb-9^8", {"b.yaml": alias_bomb()}, "b.yaml", ["expand the document to more than 10000 values", "^"]),
    ("alias-bomb-in-a-board", {"b.yaml": BASE + "reserved:\n" + "".join(
        f"  g{i}: &g{i} [" + ", ".join([f"*g{i - 1}"] * 8 if i else ["1"] * 8) + "]\n" for i in range(8))},
     "b.yaml", ["expand the document"]),
    ("merge-key-bomb", {"b.yaml": merge_bomb()}, "b.yaml", ["expand the document"]),
    ("nesting-1000-deep", {"b.yaml": "name: " + "[" * 1000 + "]" * 1000 + "\n"}, "b.yaml",
     ["nested more than 32 levels"]),
    ("nesting-block-style", {"b.yaml": "".join("  " * i + f"k{i}:\n" for i in range(40)) + "  " * 40 + "v\n"},
     "b.yaml", ["nested more than 32 levels"]),
    ("undefined-alias", {"b.yaml": BASE + "led: *nowhere\n"}, "b.yaml", ["alias *nowhere names no anchor"]),
    ("dev-zero", {}, "/dev/zero", ["is a device, not a regular file"]),
    ("link-to-dev-zero", {"b.yaml": lambda p: p.symlink_to("/dev/zero")}, "b.yaml", ["is a device"]),
    ("fifo-without-writer", {"b.yaml": fifo}, "b.yaml", ["is a FIFO, not a regular file"]),
    ("extends-a-fifo", {"b.yaml": "extends: ./pipe.yaml\nname: x\n", "pipe.yaml": fifo}, "b.yaml", ["is a FIFO"]),
    ("folder-named-yaml", {"b.yaml": lambda p: p.mkdir()}, "b.yaml", ["is a folder"]),
    ("sparse-1-GB", {"b.yaml": sparse_gigabyte}, "b.yaml",
     ["file is 1073.7 MB"]),
    ("nul-bytes", {"b.yaml": b"name: x\n\x00\x00\x00"}, "b.yaml", ["binary data (a NUL byte)"]),
    ("not-utf8", {"b.yaml": b"name: \xff\xfe\n"}, "b.yaml", ["not UTF-8"]),
    ("tab-indent", {"b.yaml": BASE + "imu:\n\taddress: 0x69\n"}, "b.yaml",
     ["b.yaml:3:1: error: tab character", "\taddress: 0x69\n    ^"]),
    ("syntax-error", {"b.yaml": BASE + "imu: {address: 0x69\nled: {pin: 13}\n"}, "b.yaml",
     ["b.yaml:3:4: error: YAML syntax", "    led: {pin: 13}\n       ^"]),
    ("duplicate-key", {"b.yaml": BASE + "led:\n  pin: 13\n  pin: 14\n"}, "b.yaml",
     ["b.yaml:4:3: error: duplicate key 'pin'", "      pin: 14\n      ^", "first 'pin' is on line 3"]),
    ("two-documents", {"b.yaml": BASE + "---\nname: other\n"}, "b.yaml", ["YAML syntax"]),
    ("python-object-tag", {"b.yaml": BASE + "name: !!python/object/apply:os.system [touch hacked]\n"}, "b.yaml",
     ["YAML tag", "board files use plain values only"]),
    ("custom-tag", {"b.yaml": BASE + "led: !include other.yaml\n"}, "b.yaml", ["YAML tag '!include'"]),
    ("pin-quoted", {"b.yaml": BASE + "led: {pin: '21'}\n"}, "b.yaml",
     ["led.pin: a pin is a GPIO number, not the string '21'", "write 21 without quotes"]),
    ("pin-float", {"b.yaml": BASE + "i2c: {main: {sda: 21.0}}\n"}, "b.yaml",
     ["i2c.main.sda: a pin is a whole GPIO number, not 21.0", "write `21`"]),
    ("pin-boolean", {"b.yaml": BASE + "buttons: {test_mode: {pin: true}}\n"}, "b.yaml",
     ["buttons.test_mode.pin: a pin is a GPIO number, not true (a boolean)"]),
    ("pin-name", {"b.yaml": BASE + "led: {pin: GPIO4}\n"}, "b.yaml", ["a pin is a GPIO number, not the string"]),
    ("pin-list", {"b.yaml": BASE + "uart: {gps: {rx: [34, 35]}}\n"}, "b.yaml", ["a pin is one GPIO number"]),
    ("micropython-1.10", {"b.yaml": BASE + "micropython: {version: '1.10'}\n"}, "b.yaml",
     ["the app does not run on MicroPython 1.10; it needs 1.23 or newer"]),
    ("micropython-1.22", {"b.yaml": BASE + "micropython: {version: '1.22.2'}\n"}, "b.yaml",
     ["needs 1.23 or newer"]),
    ("micropython-version-as-float", {"b.yaml": BASE + "micropython: {version: 1.24}\n"}, "b.yaml",
     ["micropython.version: should be a valid string"]),
    ("huge-integer", {"b.yaml": BASE + "imu: {address: 123456789012345678901234567890}\n"}, "b.yaml",
     ["imu.address"]),
    ("filesystem-too-small-for-the-app", {
        "t.csv": "nvs, data, nvs, 0x9000, 0x6000\nphy_init, data, phy, 0xf000, 0x1000\n"
                 "factory, app, factory, 0x10000, 0x3E0000\nvfs, data, fat, 0x3F0000, 0x10000\n",
        "b.yaml": BASE + "micropython:\n  partitions: {table: t.csv}\n"
                         "  filesystem: {offset: 0x3F0000, size: 0x10000}\n"},
     "b.yaml", ["micropython.filesystem.size: the app", "does not fit in the 64 KiB filesystem"]),
    ("filesystem-without-room-for-logs", {
        "t.csv": "nvs, data, nvs, 0x9000, 0x6000\nphy_init, data, phy, 0xf000, 0x1000\n"
                 "factory, app, factory, 0x10000, 0x3B0000\nvfs, data, fat, 0x3C0000, 0x40000\n",
        "b.yaml": BASE + "micropython:\n  partitions: {table: t.csv}\n"
                         "  filesystem: {offset: 0x3C0000, size: 0x40000}\n"},
     "b.yaml", ["its log needs 260 KiB"]),
    ("eskf-on-circuitpython", {"b.yaml": "extends: pico-gy521-circuitpython\nalgorithm:\n  mode: eskf\n"}, "b.yaml",
     ["b.yaml:3:9: error: algorithm.mode: eskf runs in the native module only, and CircuitPython loads no native "
      "module", "hint: use `mode: fused`"]),
    ("eskf-sigma-zero", {"b.yaml": BASE + "algorithm: {mode: eskf, eskf_gps_pos_sigma: 0}\n"}, "b.yaml",
     ["algorithm.eskf_gps_pos_sigma: should be greater than 0 (got 0)"]),
    ("eskf-key-misspelt", {"b.yaml": BASE + "algorithm: {mode: eskf, eskf_nhc_sigm: 0.5}\n"}, "b.yaml",
     ["unknown key 'eskf_nhc_sigm' in algorithm", "did you mean `eskf_nhc_sigma`?"]),
    ("eskf-heap-too-small", {"b.yaml": "extends: esp32-devkitc-gy521\nmicropython: {heap_kb: 90}\n"
                                       "algorithm: {mode: eskf}\n"}, "b.yaml",
     ["b.yaml:2:24: error: algorithm.mode: eskf does not fit in this board's 90 KiB heap (micropython.heap_kb)",
      "hint: use `mode: fused`"]),
    ("extends-cycle", {"a.yaml": "extends: ./b.yaml\nname: a\n", "b.yaml": "extends: ./a.yaml\nname: b\n"},
     "a.yaml", ["`extends:` forms a cycle"]),
    ("extends-dev-zero", {"b.yaml": "extends: /dev/zero.yaml\nname: x\n"}, "b.yaml", ["no such board file"]),
    ("partition-csv-fifo", {"t.csv": fifo, "b.yaml": BASE + "micropython: {partitions: {table: t.csv}}\n"},
     "b.yaml", ["micropython.partitions.table: t.csv is a FIFO"]),
    ("partition-csv-dev-zero", {"t.csv": lambda p: p.symlink_to("/dev/zero"),
                                "b.yaml": BASE + "micropython: {partitions: {table: t.csv}}\n"},
     "b.yaml", ["t.csv is a device"]),
    ("partition-csv-garbage", {"t.csv": "vfs, data, fat, somewhere, 0x10000\n",
                               "b.yaml": BASE + "micropython: {partitions: {table: t.csv}}\n"},
     "b.yaml", ["t.csv:1:17: error: offset 'somewhere' is not a number", "^"]),
    ("partition-csv-short-row", {"t.csv": "vfs, data\n",
                                 "b.yaml": BASE + "micropython: {partitions: {table: t.csv}}\n"},
     "b.yaml", ["a partition row has 5 columns"]),
]


@pytest.mark.parametrize("files,board,phrases", [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_hostile_board_file_is_refused(tmp_path, files, board, phrases):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    for name, content in files.items():
        path = home / name
        if callable(content):
            content(path)
        elif isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    before = snapshot(home)
    outcome = run_cli("validate", board, cwd=home)
    assert_refused(outcome, *phrases)
    assert snapshot(home) == before
