"""The LittleFS image of a board's vfs partition, with the parameters MicroPython's ESP32 port mounts it with.

MicroPython (ports/esp32, extmod/vfs_lfs) formats the vfs partition as LittleFS v2 with block size = the flash
sector (4096), block count = partition size / 4096, read and prog size 32, lookahead 32, name_max 255. It mounts
disk version 2.0; littlefs-python writes 2.1 unless told otherwise. A mismatch makes the board print
"filesystem appears to be corrupted" at every boot, so `mount_image` reads images back with the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from codegen.errors import UserError
from codegen.safeio import write_atomically

READ_SIZE = 32  # bytes
PROG_SIZE = 32  # bytes
LOOKAHEAD_SIZE = 32  # bytes
NAME_MAX = 255  # bytes
DISK_VERSION = 0x00020000  # LittleFS on-disk format 2.0


@dataclass(frozen=True)
class LfsParams:
    size: int  # partition size, bytes
    block_size: int = 4096  # bytes

    @property
    def block_count(self) -> int:
        return self.size // self.block_size

    def kwargs(self) -> dict:
        return dict(
            block_size=self.block_size,
            block_count=self.block_count,
            read_size=READ_SIZE,
            prog_size=PROG_SIZE,
            lookahead_size=LOOKAHEAD_SIZE,
            name_max=NAME_MAX,
            disk_version=DISK_VERSION,
        )


def _check(params: LfsParams) -> None:
    if params.size % params.block_size:
        raise UserError(
            f"filesystem size {params.size:#x} is not a multiple of its block size {params.block_size}",
            hint="micropython.filesystem.size must be whole 4096-byte sectors",
        )


def image_bytes(source: Path, size: int, block_size: int = 4096) -> bytes:
    """Return a LittleFS image of every file under `source` (paths kept), exactly `size` bytes long."""
    import littlefs

    params = LfsParams(size, block_size)
    _check(params)
    fs = littlefs.LittleFS(**params.kwargs())
    total = 0
    try:
        for path in sorted(Path(source).rglob("*")):
            rel = path.relative_to(source).as_posix()
            if path.is_dir():
                fs.makedirs(rel, exist_ok=True)
            elif path.is_file():
                data = path.read_bytes()
                total += len(data)
                with fs.open(rel, "wb") as handle:
                    handle.write(data)
    except littlefs.errors.LittleFSError as exc:
        if exc.code == littlefs.errors.LittleFSError.Error.LFS_ERR_NOSPC:
            raise UserError(
                f"the app ({total} bytes and growing) does not fit in the {size // 1024} KiB filesystem partition",
                hint="enlarge micropython.filesystem.size in the board YAML, or leave files out of the app",
            )
        raise
    image = bytes(fs.context.buffer)
    assert len(image) == size
    return image


def free_after(files: dict[str, bytes], size: int, block_size: int = 4096) -> Optional[int]:
    """The bytes a LittleFS of `size` bytes has free once `files` ({relative/path: bytes}) are in it, counted in
    whole blocks as LittleFS allocates them; None when they do not fit at all."""
    import littlefs

    params = LfsParams(size, block_size)
    _check(params)
    fs = littlefs.LittleFS(**params.kwargs())
    try:
        for rel, data in sorted(files.items()):
            folder = rel.rpartition("/")[0]
            if folder:
                fs.makedirs(folder, exist_ok=True)
            with fs.open(rel, "wb") as handle:
                handle.write(data)
    except littlefs.errors.LittleFSError as exc:
        if exc.code == littlefs.errors.LittleFSError.Error.LFS_ERR_NOSPC:
            return None
        raise
    return (params.block_count - fs.used_block_count) * block_size


def make_image(source: Path, target: Path, size: int, block_size: int = 4096) -> Path:
    """Write the LittleFS image of `source` to `target`; return `target`."""
    data = image_bytes(source, size, block_size)
    write_atomically(target, data)
    return target


def mount_image(data: bytes, size: int | None = None, block_size: int = 4096):
    """Mount an image (read back from a device or file) as MicroPython would; return the littlefs.LittleFS."""
    import littlefs

    size = len(data) if size is None else size
    params = LfsParams(size, block_size)
    fs = littlefs.LittleFS(mount=False, **params.kwargs())
    fs.context.buffer[:] = bytearray(data[:size])
    fs.mount()
    return fs


def read_tree(fs, top: str = "/") -> dict[str, bytes]:
    """Every file in a mounted LittleFS as {relative/path: bytes}."""
    files: dict[str, bytes] = {}
    for root, _dirs, names in fs.walk(top):
        for name in names:
            path = f"{root.rstrip('/')}/{name}"
            with fs.open(path, "rb") as handle:
                files[path.lstrip("/")] = handle.read()
    return files
