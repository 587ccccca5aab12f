"""Stale and foreign builds: `flash` and `upload` never send a build older than its generated sources, and `build`
never replaces a build/ folder it did not make.

OUT/build/BUILD.json records the SHA-256 of every source a build compiled (sealed like the manifest); a tree
regenerated, edited, grown or shrunk since is refused, naming the files, before any port is opened. The board
behind the port is the emulated ROM loader (its flash must stay blank) or a raw REPL peer that must never be
written to; each case: exit 2, a clear message, no traceback, within the bound, nothing changed.
"""

from __future__ import annotations

import json
import shutil

import pytest

from hostilekit import PORT_BOUND_S, assert_refused, run_cli, snapshot, user_files
from peers.bad_ports import BadPort
from peers.esp_rom import RomLoaderPeer
from peers.trees import merged_firmware


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """A generated and built default-board tree, copied afresh for each case."""
    home = tmp_path_factory.mktemp("stale") / "home"
    home.mkdir()
    user_files(home)
    assert run_cli("generate", "-o", "out", cwd=home, timeout=120).returncode == 0
    assert run_cli("build", "out", cwd=home, timeout=300).returncode == 0
    return home


def regenerate_with_other_pins(home):
    """The issue's case: generate, build, regenerate from a board with other pins, then flash without building."""
    (home / "mine.yaml").write_text("extends: ttgo-tbeam-v1.1\ni2c:\n  imu: {id: 1, sda: 13, scl: 14}\n"
                                    "imu: {bus: imu}\n")
    shutil.rmtree(home / "out")
    assert run_cli("generate", "-o", "out", cwd=home).returncode == 0  # a fresh generate of the old tree's board...
    assert run_cli("build", "out", cwd=home, timeout=300).returncode == 0
    assert run_cli("generate", "mine.yaml", "-o", "out", "--force", cwd=home).returncode == 0  # ...then other pins


def edit_source(home):
    path = home / "out" / "app" / "main.py"
    path.write_text(path.read_text() + "# my tweak\n")


def add_source(home):
    (home / "out" / "app" / "extra.py").write_text("X = 1\n")


def remove_source(home):
    (home / "out" / "app" / "buttons.py").unlink()


def remove_record(home):
    (home / "out" / "build" / "BUILD.json").unlink()


def tamper_record(home):
    path = home / "out" / "build" / "BUILD.json"
    record = json.loads(path.read_text())
    record["sources"]["app/main.py"] = "0" * 64  # claims another main.py was built, seal left as it was
    path.write_text(json.dumps(record))


def record_is_a_fifo(home):
    import os

    (home / "out" / "build" / "BUILD.json").unlink()
    os.mkfifo(home / "out" / "build" / "BUILD.json")


# (id, change to the built tree, phrases) -- refused by flash and by upload alike
STALE = [
    ("issue-regenerated-with-other-pins", regenerate_with_other_pins,
     ["is older than its generated sources", "app/board_config.py", "deadreckon build"]),
    ("source-edited-after-build", edit_source, ["changed after it: app/main.py"]),
    ("source-added-after-build", add_source, ["new since: app/extra.py"]),
    ("source-removed-after-build", remove_source, ["removed since: app/buttons.py"]),
    ("build-record-missing", remove_record, ["has no valid build record"]),
    ("build-record-tampered", tamper_record, ["has no valid build record"]),
    ("build-record-is-a-fifo", record_is_a_fifo, ["has no valid build record"]),
]


@pytest.mark.parametrize("change,phrases", [case[1:] for case in STALE], ids=[case[0] for case in STALE])
def test_stale_build_is_not_flashed(pristine, tmp_path, change, phrases):
    home = tmp_path / "home"
    shutil.copytree(pristine, home, symlinks=True)
    change(home)
    before = snapshot(home)
    with RomLoaderPeer() as peer:
        firmware = merged_firmware()
        peer.flash[0x1000 : 0x1000 + len(firmware)] = firmware
        on_board = bytes(peer.flash)
        assert_refused(run_cli("flash", "out", "--port", peer.url, cwd=home, timeout=PORT_BOUND_S), *phrases)
        assert bytes(peer.flash) == on_board and peer.stats.connections == 0  # not even connected
    assert snapshot(home) == before


@pytest.mark.parametrize("change,phrases", [case[1:] for case in STALE], ids=[case[0] for case in STALE])
def test_stale_build_is_not_uploaded(pristine, tmp_path, change, phrases):
    home = tmp_path / "home"
    shutil.copytree(pristine, home, symlinks=True)
    change(home)
    before = snapshot(home)
    with BadPort("liar") as port:  # would accept anything: the upload must not even connect
        assert_refused(run_cli("upload", "out", "--port", port.url, cwd=home, timeout=PORT_BOUND_S), *phrases)
        assert port.connections == 0
    assert snapshot(home) == before


def build_folder_links_outside(home):
    shutil.rmtree(home / "out" / "build")
    (home / "out" / "build").symlink_to(home / "projects")


def build_app_links_outside(home):
    shutil.rmtree(home / "out" / "build" / "app")
    (home / "out" / "build" / "app").symlink_to(home / "projects")


def build_folder_holds_user_files(home):
    (home / "out" / "build" / "my-measurements.csv").write_text("t,x\n0,1\n")


def image_links_outside(home):
    (home / "out" / "build" / "fs.img").unlink()
    (home / "out" / "build" / "fs.img").symlink_to(home / "notes.txt")


def foreign_manifest(home):
    (home / "out" / "MANIFEST.json").write_text('{"files": {}, "board_path": "../notes.txt"}')


BUILD_CASES = [
    ("build-folder-links-outside", build_folder_links_outside,
     ["is a symbolic link", "writes only into a real folder"]),
    ("build-app-links-outside", build_app_links_outside, ["build/app is a symbolic link", "did not make"]),
    ("build-folder-holds-user-files", build_folder_holds_user_files, ["holds my-measurements.csv"]),
    ("build-image-links-outside", image_links_outside, ["build/fs.img is a symbolic link"]),
    ("tree-with-foreign-manifest", foreign_manifest, ["was not written by deadreckon"]),
]


@pytest.mark.parametrize("change,phrases", [case[1:] for case in BUILD_CASES], ids=[case[0] for case in BUILD_CASES])
def test_build_replaces_only_its_own_folder(pristine, tmp_path, change, phrases):
    home = tmp_path / "home"
    shutil.copytree(pristine, home, symlinks=True)
    change(home)
    before = snapshot(home)
    assert_refused(run_cli("build", "out", cwd=home, timeout=120), *phrases)
    assert snapshot(home) == before
