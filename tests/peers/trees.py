"""Small generated-tree stand-ins and firmware images for the deploy tests (made here, never downloaded).

`merged_firmware` lays a firmware out as MicroPython publishes it (the .bin written at the bootloader offset):
bootloader image, the binary partition table at 0x8000, the app image at 0x10000. Its partition table encoder is
written here from ESP-IDF's format description, independently of the product's reader.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

from codegen.board.model import Board

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_BOARD_YAML = ROOT / "board_configs" / "ttgo-tbeam-v1.1.yaml"

APP_FILES = {
    "main.py": "import app\napp.run()\n",
    "app.py": "from lib import util\n\ndef run():\n    print('deadreckon', util.double(21))\n",
    "lib/util.py": "def double(x):\n    return 2 * x\n",
    "config.json": '{"rate_hz": 200}\n',
}


def default_board(**changes) -> Board:
    """The bundled default board, validated by the model alone (independent of the whole-board rules)."""
    from ruamel.yaml import YAML

    data = YAML(typ="safe").load(DEFAULT_BOARD_YAML.read_text())
    for dotted, value in changes.items():
        node = data
        *parents, last = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[last] = value
    return Board.model_validate(data)


def make_tree(root: Path, files: dict[str, str] | None = None) -> Path:
    """A folder shaped like `deadreckon generate`'s output: a sealed MANIFEST.json + app/."""
    files = APP_FILES if files is None else files
    from codegen import __version__
    from codegen.generate import seal

    manifest = {"generator": f"deadreckon {__version__}", "board_files": [str(DEFAULT_BOARD_YAML)],
                "board": "ttgo-tbeam-v1.1", "files": {}}
    for rel, text in files.items():
        path = root / "app" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        manifest["files"][f"app/{rel}"] = {"sha256": hashlib.sha256(text.encode()).hexdigest()}
    (root / "MANIFEST.json").write_text(json.dumps(seal(manifest), indent=2))
    return root


def esp_image(chip_id: int = 0, segment_bytes: int = 0x30000, seed: int = 1) -> bytes:
    """A well-formed ESP firmware image (the layout esptool parses): header, extended header, one segment,
    checksum. chip_id 0 is the ESP32, 9 the ESP32-S3. Contents are pseudo-random 5-bit values, which deflate
    to about 60 %, as real firmware does."""
    rng = hashlib.sha256(seed.to_bytes(4, "little"))
    data = bytearray()
    while len(data) < segment_bytes:
        rng = hashlib.sha256(rng.digest())
        data += rng.digest()
    data = bytes(b & 0x1F for b in data[:segment_bytes])
    header = struct.pack("<BBBBI", 0xE9, 1, 2, 0x20, 0x400D0018)  # magic, 1 segment, DIO, 4MB@40m, entry
    extended = struct.pack("<B3sHBHH4sB", 0xEE, b"\0\0\0", chip_id, 0, 0, 0, b"\0\0\0\0", 0)
    segment = struct.pack("<II", 0x3F400020, len(data)) + data
    body = header + extended + segment
    check = 0xEF
    for byte in data:
        check ^= byte
    padding = 15 - (len(body) % 16)
    return body + b"\0" * padding + bytes([check])



# MicroPython 1.24's ESP32_GENERIC layout (ports/esp32/partitions-4MiB.csv): (label, type, subtype, offset, size)
MICROPYTHON_4MIB = (
    ("nvs", 0x01, 0x02, 0x9000, 0x6000),
    ("phy_init", 0x01, 0x01, 0xF000, 0x1000),
    ("factory", 0x00, 0x00, 0x10000, 0x1F0000),
    ("vfs", 0x01, 0x81, 0x200000, 0x200000),
)


def partition_table_binary(rows=MICROPYTHON_4MIB, md5: bool = True) -> bytes:
    """ESP-IDF's binary partition table: 32-byte rows (0xAA50, type, subtype, offset, size, 16-byte label,
    flags), an MD5 row (0xEBEB, 14 bytes 0xFF, the MD5 of the rows), padded with 0xFF to 0xC00 bytes."""
    table = b"".join(struct.pack("<2sBBII16sI", b"\xaa\x50", kind, subtype, offset, size, label.encode(), 0)
                     for label, kind, subtype, offset, size in rows)
    if md5:
        table += b"\xeb\xeb" + b"\xff" * 14 + hashlib.md5(table).digest()
    return table + b"\xff" * (0xC00 - len(table))


def merged_firmware(chip_id: int = 0, bootloader_offset: int = 0x1000, rows=MICROPYTHON_4MIB,
                    app_bytes: int = 0x30000, table: bytes | None = None) -> bytes:
    """A whole firmware file as written at `bootloader_offset`: bootloader, partition table (0x8000), app (the
    factory row's offset)."""
    app_offset = next(offset for _, kind, _, offset, _ in rows if kind == 0)  # the factory or first OTA slot
    image = bytearray(esp_image(chip_id, segment_bytes=0x4000, seed=2))
    image += b"\xff" * (0x8000 - bootloader_offset - len(image))
    image += partition_table_binary(rows) if table is None else table
    image += b"\xff" * (app_offset - bootloader_offset - len(image))
    image += esp_image(chip_id, segment_bytes=app_bytes)
    return bytes(image)
