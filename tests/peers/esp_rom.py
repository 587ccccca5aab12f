"""An ESP32 serial ROM loader on a loopback TCP port, for the real esptool (`--port socket://127.0.0.1:PORT`).

Written from Espressif's published serial protocol description; it holds a 4 MiB NOR flash in memory.

    SLIP frames (0xC0 ends, 0xDB 0xDC / 0xDB 0xDD escape 0xC0 / 0xDB)
    request  <BBHI  0x00, opcode, data length, checksum (XOR of the payload seeded with 0xEF) + data
    response <BBHI  0x01, opcode, data length, value + data, ending in status bytes
                    (4 from the ESP32 ROM, 2 from the flasher stub): failed flag, error code

The ROM answers SYNC eight times, rejects GET_SECURITY_INFO (the ESP32 ROM predates it), shows its chip magic
0x00F01D83 at 0x40001000, MAC/revision in eFuse words at 0x3FF5A000 and the SPI flash JEDEC ID through the SPI0
user-command registers at 0x3FF42000. ROM flash writes are 0x400-byte blocks after a 4-word FLASH_BEGIN (which
erases), or FLASH_DEFL_* blocks it inflates itself; SPI_FLASH_MD5 answers 32 hex characters. A RAM upload ending
in MEM_END with an entry point runs the "stub": the peer greets with OHAI and then speaks the stub's dialect
(2 status bytes, 5-word begins, 16-byte binary MD5, ERASE_FLASH/ERASE_REGION, READ_FLASH); the ROM itself reads flash
64 bytes at a time (READ_FLASH_SLOW). Flash programming ANDs
bits into the erased 0xFF, as NOR flash does, so a write without an erase shows up as corrupted data.

Faults for tests (attributes, apply to every connection while set):
    drop_after_blocks   close the connection after this many flash data blocks
    chip_magic          the value read at the chip magic register (e.g. 0x000007C6, an ESP32-S2)
    noise_reply         (opcode, n): send non-SLIP line noise in place of the n-th reply to that opcode
    drop_on_baud_change close the connection at CHANGE_BAUDRATE (a cable or adapter that cannot go faster)
    stall_after_blocks  stop answering (the connection stays open) after this many flash data blocks
    corrupt_program     program every written block with one bit cleared: the write "succeeds", the MD5 lies
"""

from __future__ import annotations

import hashlib
import socket
import struct
import threading
import zlib
from dataclasses import dataclass, field
from typing import Optional

FLASH_SIZE = 4 * 1024 * 1024  # bytes
SECTOR_SIZE = 0x1000  # bytes, the flash erase unit

ESP32_MAGIC = 0x00F01D83
CHIP_MAGIC_REG = 0x40001000
EFUSE_BASE = 0x3FF5A000
SPI0_BASE = 0x3FF42000
SPI_CMD_USR = 1 << 18
UART_CLKDIV_REG = 0x3FF40014
RTCCALICFG1 = 0x3FF5F06C

MAC = bytes.fromhex("240ac4123456")
WINBOND = 0xEF  # JEDEC manufacturer; the capacity byte is log2(size): 0x16 -> 4 MiB
SFDP_SIGNATURE = 0x50444653

# opcodes
FLASH_BEGIN, FLASH_DATA, FLASH_END = 0x02, 0x03, 0x04
MEM_BEGIN, MEM_END, MEM_DATA = 0x05, 0x06, 0x07
SYNC, WRITE_REG, READ_REG = 0x08, 0x09, 0x0A
SPI_SET_PARAMS, SPI_ATTACH, CHANGE_BAUDRATE = 0x0B, 0x0D, 0x0F
FLASH_DEFL_BEGIN, FLASH_DEFL_DATA, FLASH_DEFL_END = 0x10, 0x11, 0x12
SPI_FLASH_MD5, GET_SECURITY_INFO = 0x13, 0x14
READ_FLASH_SLOW = 0x0E
READ_FLASH_SLOW_BLOCK = 64  # bytes the ROM returns per READ_FLASH_SLOW
ERASE_FLASH, ERASE_REGION, READ_FLASH = 0xD0, 0xD1, 0xD2

# error codes in the second status byte
ERR_INVALID_MESSAGE = 0x05
ERR_FAILED = 0x06
ERR_BAD_CHECKSUM = 0x07
ERR_DEFLATE = 0x0B

