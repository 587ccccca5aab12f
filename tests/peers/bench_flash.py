"""How long the 2 MiB filesystem image (plus a 252 KiB firmware: bootloader, partition table, 192 KiB app) takes to
flash into the ROM loader peer, by path.

    python tests/peers/bench_flash.py          # prints a table; not a test
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent.parent), str(HERE.parent)]

from codegen.deploy.build import build  # noqa: E402
from codegen.deploy.flash import flash  # noqa: E402
from peers.esp_rom import RomLoaderPeer  # noqa: E402
from peers.trees import default_board, make_tree, merged_firmware  # noqa: E402


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        tree = make_tree(root / "out")
        board = default_board()
        build(tree, board=board, progress=lambda _: None)
        firmware = root / "fw.bin"
        firmware.write_bytes(merged_firmware())
        print(f"{'path':40s} {'seconds':>8s}")
        for label, stub, compress in (("ROM loader, 0x400 blocks (--no-stub)", False, False),
                                      ("ROM loader, compressed", False, True),
                                      ("stub, compressed (default)", True, True)):
            with RomLoaderPeer() as peer:
                started = time.monotonic()
                flash(tree, peer.url, firmware=firmware, board=board, stub=stub, compress=compress,
                      progress=lambda _: None)
                print(f"{label:40s} {time.monotonic() - started:8.1f}")


if __name__ == "__main__":
    main()
