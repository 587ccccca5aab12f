"""`deadreckon build`: .mpy for the board's arch and MicroPython, and a LittleFS image MicroPython mounts."""

from __future__ import annotations

import subprocess

import pytest

from codegen.deploy.build import build
from codegen.tools import mpy_format
from codegen.deploy.fsimage import DISK_VERSION, image_bytes, mount_image, read_tree
from codegen.errors import UserError
from conftest import require_tool
from peers.trees import APP_FILES, default_board, make_tree


@pytest.fixture
def built(tmp_path):
    tree = make_tree(tmp_path / "out")
    lines = []
    result = build(tree, board=default_board(), progress=lines.append)
    return tree, result, lines


def test_build_compiles_for_the_board_and_keeps_main_as_source(built):
    tree, result, lines = built
    assert sorted(result.files) == ["app.mpy", "config.json", "lib/util.mpy", "main.py"]
    mpy = (result.app_dir / "app.mpy").read_bytes()
    assert mpy[:2] == b"M\x06"  # .mpy format 6.x, what MicroPython 1.24 loads
    assert (result.app_dir / "main.py").read_text() == APP_FILES["main.py"]
    assert result.image == tree / "build" / "fs.img"
    assert all(p.is_relative_to(tree / "build") for p in result.app_dir.rglob("*"))
    assert any("pure-Python fallback" in line for line in lines)  # said plainly when no natmod is built
    assert any("[4/4]" in line for line in lines)  # progress per file


def test_mpy_format_follows_the_micropython_release():
    assert mpy_format("1.24.1") == "6.3"
    assert mpy_format("1.22.2") == "6.2"
    assert mpy_format("1.20.0") == "6.1"
    with pytest.raises(UserError, match="too old"):
        mpy_format("1.18")


def test_syntax_error_is_a_user_error(tmp_path):
    tree = make_tree(tmp_path / "out", {"main.py": "pass\n", "bad.py": "def f(:\n"})
    with pytest.raises(UserError, match="mpy-cross failed on bad.py"):
        build(tree, board=default_board(), progress=lambda _: None)


def test_image_has_micropythons_littlefs_parameters(built):
    tree, result, _ = built
    board = default_board()
    data = result.image.read_bytes()
    assert len(data) == board.micropython.filesystem.size
    fs = mount_image(data, block_size=4096)
    stat = fs.fs_stat()
    assert (stat.disk_version, stat.block_size, stat.block_count, stat.name_max) == (DISK_VERSION, 4096, 512, 255)
    files = read_tree(fs)
    assert files == {rel: (result.app_dir / rel).read_bytes() for rel in result.files}


def test_image_with_the_wrong_block_size_does_not_mount(built):
    _, result, _ = built
    with pytest.raises(Exception):
        mount_image(result.image.read_bytes(), block_size=512)


