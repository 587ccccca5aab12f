"""`deadreckon flash OUT --port PORT`: firmware (optional) and the app's filesystem image onto an ESP32, by esptool.

esptool 5 does the talking (`write-flash`, which verifies every region by MD5 afterwards); this module plans the
regions from the board's layout, checks what can be checked before touching the board, runs esptool, and turns
its failures into messages that say what to do. Flash mode, frequency and size are always `keep`: anything else
makes esptool rewrite the firmware's header.

Nothing is written before the layout is known to be right: a firmware image must be a whole MicroPython image for
the board's chip whose own partition table (read from the image) agrees with the board YAML; without a firmware,
the partition table of the MicroPython already on the board is read back first (`read_board_layout`) and must agree.
The build must be current (`codegen.deploy.buildrecord`), the port must be a port, and esptool is stopped when it
goes silent for longer than its own longest wait.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from struct import error as struct_error
from typing import Callable, Optional

from codegen.board.chips import CHIPS
from codegen.board.flashlayout import FlashLayout
from codegen.board.model import Board
from codegen.deploy.ports import (BUSY_HINT, DIALOUT_HINT, check_port, is_url, open_failure, ports_hint,
                                  rfc2217_refused)
from codegen.errors import UserError

FAST_BAUD = 460800
SAFE_BAUD = 115200
ESP_IMAGE_MAGIC = 0xE9
IMAGE_CHIP_IDS = {"esp32": 0x0000, "esp32s3": 0x0009}  # the chip id in an ESP image's extended header
IMAGE_CHIP_NAMES = {0x0000: "ESP32", 0x0002: "ESP32-S2", 0x0005: "ESP32-C3", 0x0009: "ESP32-S3", 0x000C: "ESP32-C2",
                    0x000D: "ESP32-C6", 0x0010: "ESP32-H2"}
FIRMWARE_NAMES = {"esp32": "ESP32_GENERIC", "esp32s3": "ESP32_GENERIC_S3"}
ESPTOOL_CHIP_ERASE_S = 120.0  # esptool's CHIP_ERASE_TIMEOUT
ESPTOOL_ERASE_S_PER_MIB = 40.0  # esptool's ERASE_WRITE_TIMEOUT_PER_MB
ESPTOOL_SILENCE_MARGIN_S = 15.0
ESPTOOL_STALLED = "deadreckon: esptool stalled"

Progress = Callable[[str], None]


@dataclass(frozen=True)
class Region:
    offset: int
    path: Path
    label: str
    size: int


@dataclass
class FlashResult:
    regions: list[Region]
    baud: int
    seconds: float
    output: str = ""
    attempts: list[str] = field(default_factory=list)


def plan_regions(board: Board, image: Path, firmware: Optional[Path] = None) -> list[Region]:
    """The (offset, file) pairs to write, after checking they fit the board's layout and flash."""
    fs = board.micropython.filesystem
    layout_end = fs.offset + fs.size
    if layout_end > board.flash_bytes:
        raise UserError(
            f"the layout ends at {layout_end:#x} (vfs at {fs.offset:#x} + {fs.size:#x}) but {board.name} has "
            f"{board.flash_size} of flash",
            hint="fix micropython.filesystem in the board YAML, or flash_size if the board has more flash",
        )
    image = Path(image)
    if not image.is_file():
        raise UserError(f"no filesystem image at {image}", hint="run `deadreckon build OUT` first")
    image_size = image.stat().st_size
    if image_size > fs.size:
        raise UserError(
            f"the filesystem image {image} ({image_size} bytes) is larger than the vfs partition ({fs.size} bytes)",
            hint="rebuild with `deadreckon build OUT` after changing the board's filesystem size",
        )
    regions = []
    if firmware is not None:
        firmware = Path(firmware)
        if not os.path.lexists(firmware):
            raise UserError(f"no firmware file at {firmware}", hint="download MicroPython's ESP32 .bin first")
        check_firmware(board, firmware)
        start = board.micropython.partitions.bootloader
        size = firmware.stat().st_size
        if start + size > fs.offset:
            raise UserError(
                f"the firmware {firmware} ({size} bytes at {start:#x}) runs into the vfs partition at {fs.offset:#x}",
                hint="this firmware needs a different layout: check micropython.filesystem.offset in the board YAML",
            )
        regions.append(Region(start, firmware, "MicroPython firmware", size))
    regions.append(Region(fs.offset, image, "filesystem image", image_size))
    return regions


