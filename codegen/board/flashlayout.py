"""Where things live in a board's flash, and the checks that keep an image from landing on top of MicroPython.

An ESP32's flash holds, in this order (ESP-IDF's layout, which MicroPython's firmware uses):

    bootloader        at 0x1000 on the ESP32, 0x0 on the ESP32-S3: fixed by the chip's ROM, which loads it
    partition table   at 0x8000 (compiled into the bootloader), one 4 KiB sector of 32-byte rows
    partitions        nvs 0x9000, phy_init 0xF000, the app ("factory") at 0x10000, then the filesystem ("vfs")

MicroPython's generic firmware (ports/esp32, ESP32_GENERIC and ESP32_GENERIC_S3, releases 1.19 to 1.28) keeps the
app at 0x10000 with 0x1F0000 bytes (0x160000 in the 2 MiB D2WD build). Up to 1.25 the vfs partition is a row of
its partition table: 0x200000 + 0x200000 on the ESP32 (a 4 MiB table, whatever the flash size), 0x200000 +
0x600000 on the ESP32-S3 (an 8 MiB table; 0x200000 bytes in its FLASH_4M build), 0x170000 + 0x50000 in the 2 MiB
build. From 1.26 the table has no vfs row and MicroPython makes one at boot from the end of the last partition to
the end of the physical flash. On the RP2040 (ports/rp2, RPI_PICO) the firmware starts the flash and the
filesystem is its last 1408 KiB.

A board may name its own partition table (`micropython.partitions.table`, an ESP-IDF CSV beside the board file)
for a firmware built with one; `deadreckon flash` reads the table inside the firmware image it writes and checks
the board against that too (`codegen.deploy.flash`). Every finding here is a located `Diagnostic`.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

from codegen.board.diagnostics import Diagnostic, error
from codegen.board.model import Board
from codegen.board.yamlsource import KeyPath, SourceMap, YamlError
from codegen.errors import Location, UserError
from codegen.safeio import read_bounded

SECTOR_BYTES = 0x1000  # the flash erase unit; every partition starts on one
APP_ALIGN_BYTES = 0x10000  # an app partition starts on a 64 KiB MMU page
PARTITION_TABLE_SECTOR_BYTES = 0x1000
PARTITION_TABLE_MAX_BYTES = 0xC00  # ESP-IDF reads at most this much of the table (96 rows of 32 bytes)
ENTRY_BYTES = 32
ENTRY_MAGIC = 0x50AA  # the first two bytes of a row, 0xAA50 little-endian
MD5_MAGIC = 0xEBEB  # a row holding the MD5 of the rows before it
MAX_CSV_BYTES = 64 * 1024

ROM_BOOTLOADER_OFFSET = {"esp32": 0x1000, "esp32s3": 0x0}
MICROPYTHON_PARTITION_TABLE_OFFSET = 0x8000
MICROPYTHON_APP_OFFSET = 0x10000
RP2_PICO_STORAGE_BYTES = 1408 * 1024  # ports/rp2 MICROPY_HW_FLASH_STORAGE_BYTES, at the end of a 2 MiB flash
AUTO_VFS_SINCE = (1, 26)  # MicroPython makes the vfs partition itself from this release on

TYPE_APP, TYPE_DATA = 0x00, 0x01
TYPE_NAMES = {"app": TYPE_APP, "data": TYPE_DATA}
SUBTYPE_NAMES = {
    TYPE_APP: {"factory": 0x00, "test": 0x20, **{f"ota_{index}": 0x10 + index for index in range(16)}},
    TYPE_DATA: {"ota": 0x00, "phy": 0x01, "nvs": 0x02, "coredump": 0x03, "nvs_keys": 0x04, "efuse": 0x05,
                "undefined": 0x06, "esphttpd": 0x80, "fat": 0x81, "spiffs": 0x82, "littlefs": 0x83},
}
FILESYSTEM_LABELS = ("vfs", "ffat")  # the labels MicroPython's flashbdev looks for

PARTITIONS_PATH: KeyPath = ("micropython", "partitions")
FILESYSTEM_PATH: KeyPath = ("micropython", "filesystem")


@dataclass(frozen=True)
class Partition:
    label: str
    type: int
    subtype: int
    offset: int
    size: int
    location: Optional[Location] = None  # the CSV row it was read from

    @property
    def end(self) -> int:
        return self.offset + self.size

    @property
    def is_app(self) -> bool:
        return self.type == TYPE_APP

    def span(self) -> str:
        return f"{self.offset:#x}..{self.end:#x}"


@dataclass(frozen=True)
class FlashLayout:
    """A firmware's flash layout: its bootloader, partition table and partitions."""

    origin: str  # what the layout is read from, for messages
    bootloader: Optional[int]  # None on the RP2040 (its boot stage is part of the firmware)
    partition_table: Optional[int]
    partitions: tuple[Partition, ...]
    auto_filesystem: bool = False  # no vfs row: the firmware makes one from the last partition to the flash end

    def app(self) -> Optional[Partition]:
        apps = [p for p in self.partitions if p.is_app]
        factory = [p for p in apps if p.subtype == 0x00]
        return (factory or apps or [None])[0]

    def filesystem(self, flash_bytes: int) -> Optional[Partition]:
        for partition in self.partitions:
            if partition.type == TYPE_DATA and partition.label in FILESYSTEM_LABELS:
                return partition
        if self.auto_filesystem and self.partitions:
            start = max(p.end for p in self.partitions)
            if start < flash_bytes:
                return Partition("vfs", TYPE_DATA, 0x81, start, flash_bytes - start)
        return None