SYNC_PAYLOAD = b"\x07\x07\x12\x20" + 32 * b"\x55"
IRAM = (0x40070000, 0x400C0000)  # where a stub's text may be loaded and entered


def checksum(data: bytes, state: int = 0xEF) -> int:
    for byte in data:
        state ^= byte
    return state


def slip_encode(packet: bytes) -> bytes:
    return b"\xc0" + packet.replace(b"\xdb", b"\xdb\xdd").replace(b"\xc0", b"\xdb\xdc") + b"\xc0"


def slip_decode(body: bytes) -> bytes:
    return body.replace(b"\xdb\xdc", b"\xc0").replace(b"\xdb\xdd", b"\xdb")


def efuse_words() -> dict[int, int]:
    """eFuse read words of an ESP32-D0WDQ6 rev 1 with a 40 MHz crystal and MAC 24:0a:c4:12:34:56."""
    return {
        1: int.from_bytes(MAC[2:6], "big"),
        2: int.from_bytes(MAC[0:2], "big"),
        3: 1 << 15,  # CHIP_VER_REV1
        4: 0x80,  # CK8M frequency calibration, read by esptool's crystal estimate
    }


class CommandError(Exception):
    def __init__(self, code: int):
        self.code = code


class Dropped(Exception):
    """The peer closes the connection (fault injection)."""


@dataclass
class WriteState:
    offset: int
    block_size: int
    blocks: int
    compressed: bool
    next_seq: int = 0
    written: int = 0
    inflater: Optional[object] = None


@dataclass
class Stats:
    connections: int = 0
    commands: dict = field(default_factory=dict)
    stub_runs: int = 0

    def count(self, op: int) -> None:
        self.commands[op] = self.commands.get(op, 0) + 1


