"""Hostile flash layouts: a typo in the board YAML, a firmware that does not fit it, a board whose firmware differs.

`validate` checks the bootloader, partition table, app and filesystem against MicroPython's firmware for the chip
(or the board's own partition table); `flash` checks the firmware image it writes (the partition table inside it),
or without --firmware the partition table already on the board (read back first), and writes nothing when they
disagree. The board is the emulated ESP32 ROM loader (tests/peers/esp_rom.py) with MicroPython's layout on it;
each case proves its flash unchanged, byte for byte.
"""

from __future__ import annotations

import os
import struct

import pytest

from conftest import require
from hostilekit import PORT_BOUND_S, assert_refused, run_cli, snapshot, user_files
from peers.esp_rom import RomLoaderPeer
from peers.trees import MICROPYTHON_4MIB, merged_firmware, partition_table_binary

BASE = "extends: ttgo-tbeam-v1.1\n"
OTA_4MIB = (  # MicroPython's ESP32_GENERIC-OTA layout: two app slots, vfs at 0x310000
    ("nvs", 0x01, 0x02, 0x9000, 0x4000),
    ("otadata", 0x01, 0x00, 0xD000, 0x2000),
    ("phy_init", 0x01, 0x01, 0xF000, 0x1000),
    ("ota_0", 0x00, 0x10, 0x10000, 0x180000),
    ("ota_1", 0x00, 0x11, 0x190000, 0x180000),
    ("vfs", 0x01, 0x81, 0x310000, 0xF0000),
)
AUTO_VFS_4MIB = MICROPYTHON_4MIB[:-1]  # MicroPython 1.26 and later: no vfs row, made at boot

# --- validate: the board YAML against MicroPython's layout ---------------------------------------------------

TABLE = "t.csv"
LAYOUT_CASES = [
    ("issue-filesystem-over-micropython", BASE + "micropython: {filesystem: {offset: 0x20000}}\n",
     ["overlaps the factory partition (MicroPython itself) at 0x10000..0x200000",
      "write `filesystem: {offset: 0x200000, size: 0x200000}`"]),
    ("bootloader-at-0-on-esp32", BASE + "micropython: {partitions: {bootloader: 0x0}}\n",
     ["the ESP32's ROM loads the bootloader from 0x1000"]),
    ("bootloader-at-0x1000-on-esp32s3",
     "extends: esp32s3-devkitc-gy521\nmicropython: {partitions: {bootloader: 0x1000}}\n",
     ["the ESP32-S3's ROM loads the bootloader from 0x0"]),
    ("app-inside-the-filesystem", BASE + "micropython: {partitions: {app: 0x200000}}\n",
     ["has its app (factory) at 0x10000, not 0x200000"]),
    ("app-misaligned", BASE + "micropython: {partitions: {app: 0x11000}}\n", ["not on a 64 KiB boundary"]),
    ("partition-table-misaligned", BASE + "micropython: {partitions: {partition_table: 0x8800}}\n",
     ["0x8800 is not a multiple of the 4096-byte flash sector"]),
    ("partition-table-moved", BASE + "micropython: {partitions: {partition_table: 0x9000}}\n",
     ["reads its partition table at 0x8000, not 0x9000"]),
    ("filesystem-beyond-flash", BASE + "micropython: {filesystem: {offset: 0x300000}}\n",
     ["ends at 0x500000, beyond the 4MB flash"]),
    ("filesystem-misaligned", BASE + "micropython: {filesystem: {offset: 0x200800}}\n",
     ["not a multiple of the 4096-byte flash sector"]),
    ("filesystem-over-the-partition-table", BASE + "micropython: {filesystem: {offset: 0x8000, size: 0x1000}}\n",
     ["overlaps the partition table at 0x8000..0x9000"]),
    ("filesystem-size-differs", BASE + "micropython: {filesystem: {size: 0x100000}}\n",
     ["would not mount", "write `filesystem: {offset: 0x200000, size: 0x200000}`"]),
    ("filesystem-elsewhere", BASE + "micropython: {filesystem: {offset: 0x300000, size: 0x100000}}\n",
     ["would sit where MicroPython never looks"]),
    ("flash-size-2MB-micropython-1.24", BASE + "flash_size: 2MB\nmicropython: {version: '1.24.1'}\n",
     ["beyond the 2MB flash", "offset: 0x170000, size: 0x50000"]),
    ("flash-size-2MB-micropython-1.28", BASE + "flash_size: 2MB\nmicropython: {version: '1.28.0'}\n",
     ["beyond the 2MB flash", "offset: 0x170000, size: 0x90000"]),  # 1.26+: the vfs runs to the end of flash
    ("8MB-micropython-1.24-vfs-is-6MB-not-the-rest",
     BASE + "flash_size: 8MB\nmicropython: {version: '1.24.1', filesystem: {size: 0x600000}}\n",
     ["ESP32_GENERIC firmware mounts the filesystem at 0x200000 (0x200000 bytes)"]),
    ("own-table-rows-overlap", BASE + f"micropython: {{partitions: {{table: {TABLE}}}}}\n",
     ["t.csv:4:17: error: partition vfs (0x180000..0x400000) overlaps partition factory"]),
    ("own-table-app-misaligned", BASE + f"micropython: {{partitions: {{table: {TABLE}}}}}\n",
     ["partition factory: offset 0x18000 is not a multiple of 0x10000"]),
    ("own-table-beyond-flash", BASE + f"micropython: {{partitions: {{table: {TABLE}}}}}\n",
     ["partition vfs (0x200000..0x600000) ends beyond the 4 MiB flash"]),
]
LAYOUT_TABLES = {
    "own-table-rows-overlap":
        "factory, app, factory, 0x10000, 0x1F0000\n# a comment\n\nvfs, data, fat, 0x180000, 0x280000\n",
    "own-table-app-misaligned": "factory, app, factory, 0x18000, 0x1E8000\nvfs, data, fat, 0x200000, 0x200000\n",
    "own-table-beyond-flash": "factory, app, factory, 0x10000, 0x1F0000\nvfs, data, fat, 0x200000, 0x400000\n",
}