def version_tuple(version: str) -> tuple[int, ...]:
    return tuple(int(part) for part in version.split("."))


def micropython_layout(board: Board) -> Optional[FlashLayout]:
    """The layout of MicroPython's own firmware for the board's chip, flash size and release; None if unknown."""
    version = version_tuple(board.micropython.version)
    flash = board.flash_bytes
    auto = version >= AUTO_VFS_SINCE
    if board.chip == "rp2040":
        if flash != 2 * 1024 * 1024:
            return None  # RP2040 boards with more flash set their own storage size
        storage = flash - RP2_PICO_STORAGE_BYTES
        return FlashLayout(
            f"MicroPython {board.micropython.version}'s RPI_PICO firmware", None, None,
            (Partition("firmware", TYPE_APP, 0x00, 0, storage),
             Partition("vfs", TYPE_DATA, 0x81, storage, RP2_PICO_STORAGE_BYTES)),
        )
    if board.chip not in ROM_BOOTLOADER_OFFSET:
        return None
    small = flash <= 2 * 1024 * 1024
    if board.chip == "esp32":
        build = "ESP32_GENERIC-D2WD" if small else "ESP32_GENERIC"
        vfs = (0x170000, 0x50000) if small else (0x200000, 0x200000)
    else:
        if small:
            return None  # no ESP32_GENERIC_S3 build for 2 MiB of flash
        build = "ESP32_GENERIC_S3-FLASH_4M" if flash == 4 * 1024 * 1024 and not auto else "ESP32_GENERIC_S3"
        vfs = (0x200000, 0x200000) if flash == 4 * 1024 * 1024 else (0x200000, 0x600000)
    app_size = 0x160000 if small else 0x1F0000
    partitions = [
        Partition("nvs", TYPE_DATA, 0x02, 0x9000, 0x6000),
        Partition("phy_init", TYPE_DATA, 0x01, 0xF000, 0x1000),
        Partition("factory", TYPE_APP, 0x00, MICROPYTHON_APP_OFFSET, app_size),
    ]
    if not auto:
        partitions.append(Partition("vfs", TYPE_DATA, 0x81, *vfs))
    return FlashLayout(
        f"MicroPython {board.micropython.version}'s {build} firmware", ROM_BOOTLOADER_OFFSET[board.chip],
        MICROPYTHON_PARTITION_TABLE_OFFSET, tuple(partitions), auto_filesystem=auto,
    )


# --- reading partition tables --------------------------------------------------------------------------------


class PartitionTableError(ValueError):
    """A partition table that cannot be read; `location` says where when it came from a CSV."""

    def __init__(self, message: str, location: Optional[Location] = None, hint: Optional[str] = None):
        super().__init__(message)
        self.message = message
        self.location = location
        self.hint = hint