class Session:
    """One connection: the chip freshly reset into its ROM download mode."""

    def __init__(self, peer: "RomLoaderPeer", conn: socket.socket):
        self.peer = peer
        self.conn = conn
        self.stub = False
        self.write: Optional[WriteState] = None
        self.mem: Optional[dict] = None
        self.regs: dict[int, int] = {}
        self.blocks_seen = 0
        self.replies: dict[int, int] = {}
        self.stalled = False

    # -- framing
    def run(self) -> None:
        buffer = b""
        while True:
            chunk = self.conn.recv(65536)
            if not chunk:
                return
            buffer += chunk
            while True:
                start = buffer.find(b"\xc0")
                if start < 0:
                    buffer = b""
                    break
                end = buffer.find(b"\xc0", start + 1)
                if end < 0:
                    buffer = buffer[start:]
                    break
                body = buffer[start + 1 : end]
                buffer = buffer[end:]  # the closing 0xC0 may also open the next frame
                if body:
                    self.handle(slip_decode(body))

    def send(self, packet: bytes) -> None:
        self.conn.sendall(slip_encode(packet))

    def reply(self, op: int, value: int = 0, data: bytes = b"", error: int = 0) -> None:
        self.replies[op] = self.replies.get(op, 0) + 1
        if self.peer.noise_reply == (op, self.replies[op]):
            self.conn.sendall(b"\x55\xaa\x13\x37 line noise")
            return
        status = bytes([1 if error else 0, error])
        status += b"" if self.stub else b"\x00\x00"
        payload = data + status
        self.send(struct.pack("<BBHI", 1, op, len(payload), value) + payload)

    # -- dispatch
    def handle(self, packet: bytes) -> None:
        if self.stalled:
            return  # a chip that hung: it reads, it never answers
        if len(packet) < 8:
            return  # an ack from READ_FLASH, or noise: the ROM ignores it
        direction, op, length, chk = struct.unpack("<BBHI", packet[:8])
        data = packet[8:]
        if direction != 0 or length != len(data):
            self.reply(op, error=ERR_INVALID_MESSAGE)
            return
        self.peer.stats.count(op)
        handler = getattr(self, f"op_{op:02x}", None)
        if handler is None or (op >= 0xD0 and not self.stub):  # GET_SECURITY_INFO has no handler: ESP32 ROM
            self.reply(op, error=ERR_INVALID_MESSAGE)
            return
        try:
            result = handler(data, chk)
        except CommandError as exc:
            self.reply(op, error=exc.code)
            return
        except struct.error:
            self.reply(op, error=ERR_INVALID_MESSAGE)
            return
        if result is None:
            return  # the handler replied itself
        value, payload = result
        self.reply(op, value, payload)

    # -- commands
    def op_08(self, data: bytes, chk: int):  # SYNC
        if data != SYNC_PAYLOAD:
            return None  # not a sync: the ROM stays silent
        value = 0 if self.stub else 0x20120707
        for _ in range(8):
            self.reply(SYNC, value)
        return None

    def read_register(self, addr: int) -> int:
        if addr == CHIP_MAGIC_REG:
            return self.peer.chip_magic
        if EFUSE_BASE <= addr < EFUSE_BASE + 0x100:
            return efuse_words().get((addr - EFUSE_BASE) // 4, 0)
        if addr == UART_CLKDIV_REG:
            return 347  # 40 MHz / 115200 baud
        if addr == RTCCALICFG1:
            return 800 << 7  # with CK8M 0x80: the ROM's crystal estimate is 40 MHz
        return self.regs.get(addr, 0)

    def op_0a(self, data: bytes, chk: int):  # READ_REG
        (addr,) = struct.unpack("<I", data)
        return self.read_register(addr), b""

    def op_09(self, data: bytes, chk: int):  # WRITE_REG, one or more (addr, value, mask, delay) words
        if len(data) % 16:
            raise CommandError(ERR_INVALID_MESSAGE)
        for index in range(0, len(data), 16):
            addr, value, mask, _delay = struct.unpack("<IIII", data[index : index + 16])
            old = self.regs.get(addr, 0)
            self.regs[addr] = (old & ~mask) | (value & mask)
            if addr == SPI0_BASE and value & SPI_CMD_USR:
                self.spi_user_command()
        return 0, b""

    def spi_user_command(self) -> None:
        """Run the SPI flash command the registers describe; the answer goes to W0, the busy bit clears."""
        command = self.regs.get(SPI0_BASE + 0x24, 0) & 0xFF
        address = self.regs.get(SPI0_BASE + 0x04, 0)
        if command == 0x9F:  # RDID
            answer = WINBOND | 0x40 << 8 | (len(self.peer.flash).bit_length() - 1) << 16
        elif command == 0x5A:  # RDSFDP
            answer = SFDP_SIGNATURE if address == 0 else WINBOND
        else:
            answer = 0  # status registers read as 0 (no protection bits), resets and the like just complete
        self.regs[SPI0_BASE + 0x80] = answer
        self.regs[SPI0_BASE] = self.regs.get(SPI0_BASE, 0) & ~SPI_CMD_USR

    def op_0b(self, data: bytes, chk: int):  # SPI_SET_PARAMS
        _id, total, _block, _sector, _page, _mask = struct.unpack("<IIIIII", data)
        if total > len(self.peer.flash):
            raise CommandError(ERR_FAILED)
        return 0, b""

    def op_0d(self, data: bytes, chk: int):  # SPI_ATTACH: 8 bytes from ROM clients, 4 to the stub
        if len(data) != (4 if self.stub else 8):
            raise CommandError(ERR_INVALID_MESSAGE)
        return 0, b""

    def op_0f(self, data: bytes, chk: int):  # CHANGE_BAUDRATE (a socket has no baud rate)
        struct.unpack("<II", data)
        if self.peer.drop_on_baud_change:
            raise Dropped()
        return 0, b""

    def _erase(self, start: int, end: int) -> None:
        start -= start % SECTOR_SIZE
        end = min(len(self.peer.flash), -(-end // SECTOR_SIZE) * SECTOR_SIZE)
        self.peer.flash[start:end] = b"\xff" * (end - start)

    def _program(self, addr: int, data: bytes) -> None:
        flash = self.peer.flash
        if addr + len(data) > len(flash):
            raise CommandError(ERR_FAILED)
        old = flash[addr : addr + len(data)]
        new = (int.from_bytes(old, "little") & int.from_bytes(data, "little")).to_bytes(len(data), "little")
        flash[addr : addr + len(data)] = new

    def _begin(self, data: bytes, compressed: bool) -> tuple[int, bytes]:
        words = 5 if self.stub else 4  # the ESP32 ROM takes no "encrypted" word
        if len(data) != 4 * words:
            raise CommandError(ERR_INVALID_MESSAGE)
        size, blocks, block_size, offset = struct.unpack("<IIII", data[:16])
        if offset % SECTOR_SIZE and not self.stub:
            raise CommandError(ERR_FAILED)
        if offset + size > len(self.peer.flash):
            raise CommandError(ERR_FAILED)
        self._erase(offset, offset + size)
        self.write = WriteState(offset, block_size, blocks, compressed)
        if compressed:
            self.write.inflater = zlib.decompressobj()
        return 0, b""

    def _data(self, data: bytes, chk: int, compressed: bool) -> tuple[int, bytes]:
        state = self.write
        if state is None or state.compressed != compressed:
            raise CommandError(ERR_FAILED)
        size, seq, _, _ = struct.unpack("<IIII", data[:16])
        payload = data[16:]
        if size != len(payload):
            raise CommandError(ERR_INVALID_MESSAGE)
        if checksum(payload) != (chk & 0xFF):
            raise CommandError(ERR_BAD_CHECKSUM)
        if seq != state.next_seq:
            raise CommandError(ERR_FAILED)
        self.blocks_seen += 1
        faults = self.peer
        if faults.drop_after_blocks is not None and self.blocks_seen > faults.drop_after_blocks:
            raise Dropped()
        if faults.stall_after_blocks is not None and self.blocks_seen > faults.stall_after_blocks:
            self.stalled = True
            return None
        if compressed:
            try:
                plain = state.inflater.decompress(payload)
            except zlib.error:
                raise CommandError(ERR_DEFLATE)
        else:
            if not self.stub and len(payload) != state.block_size:
                raise CommandError(ERR_INVALID_MESSAGE)  # the ROM wants whole, padded blocks
            plain = payload
        if faults.corrupt_program and plain:
            plain = bytes([plain[0] & 0xFE]) + plain[1:] if plain[0] & 1 else bytes([plain[0] & 0xFD]) + plain[1:]
        self._program(state.offset + state.written, plain)
        state.written += len(plain)
        state.next_seq += 1
        return 0, b""

    def op_02(self, data: bytes, chk: int):  # FLASH_BEGIN
        return self._begin(data, compressed=False)

    def op_03(self, data: bytes, chk: int):  # FLASH_DATA
        return self._data(data, chk, compressed=False)

    def op_04(self, data: bytes, chk: int):  # FLASH_END
        self.write = None
        return 0, b""

    def op_10(self, data: bytes, chk: int):  # FLASH_DEFL_BEGIN
        return self._begin(data, compressed=True)

    def op_11(self, data: bytes, chk: int):  # FLASH_DEFL_DATA
        return self._data(data, chk, compressed=True)

    def op_12(self, data: bytes, chk: int):  # FLASH_DEFL_END
        self.write = None
        return 0, b""

    def op_13(self, data: bytes, chk: int):  # SPI_FLASH_MD5
        addr, size, _, _ = struct.unpack("<IIII", data)
        if addr + size > len(self.peer.flash):
            raise CommandError(ERR_FAILED)
        digest = hashlib.md5(self.peer.flash[addr : addr + size])
        return 0, (digest.digest() if self.stub else digest.hexdigest().encode())

    def op_0e(self, data: bytes, chk: int):  # READ_FLASH_SLOW (ROM only): always a 64-byte block back
        if self.stub:
            raise CommandError(ERR_INVALID_MESSAGE)
        offset, length = struct.unpack("<II", data)
        if length > READ_FLASH_SLOW_BLOCK or offset + length > len(self.peer.flash):
            raise CommandError(ERR_FAILED)
        block = bytes(self.peer.flash[offset : offset + length])
        return 0, block + b"\xff" * (READ_FLASH_SLOW_BLOCK - len(block))

    def op_05(self, data: bytes, chk: int):  # MEM_BEGIN
        size, blocks, block_size, offset = struct.unpack("<IIII", data)
        self.mem = {"offset": offset, "size": size, "data": bytearray(), "seq": 0}
        return 0, b""

    def op_07(self, data: bytes, chk: int):  # MEM_DATA
        if self.mem is None:
            raise CommandError(ERR_FAILED)
        size, seq, _, _ = struct.unpack("<IIII", data[:16])
        payload = data[16:]
        if size != len(payload) or seq != self.mem["seq"]:
            raise CommandError(ERR_INVALID_MESSAGE)
        if checksum(payload) != (chk & 0xFF):
            raise CommandError(ERR_BAD_CHECKSUM)
        self.mem["data"] += payload
        self.mem["seq"] += 1
        self.peer.ram[self.mem["offset"]] = bytes(self.mem["data"])
        return 0, b""

    def op_06(self, data: bytes, chk: int):  # MEM_END: run the uploaded code at the entry point
        no_entry, entry = struct.unpack("<II", data)
        self.reply(MEM_END, 0, b"")
        if no_entry:
            return None
        loaded = any(start <= entry < start + len(code) for start, code in self.peer.ram.items())
        if not (IRAM[0] <= entry < IRAM[1]) or not loaded:
            return None  # jumping into nothing: a real chip would crash and stay silent
        self.stub = True
        self.peer.stats.stub_runs += 1
        self.send(b"OHAI")
        return None

    # stub-only commands
    def op_d0(self, data: bytes, chk: int):  # ERASE_FLASH
        self._erase(0, len(self.peer.flash))
        return 0, b""

    def op_d1(self, data: bytes, chk: int):  # ERASE_REGION
        offset, size = struct.unpack("<II", data)
        if offset % SECTOR_SIZE or size % SECTOR_SIZE:
            raise CommandError(ERR_INVALID_MESSAGE)
        self._erase(offset, offset + size)
        return 0, b""

    def op_d2(self, data: bytes, chk: int):  # READ_FLASH: data frames, then the MD5 of all of it
        offset, length, sector, _in_flight = struct.unpack("<IIII", data)
        self.reply(READ_FLASH, 0, b"")
        chunk = bytes(self.peer.flash[offset : offset + length])
        for index in range(0, len(chunk), sector):
            self.send(chunk[index : index + sector])
        self.send(hashlib.md5(chunk).digest())
        return None


class RomLoaderPeer:
    """The emulated ESP32 on 127.0.0.1; one client at a time, like a serial port. Use as a context manager."""

    def __init__(self, flash_size: int = FLASH_SIZE, chip_magic: int = ESP32_MAGIC):
        self.flash = bytearray(b"\xff" * flash_size)
        self.ram: dict[int, bytes] = {}
        self.chip_magic = chip_magic
        self.drop_after_blocks: Optional[int] = None
        self.noise_reply: Optional[tuple[int, int]] = None
        self.drop_on_baud_change = False
        self.stall_after_blocks: Optional[int] = None
        self.corrupt_program = False
        self.stats = Stats()
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", 0))
        self._server.listen(4)
        self._thread: Optional[threading.Thread] = None
        self._stopping = False

    @property
    def port(self) -> int:
        return self._server.getsockname()[1]

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def clear_faults(self) -> None:
        self.chip_magic = ESP32_MAGIC
        self.drop_after_blocks = None
        self.noise_reply = None
        self.drop_on_baud_change = False
        self.stall_after_blocks = None
        self.corrupt_program = False

    def start(self) -> "RomLoaderPeer":
        self._thread = threading.Thread(target=self._serve, name="esp32-rom-peer", daemon=True)
        self._thread.start()
        return self

    def _serve(self) -> None:
        while not self._stopping:
            try:
                conn, _ = self._server.accept()
            except OSError:
                return
            self.stats.connections += 1
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            try:
                Session(self, conn).run()
            except (Dropped, OSError):
                pass
            finally:
                try:
                    conn.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                conn.close()

    def stop(self) -> None:
        self._stopping = True
        try:
            self._server.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._server.close()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def __enter__(self) -> "RomLoaderPeer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


if __name__ == "__main__":
    import argparse
    import time

    parser = argparse.ArgumentParser(description="emulated ESP32 ROM loader on a loopback port")
    parser.add_argument("--port", type=int, default=0)
    args = parser.parse_args()
    peer = RomLoaderPeer()
    if args.port:
        peer._server.close()
        peer._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        peer._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        peer._server.bind(("127.0.0.1", args.port))
        peer._server.listen(4)
    peer.start()
    print(f"ESP32 ROM loader peer on {peer.url}", flush=True)
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        peer.stop()