def test_image_mounts_on_real_micropython_as_the_esp32_port_does(built, tmp_path):
    micropython = require_tool("micropython")
    _, result, _ = built
    script = tmp_path / "mount.py"
    script.write_text(f"""
import vfs
class Partition:  # a block device like esp32.Partition: 4096-byte blocks, extended interface
    def __init__(self, path, size):
        self.file = open(path, "r+b")
        self.size = size
    def readblocks(self, n, buf, off=0):
        self.file.seek(n * 4096 + off)
        self.file.readinto(buf)
    def writeblocks(self, n, buf, off=None):
        raise OSError(30)  # EROFS: mounting must not need to write
    def ioctl(self, op, arg):
        if op == 4: return self.size // 4096
        if op == 5: return 4096
        if op == 6: return 0
bdev = Partition({str(result.image)!r}, {result.image.stat().st_size})
vfs.mount(vfs.VfsLfs2(bdev, readsize=32, progsize=32, lookahead=32), "/flash")
print(sorted(__import__("os").listdir("/flash")))
print(open("/flash/main.py").read().strip().replace(chr(10), "|"))
print(len(open("/flash/lib/util.mpy", "rb").read()))
""")
    out = subprocess.run([micropython, str(script)], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr + out.stdout
    lines = out.stdout.splitlines()
    assert lines[0] == "['app.mpy', 'config.json', 'lib', 'main.py']"
    assert lines[1] == APP_FILES["main.py"].strip().replace("\n", "|")
    assert int(lines[2]) == (result.app_dir / "lib/util.mpy").stat().st_size


def test_app_too_big_for_the_partition(tmp_path):
    (tmp_path / "big.bin").write_bytes(bytes(range(256)) * 4096 * 3)  # 3 MiB does not fit in 64 KiB
    with pytest.raises(UserError, match="does not fit"):
        image_bytes(tmp_path, size=64 * 1024)


def test_build_cli_on_a_tree_without_manifest(tmp_path, capsys):
    from codegen.cli import main

    (tmp_path / "app").mkdir()
    assert main(["build", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "MANIFEST.json" in err and "Traceback" not in err


def test_native_module_needs_mpy_dir_and_a_cross_compiler(tmp_path, monkeypatch):
    tree = make_tree(tmp_path / "out")
    (tree / "native").mkdir()
    (tree / "native" / "Makefile").write_text("include $(MPY_DIR)/py/dynruntime.mk\n")
    monkeypatch.delenv("MPY_DIR", raising=False)
    monkeypatch.setattr("codegen.tools.SHARED_MICROPYTHON", tmp_path / "no-shared-tree")
    monkeypatch.setenv("DEADRECKON_CACHE", str(tmp_path / "cache"))  # nothing cached, and the download fails:
    monkeypatch.setenv("DEADRECKON_MICROPYTHON_URL", "http://127.0.0.1:1/micropython-{version}.tar.xz")
    result = build(tree, board=default_board(), progress=lambda _: None, image=False)
    assert result.native is None and "MPY_DIR" in result.native_note and "pure-Python fallback" in result.native_note
    fake_tree = tmp_path / "micropython"
    (fake_tree / "py").mkdir(parents=True)
    (fake_tree / "py" / "dynruntime.mk").write_text("")
    monkeypatch.setenv("MPY_DIR", str(fake_tree))
    monkeypatch.setenv("CROSS", str(tmp_path / "nowhere" / "xtensa-esp32-elf-"))
    result = build(tree, board=default_board(), progress=lambda _: None, image=False)
    assert result.native is None and "no cross compiler for xtensawin" in result.native_note


def test_build_finds_the_board_by_the_manifest_and_refuses_an_edited_one(tmp_path, monkeypatch):
    from codegen.board.loader import load_board
    from codegen.generate import generate

    board_file = tmp_path / "my-board.yaml"
    board_file.write_text("extends: ttgo-tbeam-v1.1\nname: my-board\nimu: {address: 0x69}\n")
    out = tmp_path / "out"
    generate(load_board(board_file), out)
    monkeypatch.chdir(tmp_path.parent)  # the board file sits beside OUT, not in the working folder
    result = build(out, progress=lambda _: None, image=False)
    assert result.tree.board.name == "my-board" and result.tree.board.imu.address == 0x69
    board_file.write_text(board_file.read_text() + "led: null\n")
    with pytest.raises(UserError, match="changed since"):
        build(out, progress=lambda _: None, image=False)


def test_a_failed_build_leaves_nothing_to_flash(tmp_path):
    """The record of the last good build goes when a new build starts: a build that stops half way (here at a
    syntax error) cannot be flashed or uploaded as if it were whole."""
    from codegen.deploy.buildrecord import check_build_current

    tree = make_tree(tmp_path / "out")
    build(tree, board=default_board(), progress=lambda _: None, image=False)
    check_build_current(tree)  # a good build is current
    (tree / "app" / "zz_broken.py").write_text("def f(:\n")
    with pytest.raises(UserError, match="mpy-cross failed on zz_broken.py"):
        build(tree, board=default_board(), progress=lambda _: None, image=False)
    (tree / "app" / "zz_broken.py").unlink()  # even with the sources as they were at the good build
    with pytest.raises(UserError, match="has no valid build record"):
        check_build_current(tree)