def _csv_number(text: str, what: str, where: Location) -> int:
    match = re.fullmatch(r"(0x[0-9a-fA-F]+|[0-9]+)\s*([kKmM]?)", text)
    if not match:
        raise PartitionTableError(f"{what} {text!r} is not a number (write 0x10000, 65536, 64K or 1M)", where)
    value = int(match[1], 0)
    return value * {"": 1, "k": 1024, "m": 1024 * 1024}[match[2].lower()]


def parse_partition_csv(text: str, name: str, table_offset: int = MICROPYTHON_PARTITION_TABLE_OFFSET
                        ) -> list[Partition]:
    """The rows of an ESP-IDF partition table CSV (Name, Type, SubType, Offset, Size[, Flags]). An empty offset
    follows the previous row, aligned as ESP-IDF aligns it (64 KiB for apps, 4 KiB otherwise)."""
    partitions: list[Partition] = []
    next_offset = table_offset + PARTITION_TABLE_SECTOR_BYTES
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        columns, fields, start = [], [], 0
        for raw in line.split(","):
            columns.append(start + len(raw) - len(raw.lstrip()) + 1)
            fields.append(raw.strip())
            start += len(raw) + 1

        def at(index: int) -> Location:
            return Location(name, number, columns[min(index, len(columns) - 1)])

        if len(fields) < 5:
            raise PartitionTableError("a partition row has 5 columns: Name, Type, SubType, Offset, Size", at(0),
                                      "e.g. `vfs, data, fat, 0x200000, 0x200000`")
        label, kind, subkind, offset_text, size_text = fields[:5]
        if not label or len(label.encode()) > 16:
            raise PartitionTableError(f"partition name {label!r} must be 1 to 16 bytes", at(0))
        if kind in TYPE_NAMES:
            type_ = TYPE_NAMES[kind]
        else:
            type_ = _csv_number(kind, "type", at(1))
            if not 0x40 <= type_ <= 0xFE:
                raise PartitionTableError(f"type {kind!r} is neither app, data nor a custom type 0x40..0xFE",
                                          at(1))
        names = SUBTYPE_NAMES.get(type_, {})
        if not subkind:
            subtype = 0
        elif subkind in names:
            subtype = names[subkind]
        elif re.fullmatch(r"0x[0-9a-fA-F]+|[0-9]+", subkind):
            subtype = int(subkind, 0)
        else:
            raise PartitionTableError(f"subtype {subkind!r} is not one of {', '.join(names) or 'a number'}",
                                      at(2))
        align = APP_ALIGN_BYTES if type_ == TYPE_APP else SECTOR_BYTES
        if offset_text:
            offset = _csv_number(offset_text, "offset", at(3))
        else:
            offset = -(-next_offset // align) * align
        if not size_text:
            raise PartitionTableError("every partition needs a size", at(4))
        size = _csv_number(size_text, "size", at(4))
        if size <= 0:
            raise PartitionTableError("a partition's size must be above 0", at(4))
        partitions.append(Partition(label, type_, subtype, offset, size, at(3 if offset_text else 0)))
        next_offset = offset + size
    if not partitions:
        raise PartitionTableError("the partition table has no rows", Location(name, 1, 1))
    return partitions


def read_partition_csv(path: Path, name: str, table_offset: int) -> tuple[list[Partition], list[str]]:
    """Read a partition table CSV safely (regular file, at most 64 KiB, UTF-8); return its rows and lines."""
    try:
        raw = read_bounded(path, name, MAX_CSV_BYTES, what="partition table CSV")
    except UserError as problem:
        raise YamlError(problem.message, location=problem.location, hint=problem.hint) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise YamlError(f"{name} is not UTF-8 text", hint="a partition table CSV is a text file") from None
    lines = text.splitlines()
    try:
        return parse_partition_csv(text, name, table_offset), lines
    except PartitionTableError as problem:
        raise YamlError(problem.message, location=problem.location, hint=problem.hint, lines=lines) from None


def parse_partition_binary(data: bytes) -> list[Partition]:
    """The rows of a binary partition table (the 0xC00 bytes at its offset): 32-byte rows of magic 0xAA50, type,
    subtype, offset, size, a 16-byte label and flags; ended by 0xFF bytes, optionally after an MD5 row."""
    partitions: list[Partition] = []
    area = data[:PARTITION_TABLE_MAX_BYTES]
    for start in range(0, len(area) - ENTRY_BYTES + 1, ENTRY_BYTES):
        row = area[start : start + ENTRY_BYTES]
        magic = struct.unpack_from("<H", row)[0]
        if row == b"\xff" * ENTRY_BYTES:
            break
        if magic == MD5_MAGIC:
            if row[16:] != hashlib.md5(area[:start]).digest():
                raise PartitionTableError("its MD5 row does not match its rows (a damaged partition table)")
            break
        if magic != ENTRY_MAGIC:
            raise PartitionTableError(f"row {start // ENTRY_BYTES} does not start with the 0xAA50 magic")
        type_, subtype, offset, size = struct.unpack_from("<BBII", row, 2)
        label = row[12:28].split(b"\0")[0].decode("utf-8", "replace")
        partitions.append(Partition(label, type_, subtype, offset, size))
    else:
        raise PartitionTableError("it does not end within 0xC00 bytes")
    if not partitions:
        raise PartitionTableError("it has no rows")
    return partitions


# --- the checks ------------------------------------------------------------------------------------------------


def _overlap(a_start: int, a_end: int, b_start: int, b_end: int) -> bool:
    return a_start < b_end and b_start < a_end


def _check_table_rows(layout: FlashLayout, flash: int) -> Iterator[Diagnostic]:
    """A board's own table: rows aligned, inside the flash, clear of the bootloader, the table and each other."""
    reserved_end = (layout.partition_table or 0) + PARTITION_TABLE_SECTOR_BYTES
    for index, row in enumerate(layout.partitions):
        align = APP_ALIGN_BYTES if row.is_app else SECTOR_BYTES
        if row.offset % align:
            yield error(f"partition {row.label}: offset {row.offset:#x} is not a multiple of {align:#x}",
                        row.location, "app partitions start on a 64 KiB boundary, the others on a 4 KiB sector")
        if row.end > flash:
            yield error(f"partition {row.label} ({row.span()}) ends beyond the {flash // (1024 * 1024)} MiB flash",
                        row.location)
        if row.offset < reserved_end:
            yield error(f"partition {row.label} ({row.span()}) overlaps the bootloader and partition table "
                        f"(0x0..{reserved_end:#x})", row.location)
        for other in layout.partitions[:index]:
            if _overlap(row.offset, row.end, other.offset, other.end):
                yield error(f"partition {row.label} ({row.span()}) overlaps partition {other.label} "
                            f"({other.span()})", row.location)


def _check_boot_area(board: Board, layout: FlashLayout, source: SourceMap, own_table: bool) -> Iterator[Diagnostic]:
    partitions = board.micropython.partitions
    rom = ROM_BOOTLOADER_OFFSET[board.chip]
    chip = board.chip.upper().replace("ESP32S3", "ESP32-S3")
    if partitions.bootloader != rom:
        yield error(
            f"micropython.partitions.bootloader: the {chip}'s ROM loads the bootloader from {rom:#x}; one written "
            f"at {partitions.bootloader:#x} never runs and the board does not boot",
            source.value(PARTITIONS_PATH + ("bootloader",)),
            f"write `bootloader: {rom:#x}` (0x1000 on the ESP32, 0x0 on the ESP32-S3)",
        )
    table_where = source.value(PARTITIONS_PATH + ("partition_table",))
    if partitions.partition_table % SECTOR_BYTES:
        yield error(f"micropython.partitions.partition_table: {partitions.partition_table:#x} is not a multiple of "
                    "the 4096-byte flash sector", table_where)
    elif partitions.partition_table <= partitions.bootloader:
        yield error(f"micropython.partitions.partition_table: {partitions.partition_table:#x} is not after the "
                    f"bootloader at {partitions.bootloader:#x}", table_where)
    elif not own_table and partitions.partition_table != layout.partition_table:
        yield error(
            f"micropython.partitions.partition_table: {layout.origin} reads its partition table at "
            f"{layout.partition_table:#x}, not {partitions.partition_table:#x}",
            table_where,
            f"write `partition_table: {layout.partition_table:#x}`, or name your firmware's own table with "
            "micropython.partitions.table",
        )
    app_where = source.value(PARTITIONS_PATH + ("app",))
    app = layout.app()
    if partitions.app % APP_ALIGN_BYTES:
        yield error(f"micropython.partitions.app: {partitions.app:#x} is not on a 64 KiB boundary "
                    "(app partitions start on an MMU page)", app_where)
    elif app is None:
        yield error(f"{layout.origin} has no app partition", source.value(PARTITIONS_PATH + ("table",)))
    elif partitions.app != app.offset:
        yield error(
            f"micropython.partitions.app: {layout.origin} has its app ({app.label}) at {app.offset:#x}, not "
            f"{partitions.app:#x}",
            app_where,
            f"write `app: {app.offset:#x}`",
        )


def _check_filesystem(board: Board, layout: FlashLayout, source: SourceMap) -> Iterator[Diagnostic]:
    fs = board.micropython.filesystem
    start, end = fs.offset, fs.offset + fs.size
    where = source.value(FILESYSTEM_PATH + ("offset",))
    flash = board.flash_bytes
    wanted = layout.filesystem(flash)
    fix = (f"write `filesystem: {{offset: {wanted.offset:#x}, size: {wanted.size:#x}}}` (where MicroPython mounts "
           "it)" if wanted else "name the partition table of your firmware with micropython.partitions.table")
    if end > flash:
        yield error(f"micropython.filesystem: ends at {end:#x}, beyond the {board.flash_size} flash",
                    source.value(FILESYSTEM_PATH), f"{fix}, or fix flash_size if the board has more flash")
    regions = []
    if layout.bootloader is not None:
        regions.append(("the bootloader", layout.bootloader, layout.partition_table))
        regions.append(("the partition table", layout.partition_table,
                        layout.partition_table + PARTITION_TABLE_SECTOR_BYTES))
    regions += [(f"the {p.label} partition" + (" (MicroPython itself)" if p.is_app else ""), p.offset, p.end)
                for p in layout.partitions if p is not wanted and p.label not in FILESYSTEM_LABELS]
    hits = [(label, a, b) for label, a, b in regions if _overlap(start, end, a, b)]
    for label, a, b in hits:
        yield error(
            f"micropython.filesystem: {start:#x}..{end:#x} overlaps {label} at {a:#x}..{b:#x} in {layout.origin}: "
            "flashing the image would overwrite it and the board would not boot",
            where, fix,
        )
    if hits or end > flash:
        return
    if wanted is None:
        yield error(f"micropython.filesystem: {layout.origin} has no filesystem partition (vfs or ffat)",
                    where, fix)
    elif (start, fs.size) != (wanted.offset, wanted.size):
        consequence = ("would not mount: LittleFS records its size, and MicroPython would report the filesystem "
                       "as corrupted" if start == wanted.offset else "would sit where MicroPython never looks")
        if start == wanted.offset:
            where = source.value(FILESYSTEM_PATH + ("size",))
        yield error(
            f"micropython.filesystem: {layout.origin} mounts the filesystem at {wanted.offset:#x} "
            f"({wanted.size:#x} bytes); an image at {start:#x} ({fs.size:#x} bytes) {consequence}",
            where, fix,
        )


def check_flash_layout(board: Board, source: SourceMap, own: Optional[FlashLayout] = None) -> list[Diagnostic]:
    """Every finding about where the board's bootloader, partition table, app and filesystem sit: against the
    board's own partition table when it names one, else against MicroPython's firmware for the chip."""
    flash = board.flash_bytes
    fs = board.micropython.filesystem
    layout = own or micropython_layout(board)
    found: list[Diagnostic] = []
    if layout is None:  # a chip and flash size without a known firmware: only what holds for any layout
        if fs.offset + fs.size > flash:
            found.append(error(f"micropython.filesystem: ends at {fs.offset + fs.size:#x}, beyond the "
                               f"{board.flash_size} flash", source.value(FILESYSTEM_PATH)))
        return found
    if own is not None:
        found += _check_table_rows(own, flash)
    if layout.bootloader is not None:
        found += _check_boot_area(board, layout, source, own is not None)
    found += _check_filesystem(board, layout, source)
    return found