def _read_firmware(board: Board, firmware: Path) -> bytes:
    from codegen.safeio import read_bounded

    return read_bounded(firmware, str(firmware), board.flash_bytes, what="firmware image",
                        typical=f"at most the {board.flash_size} flash")


def layout_from_table(board: Board, table: bytes, origin: str, damaged_hint: str) -> FlashLayout:
    """The layout a binary partition table describes, checked against the board YAML; a UserError when they
    disagree (the image would land where that firmware keeps something else, or where it does not look)."""
    from codegen.board.flashlayout import (
        AUTO_VFS_SINCE,
        FILESYSTEM_LABELS,
        PartitionTableError,
        check_flash_layout,
        parse_partition_binary,
        version_tuple,
    )
    from codegen.board.yamlsource import SourceMap

    partitions = board.micropython.partitions
    try:
        rows = parse_partition_binary(table)
    except PartitionTableError as problem:
        raise UserError(f"the partition table of {origin} is damaged: {problem.message}", hint=damaged_hint) from None
    layout = FlashLayout(origin, partitions.bootloader, partitions.partition_table, tuple(rows),
                         auto_filesystem=not any(row.label in FILESYSTEM_LABELS for row in rows))
    if layout.auto_filesystem and version_tuple(board.micropython.version) < AUTO_VFS_SINCE:
        raise UserError(
            f"{origin} has no vfs partition, as MicroPython 1.26 and later have (it makes one at boot), but the "
            f"board YAML says MicroPython {board.micropython.version}",
            hint="set micropython.version in the board YAML to the firmware's release",
        )
    found = [d for d in check_flash_layout(board, SourceMap(), layout) if d.severity == "error"]
    if found:
        raise UserError(f"the board YAML does not match {origin}: {found[0].message}",
                        hint=found[0].hint or "fix micropython.partitions/filesystem in the board YAML")
    return layout


def read_board_layout(board: Board, port: str, stub: bool, progress: Progress) -> FlashLayout:
    """Read the partition table of the firmware already on the board (esptool read-flash, 3 KiB at 115200 baud;
    the ROM loader reads it too) and check the board YAML against it, before the filesystem image is written
    without a firmware: the image must land in that firmware's filesystem partition, not in its app."""
    from codegen.board.flashlayout import PARTITION_TABLE_MAX_BYTES

    offset = board.micropython.partitions.partition_table
    with tempfile.TemporaryDirectory(prefix="deadreckon-") as folder:
        target = Path(folder) / "partition-table.bin"
        command = esptool_base(board, port, SAFE_BAUD, stub) + [
            "read-flash", f"{offset:#x}", f"{PARTITION_TABLE_MAX_BYTES:#x}", str(target)]
        progress(f"reading the board's partition table at {offset:#x}")
        status, output = run_esptool(command, progress, CHIPS[board.chip].name)
        if status != 0 or not target.is_file():
            raise classify(output, port, board, []) or UserError(
                f"cannot read the partition table of the board on {port}: {_last_error_line(output)}",
                hint="run the same command again; with --firmware the board's table is not needed")
        table = target.read_bytes()
    if table[:2] == b"\xff\xff":
        raise UserError(f"the board on {port} has no partition table at {offset:#x}: no MicroPython is on it (a "
                        "blank or erased flash), so the app's filesystem alone would not run",
                        hint=f"write MicroPython with it: --firmware {FIRMWARE_NAMES[board.chip]}-v"
                             f"{board.micropython.version}.bin")
    return layout_from_table(board, table, f"the firmware on the board on {port}",
                             damaged_hint="write a fresh MicroPython with --firmware (and --erase)")