@pytest.mark.parametrize("text,phrases", [case[1:] for case in LAYOUT_CASES], ids=[case[0] for case in LAYOUT_CASES])
def test_hostile_layout_is_refused_by_validate_and_generate(tmp_path, request, text, phrases):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    (home / "b.yaml").write_text(text)
    table = LAYOUT_TABLES.get(request.node.callspec.id)
    if table:
        (home / TABLE).write_text(table)
    before = snapshot(home)
    assert_refused(run_cli("validate", "b.yaml", cwd=home), *phrases)
    assert_refused(run_cli("generate", "b.yaml", "-o", "out", cwd=home), phrases[0])
    assert snapshot(home) == before  # no out/ either: nothing is generated for a board that would not boot


# --- flash: the firmware image, or the firmware on the board ---------------------------------------------------


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A built tree of the default board, pinned to MicroPython 1.24.1 (a vfs row in the partition table)."""
    try:
        import esptool  # noqa: F401
    except ImportError:
        esptool = None
    require(esptool is not None, "esptool is not installed (pip install esptool)")
    home = tmp_path_factory.mktemp("layout") / "home"
    home.mkdir()
    user_files(home)
    (home / "board.yaml").write_text(BASE + "micropython: {version: '1.24.1'}\n")
    assert run_cli("generate", "board.yaml", "-o", "out", cwd=home, timeout=120).returncode == 0
    assert run_cli("build", "out", cwd=home, timeout=300).returncode == 0
    return home


def damaged_table() -> bytes:
    table = bytearray(partition_table_binary())
    table[40] ^= 0x01  # a bit of the second row's offset flips; the MD5 row no longer matches
    return bytes(table)


def damaged_app() -> bytes:
    image = bytearray(merged_firmware())
    image[0xF000 + 0x100] ^= 0xFF  # a byte of the app's segment: its checksum no longer matches
    return bytes(image)


def oversize(path) -> None:
    with open(path, "wb") as handle:
        handle.write(merged_firmware())
        handle.truncate(5 * 1024 * 1024)  # larger than the board's 4 MiB flash


# (id, firmware on the board before (bytes at 0x1000, or None for blank), --firmware content or None, phrases)
FLASH_CASES = [
    ("board-runs-an-ota-firmware", merged_firmware(rows=OTA_4MIB), None,
     ["does not match the firmware on the board", "overlaps the ota_1 partition"]),
    ("board-is-blank", None, None, ["has no partition table at 0x8000: no MicroPython is on it", "--firmware"]),
    ("board-table-damaged", merged_firmware(table=damaged_table()), None,
     ["the partition table of the firmware on the board", "is damaged: its MD5 row does not match"]),
    ("board-runs-1.26-board-says-1.24", merged_firmware(rows=AUTO_VFS_4MIB), None,
     ["has no vfs partition, as MicroPython 1.26 and later have", "says MicroPython 1.24.1"]),
    ("firmware-app-only", merged_firmware(), b"\xe9" + bytes(0x1F000),
     ["has no partition table at 0x8000", "not a whole MicroPython image"]),
    ("firmware-with-another-layout", merged_firmware(), merged_firmware(rows=OTA_4MIB),
     ["does not match the firmware fw.bin", "overlaps the ota_1 partition"]),
    ("firmware-for-esp32s3", merged_firmware(), merged_firmware(chip_id=9),
     ["is not built for an ESP32 (its header names chip id 9, the ESP32-S3)"]),
    ("firmware-table-damaged", merged_firmware(), merged_firmware(table=damaged_table()),
     ["the partition table of the firmware fw.bin is damaged"]),
    ("firmware-app-damaged", merged_firmware(), damaged_app(), ["the MicroPython app inside", "is damaged"]),
    ("firmware-larger-than-flash", merged_firmware(), oversize, ["file is 5.2 MB", "at most the 4MB flash"]),
    ("firmware-is-a-fifo", merged_firmware(), os.mkfifo, ["fw.bin is a FIFO, not a regular file"]),
    ("firmware-is-dev-zero", merged_firmware(), lambda p: p.symlink_to("/dev/zero"), ["fw.bin is a device"]),
    ("firmware-is-a-uf2", merged_firmware(), b"UF2\n" * 1000, ["is not an ESP firmware image"]),
    ("erase-without-firmware", merged_firmware(), "--erase", ["--erase without --firmware"]),
]


@pytest.mark.parametrize("on_board,firmware,phrases", [case[1:] for case in FLASH_CASES],
                         ids=[case[0] for case in FLASH_CASES])
def test_hostile_flash_writes_nothing(built, tmp_path, on_board, firmware, phrases):
    home = built
    args = ["flash", "out"]
    if firmware == "--erase":
        args.append("--erase")
    elif firmware is not None:
        path = tmp_path / "fw.bin"
        firmware(path) if callable(firmware) else path.write_bytes(firmware)
        args += ["--firmware", str(path)]
    with RomLoaderPeer() as peer:
        if on_board is not None:
            peer.flash[0x1000 : 0x1000 + len(on_board)] = on_board
        flash_before = bytes(peer.flash)
        before = snapshot(home)
        outcome = run_cli(*args, "--port", peer.url, cwd=home, timeout=PORT_BOUND_S)
        assert_refused(outcome, *phrases, bound=PORT_BOUND_S)
        assert bytes(peer.flash) == flash_before
        writes = {op: peer.stats.commands.get(op, 0) for op in (0x02, 0x03, 0x10, 0x11, 0xD0, 0xD1)}
        assert not any(writes.values()), writes  # no FLASH_BEGIN/DATA, DEFL_BEGIN/DATA, ERASE_FLASH/REGION
    assert snapshot(home) == before


def test_the_firmware_check_reads_what_esptool_writes():
    """The test firmwares are what they claim: esptool's own image reader parses the app inside them."""
    from esptool.bin_image import LoadFirmwareImage

    image = merged_firmware()
    assert struct.unpack_from("<H", image, 0x7000)[0] == 0x50AA
    assert LoadFirmwareImage("esp32", image[0xF000:]).chip_id == 0