def check_firmware(board: Board, firmware: Path) -> FlashLayout:
    """Read the firmware image about to be written at the bootloader offset and check it against the board
    before anything is written: an ESP image for the board's chip, with a partition table at the board's
    partition table offset (a merged MicroPython image: bootloader, partition table, app), whose app and
    filesystem partitions are where the board YAML puts them. Return the layout the image's table describes."""
    data = _read_firmware(board, firmware)
    chip = CHIPS[board.chip].name
    if not data or data[0] != ESP_IMAGE_MAGIC:
        raise UserError(
            f"{firmware} is not an ESP firmware image (it does not start with 0xE9)",
            hint="use the MicroPython .bin for ESP32_GENERIC (the one flashed at 0x1000), not a .uf2, .elf or .zip",
        )
    expected_id = IMAGE_CHIP_IDS[board.chip]
    if len(data) >= 14 and int.from_bytes(data[12:14], "little") != expected_id:
        found_id = int.from_bytes(data[12:14], "little")
        raise UserError(
            f"the firmware {firmware} is not built for an {chip} (its header names chip id {found_id}"
            f"{', the ' + IMAGE_CHIP_NAMES[found_id] if found_id in IMAGE_CHIP_NAMES else ''})",
            hint=f"download the MicroPython firmware for the {chip} ({FIRMWARE_NAMES[board.chip]})",
        )
    partitions = board.micropython.partitions
    table_at = partitions.partition_table - partitions.bootloader
    whole = "a whole MicroPython image holds the bootloader, the partition table and MicroPython"
    if len(data) < table_at + 2 or data[table_at : table_at + 2] != b"\xaa\x50":
        raise UserError(
            f"the firmware {firmware} has no partition table at {partitions.partition_table:#x} (file offset "
            f"{table_at:#x}): it is not a whole MicroPython image for {partitions.bootloader:#x}",
            hint=f"{whole}; use the .bin from micropython.org/download for {FIRMWARE_NAMES[board.chip]}, not the "
                 "app-only micropython.bin of a build",
        )
    layout = layout_from_table(board, data[table_at:], f"the firmware {firmware.name}",
                               damaged_hint="download the firmware again")
    app = layout.app()
    app_at = app.offset - partitions.bootloader
    if data[app_at : app_at + 1] != bytes([ESP_IMAGE_MAGIC]):
        raise UserError(f"the firmware {firmware} has no app image at {app.offset:#x} where its partition table "
                        "puts MicroPython", hint=whole)
    if len(data) - app_at > app.size:
        raise UserError(f"the firmware {firmware} runs {len(data) - app_at - app.size} bytes past its own app "
                        f"partition ({app.span()})", hint="download the firmware again")
    try:
        from esptool.bin_image import LoadFirmwareImage
        from esptool.util import FatalError

        image = LoadFirmwareImage(board.chip, data[app_at:])
    except (FatalError, ValueError, struct_error, IndexError) as problem:
        raise UserError(f"the MicroPython app inside {firmware} (at {app.offset:#x}) is damaged: {problem}",
                        hint="download the firmware again") from None
    if image.chip_id != expected_id:
        raise UserError(f"the MicroPython app inside {firmware} is not built for an {chip}",
                        hint=f"download the MicroPython firmware for the {chip}")
    digest_bad = image.append_digest and image.stored_digest != image.calc_digest
    if image.checksum != image.calculate_checksum() or digest_bad:
        raise UserError(f"the MicroPython app inside {firmware} (at {app.offset:#x}) is damaged: its "
                        f"{'SHA-256 digest' if digest_bad else 'checksum'} does not match its contents",
                        hint="download the firmware again")
    return layout


def esptool_base(board: Board, port: str, baud: int, stub: bool) -> list[str]:
    """esptool's connection options for the board on `port`."""
    before = "no-reset" if port.startswith("socket://") else "default-reset"  # a TCP socket has no DTR/RTS
    command = [sys.executable, "-m", "esptool", "--chip", board.chip, "--port", port, "--baud", str(baud),
               "--before", before, "--after", "hard-reset"]
    if not stub:
        command.append("--no-stub")
    return command


def esptool_command(board: Board, port: str, regions: list[Region], baud: int, stub: bool = True,
                    erase: bool = False, compress: Optional[bool] = None) -> list[str]:
    """The esptool 5 command line for these regions."""
    command = esptool_base(board, port, baud, stub)
    command += ["write-flash", "--flash-mode", "keep", "--flash-freq", "keep", "--flash-size", "keep"]
    if erase:
        command.append("--erase-all")
    if compress is None:
        compress = True  # the stub and the ESP32 ROM both inflate; a mostly empty 2 MiB image shrinks to kilobytes
    if compress:
        command.append("--compress")
    else:
        command.append("--no-compress")
    for region in regions:
        command += [f"{region.offset:#x}", str(region.path)]
    return command


def classify(output: str, port: str, board: Board, regions: list[Region]) -> Optional[UserError]:
    """Turn esptool's output into a UserError that says what happened and what to do; None if unknown."""
    text = output
    lower = text.lower()
    expected = CHIPS[board.chip].name
    stalled = re.search(re.escape(ESPTOOL_STALLED) + r": no output for (\d+) s", text)
    if stalled:
        return UserError(
            f"the board on {port} stopped answering: esptool printed nothing for {stalled[1]} s and was stopped",
            hint="press RESET (holding BOOT) and run the same command again; the write starts over and is verified",
        )
    if "this chip is " in lower and "wrong chip argument" in lower:
        found = text[lower.index("this chip is ") + len("this chip is "):].split(",")[0].split()[0]
        return UserError(
            f"the chip on {port} is {found}, but {board.name} has an {expected}",
            hint="check the port (is another board plugged in?) or the chip: in the board YAML",
        )
    if "doesn't appear to be an" in lower or "unexpected chip" in lower:
        return UserError(
            f"the chip on {port} is not an {expected} (its chip magic value is unknown to esptool)",
            hint="check the port, and the chip: in the board YAML",
        )
    if "will not fit in" in lower:
        return UserError(
            f"the board on {port} has less flash than {board.name}'s layout needs ({board.flash_size})",
            hint="set flash_size and micropython.filesystem in the board YAML to match the board's flash",
        )
    if "is not an" in lower and "image" in lower and "--force" in lower:
        return UserError(
            f"the firmware is not built for an {expected}",
            hint="download the MicroPython firmware for this chip (ESP32_GENERIC for an ESP32)",
        )
    if "permission denied" in lower:
        return UserError(f"permission denied on {port}", hint=DIALOUT_HINT)
    if "could not exclusively lock" in lower or "resource busy" in lower:
        return UserError(f"port {port} is busy", hint=BUSY_HINT)
    if "does not seem to support rfc2217" in lower:
        return rfc2217_refused(port)
    if "connection refused" in lower or "no such file or directory" in lower and "could not open port" in lower:
        hint = "is the server at that address running?" if is_url(port) else ports_hint()
        return UserError(f"no such port {port} (nothing answers there)", hint=hint)
    if "md5 of file does not match" in lower or "write failed" in lower:
        return UserError(
            f"verification failed: the flash on {port} does not hold what was written",
            hint="try again; if it repeats, try --no-stub or a lower speed (a worn flash chip or a bad cable)",
        )
    if ("invalid head of packet" in lower or "invalid slip escape" in lower or "corrupt" in lower
            or "serial noise" in lower):
        return UserError(
            f"the board's replies on {port} arrived corrupted",
            hint="try again; a shorter or better USB cable helps, and so does a lower baud rate",
        )
    if ("socket disconnected" in lower or "lost connection" in lower or "no more data" in lower
            or "connection reset" in lower or "broken pipe" in lower or "stopped responding" in lower
            or "serial exception" in lower or "device disconnected" in lower
            or "packet content transfer stopped" in lower or "timed out waiting" in lower):
        return UserError(
            f"the connection to the board on {port} was lost while flashing",
            hint="check the cable and run the same command again; the write starts over and is verified",
        )
    if "could not open" in lower and is_url(port):
        known = open_failure(port, text)  # an unresolved host, a bad URL option: said as upload says them
        if not known.message.startswith("cannot open"):
            return known
    if "could not open" in lower:
        reason = re.search(r"could not open [^\n]*\n\(?([^\n)]+)", text, re.IGNORECASE)
        return UserError(f"cannot open {port}" + (f": {reason[1].strip()}" if reason else ""),
                         hint="is it the board's port, and is nothing else holding it?")
    if "failed to connect" in lower:
        return UserError(
            f"no {expected} bootloader answered on {port}",
            hint="hold BOOT (GPIO0) while pressing RESET/EN to enter the download mode, then run the command again",
        )
    return None


def _last_error_line(output: str) -> str:
    """esptool's last line that says what went wrong: a line naming an error, else its last line; never a line
    of a Python traceback (its frames and source lines are indented), which says where, not what."""
    lines = [line.strip() for line in output.splitlines() if line.strip() and not line.startswith(
        (" ", "\t", "Traceback", "During handling", "The above exception"))]
    for line in reversed(lines):
        if "error" in line.lower():
            return line
    return lines[-1] if lines else "no output"


def silence_limit(regions: list[Region]) -> float:
    """How long esptool may print nothing before it counts as stuck: its own longest wait, an erase, is 40 s per
    MiB of the largest region it begins (esptool's ERASE_WRITE_TIMEOUT_PER_MB) or 120 s for the whole chip."""
    largest = max((region.size for region in regions), default=0)
    return max(ESPTOOL_CHIP_ERASE_S, ESPTOOL_ERASE_S_PER_MIB * largest / (1024 * 1024)) + ESPTOOL_SILENCE_MARGIN_S


def run_esptool(command: list[str], progress: Progress, expected_chip: str,
                silence_s: float = ESPTOOL_CHIP_ERASE_S) -> tuple[int, str]:
    """Run esptool, echoing its lines (a Python traceback is kept for the diagnosis, not shown); stop it before it
    writes anything if it connected to another chip, and when it has printed nothing for `silence_s` seconds."""
    import selectors

    env = dict(os.environ, PYTHONUNBUFFERED="1", NO_COLOR="1")
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    lines: list[str] = []
    buffer = b""
    shown = -1  # the last quarter of a region's write reported
    in_traceback = False
    assert process.stdout is not None
    selector = selectors.DefaultSelector()
    selector.register(process.stdout, selectors.EVENT_READ)
    try:
        while True:
            if not selector.select(timeout=silence_s):
                process.kill()
                lines.append(f"{ESPTOOL_STALLED}: no output for {silence_s:.0f} s")
                break
            chunk = os.read(process.stdout.fileno(), 4096)
            if not chunk:
                break
            buffer += chunk
            *complete, buffer = buffer.replace(b"\r", b"\n").split(b"\n")
            for raw in complete:
                line = raw.decode("utf-8", "replace").rstrip()
                if not line:
                    continue
                lines.append(line)
                if line.startswith("Traceback (most recent call last)"):
                    in_traceback = True
                if in_traceback:
                    in_traceback = line.startswith((" ", "Traceback", "During handling", "The above exception"))
                    continue
                if line.startswith("Writing at"):
                    match = re.search(r"(\d+(?:\.\d+)?)%", line)
                    quarter = int(float(match.group(1)) // 25) if match else shown
                    if quarter != shown:
                        shown = quarter
                        progress(f"  {line.split()[2]}  {quarter * 25:3d}%")
                    continue
                shown = -1
                progress(f"  {line}")
                if "doesn't appear to be an" in line:
                    process.kill()  # esptool would "attempt to continue anyway" and write to the wrong chip
    finally:
        selector.close()
        process.stdout.close()
    if buffer.strip():
        lines.append(buffer.decode("utf-8", "replace"))
    process.wait()
    return process.returncode, "\n".join(lines)


def flash(out: Path, port: str, firmware: Optional[Path] = None, erase: bool = False,
          board: Optional[Board] = None, stub: bool = True, compress: Optional[bool] = None,
          progress: Progress = print) -> FlashResult:
    """Write OUT/build/fs.img (and the firmware) to the board on `port`, verified; raise UserError on failure."""
    from codegen.deploy.build import IMAGE_NAME, load_tree
    from codegen.deploy.buildrecord import check_build_current

    tree = load_tree(Path(out), board)
    board = tree.board
    if board.target == "circuitpython":
        raise UserError(f"{out} is a CircuitPython app: a CircuitPython board takes its files over its CIRCUITPY "
                        "drive, not a flashed image",
                        hint=f"deadreckon upload {out} --drive PATH (where the computer mounts CIRCUITPY); "
                             "CircuitPython itself is installed from circuitpython.org (UF2 file or web installer)")
    check_build_current(tree.root)
    if board.chip not in ("esp32", "esp32s3"):
        raise UserError(f"flashing {board.chip} boards is not supported (esptool is for Espressif chips)")
    if erase and firmware is None:
        raise UserError("--erase without --firmware would leave the board with no MicroPython to run the app",
                        hint="pass --firmware MICROPYTHON.bin with --erase, or drop --erase to keep the firmware")
    if erase and not stub:
        raise UserError("--erase needs the flasher stub: the ESP32 ROM loader cannot erase the whole flash",
                        hint="drop --no-stub, or flash without --erase")
    regions = plan_regions(board, tree.build_dir / IMAGE_NAME, firmware)
    check_port(port)
    if firmware is None:  # the image goes next to the firmware already there: it must fit that firmware's layout
        read_board_layout(board, port, stub, progress)
    for region in regions:
        progress(f"{region.label}: {region.path} ({region.size} bytes) -> {region.offset:#x}")
    started = time.monotonic()
    attempts = []
    error: Optional[UserError] = None
    output = ""
    for baud in (FAST_BAUD, SAFE_BAUD):
        command = esptool_command(board, port, regions, baud, stub=stub, erase=erase, compress=compress)
        progress(f"esptool at {baud} baud{'' if stub else ' (ROM loader, no stub)'}")
        status, output = run_esptool(command, progress, CHIPS[board.chip].name, silence_limit(regions))
        attempts.append(f"{baud}: exit {status}")
        if status == 0:
            seconds = time.monotonic() - started
            progress(f"flashed and verified {len(regions)} region(s) in {seconds:.1f} s")
            return FlashResult(regions, baud, seconds, output, attempts)
        error = classify(output, port, board, regions)
        # a slower line helps with noise, drops and a silent bootloader; a socket has no line speed
        retriable = error is None or error.message.startswith(("the board's replies", "the connection", "no "))
        if baud == SAFE_BAUD or not retriable or port.startswith("socket://"):
            break
        progress(f"esptool failed at {baud} baud; trying {SAFE_BAUD}")
    if error is None:
        last = _last_error_line(output)
        if last.startswith("Serial port "):  # esptool exits without a word when the port closes as it opens
            error = UserError(f"the connection to {port} closed before esptool could talk to the board",
                              hint="is the bridge or server at the other end running, and is the board attached?")
        else:
            error = UserError(f"esptool failed: {last}",
                              hint="run the esptool command above with --trace to see the exchange")
    raise error
