"""`deadreckon upload OUT --drive PATH`: the CircuitPython app onto a CIRCUITPY drive (a folder here), one file at a
time, whole or not at all; failures injected where the drive can fail (a write, an fsync, a rename, the drive gone,
full, read-only)."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from codegen.deploy import drive as drive_module
from codegen.deploy.build import build
from codegen.deploy.drive import PART_SUFFIX, RECORD, upload_drive
from codegen.errors import UserError
from codegen.sim.harness import generate_app

BOOT_OUT = "Adafruit CircuitPython 10.2.1 on 2025-11-04; Raspberry Pi Pico with rp2040\nBoard ID:{board}\nUID:E6603\n"


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A generated and built CircuitPython tree, and a second build of the same board with a changed app."""
    root = tmp_path_factory.mktemp("cp")
    trees = {}
    for name, extra in (("first", ""), ("second", "display: {refresh_ms: 250}\n")):
        yaml = root / f"{name}.yaml"
        yaml.write_text(f"extends: pico-gy521-circuitpython\nname: pico-cp-{name}\n{extra}")
        out = generate_app(yaml, root / name)
        build(out, progress=lambda line: None)
        trees[name] = out
    return trees


def _drive(tmp_path: Path, board: str = "raspberry_pi_pico") -> Path:
    drive = tmp_path / "CIRCUITPY"
    drive.mkdir()
    (drive / "boot_out.txt").write_text(BOOT_OUT.format(board=board))
    (drive / "settings.toml").write_text('CIRCUITPY_WEB_API_PASSWORD = "mine"\n')
    return drive


def _snapshot(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _app_files(out: Path) -> dict[str, str]:
    return _snapshot(out / "build" / "app")


def _quiet(line: str) -> None:
    pass


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "codegen", *args], capture_output=True, text=True, timeout=60)


def test_upload_writes_the_app_and_then_only_what_changed(built, tmp_path):
    drive = _drive(tmp_path)
    first = upload_drive(built["first"], drive, progress=_quiet)
    on_drive = _snapshot(drive)
    for rel, digest in _app_files(built["first"]).items():
        assert on_drive[rel] == digest, rel
    assert first.sent[-2:] == ["boot.py", "code.py"]  # code.py last: the firmware restarts it on every change
    assert first.board_id == "raspberry_pi_pico" and first.version == "10.2.1"
    assert (drive / RECORD).is_file() and (drive / "settings.toml").read_text().startswith("CIRCUITPY_WEB")
    again = upload_drive(built["first"], drive, progress=_quiet)
    assert again.sent == [] and len(again.unchanged) == len(first.sent)
    changed = upload_drive(built["second"], drive, progress=_quiet)
    config = next(rel for rel in _app_files(built["second"]) if rel.startswith("lib/board_config."))  # .mpy or .py
    assert set(changed.sent) == {"boot.py", "code.py", config} | {
        rel for rel in _app_files(built["second"]) if rel.startswith("lib/") and rel != config
        and _app_files(built["second"])[rel] != _app_files(built["first"])[rel]}
    assert {rel: d for rel, d in _snapshot(drive).items() if rel in _app_files(built["second"])} == \
        _app_files(built["second"])


def _tree_with_extra_modules(built, name: str) -> Path:
    """A copy of the first build (beside the board file its manifest names) whose built app also has two modules an
    older deadreckon wrote, as a tree that once uploaded them and then no longer does."""
    out = built["first"].parent / name
    shutil.copytree(built["first"], out, symlinks=True)
    for module in ("old_module.py", "edited_module.py"):
        (out / "build" / "app" / "lib" / module).write_text(f"# {module}\n")
    return out


def test_files_deadreckon_no_longer_writes_go_the_users_stay(built, tmp_path):
    out = _tree_with_extra_modules(built, "older")
    drive = _drive(tmp_path)
    upload_drive(out, drive, progress=_quiet)
    assert (drive / "lib" / "old_module.py").is_file()
    (drive / "lib" / "edited_module.py").write_text("x = 2  # the user's edit\n")
    (drive / "lib" / "mine.py").write_text("mine = True\n")
    for module in ("old_module.py", "edited_module.py"):
        (out / "build" / "app" / "lib" / module).unlink()
    result = upload_drive(out, drive, progress=_quiet)
    assert result.removed == ["lib/old_module.py"]
    assert (drive / "lib" / "mine.py").exists() and (drive / "lib" / "edited_module.py").exists()
    assert (drive / "settings.toml").exists()


@pytest.mark.parametrize("case, message", [
    ("no boot_out", "has no boot_out.txt: it is not a CircuitPython board's CIRCUITPY drive"),
    ("other board", "is a espressif_esp32s3_devkitc_1_n8r8 (its boot_out.txt), the app is for a raspberry_pi_pico"),
    ("old firmware", "the board runs CircuitPython 8.2.9; the app needs 9.0 or newer"),
    ("not a folder", "is not a folder"),
    ("missing", "no such folder"),
])
def test_refused_before_anything_is_written(built, tmp_path, case, message):
    drive = _drive(tmp_path)
    if case == "no boot_out":
        (drive / "boot_out.txt").unlink()
    elif case == "other board":
        (drive / "boot_out.txt").write_text(BOOT_OUT.format(board="espressif_esp32s3_devkitc_1_n8r8"))
    elif case == "old firmware":
        (drive / "boot_out.txt").write_text(BOOT_OUT.replace("10.2.1", "8.2.9").format(board="raspberry_pi_pico"))
    before = _snapshot(tmp_path)
    target = drive
    if case == "not a folder":
        target = drive / "settings.toml"
    elif case == "missing":
        target = tmp_path / "nowhere"
    done = _cli("upload", str(built["first"]), "--drive", str(target))
    assert done.returncode == 2, done.stderr
    assert message in done.stderr and "Traceback" not in done.stderr
    assert _snapshot(tmp_path) == before


def test_a_micropython_tree_has_no_drive(tmp_path):
    out = generate_app("pico-gy521", tmp_path / "mp")
    drive = _drive(tmp_path)
    with pytest.raises(UserError, match="MicroPython boards have no CIRCUITPY drive"):
        upload_drive(out, drive, progress=_quiet)


def test_a_full_drive_is_refused_up_front(built, tmp_path, monkeypatch):
    drive = _drive(tmp_path)
    before = _snapshot(drive)
    monkeypatch.setattr(drive_module.shutil, "disk_usage",
                        lambda path: shutil._ntuple_diskusage(1 << 20, 1 << 20, 1000))
    with pytest.raises(UserError, match=r"the app needs \d+ more bytes .* it has 1000 free; nothing was written"):
        upload_drive(built["first"], drive, progress=_quiet)
    assert _snapshot(drive) == before


class Failing:
    """Wraps an os function: its n-th call (from 1) that concerns `drive` raises OSError(err). A call concerns the
    drive when its path argument lies on it, or, for calls on descriptors (write, fsync), always (the upload is the
    only writer then)."""

    def __init__(self, real, n, err, drive):
        self.real, self.n, self.err, self.drive, self.calls = real, n, err, str(drive), 0

    def __call__(self, *args, **kwargs):
        first = args[0] if args else None
        if not isinstance(first, int) and not str(first).startswith(self.drive):
            return self.real(*args, **kwargs)
        self.calls += 1
        if self.calls == self.n:
            raise OSError(self.err, os.strerror(self.err))
        return self.real(*args, **kwargs)


def _half_write(real):
    """os.write that writes half of what it is given, then fails with EIO: a drive that stops mid-file."""
    state = {"calls": 0}

    def write(descriptor, data):
        state["calls"] += 1
        if state["calls"] == 2:  # the second file sent (a built app's .mpy carry no banner: few files change)
            real(descriptor, bytes(data[: len(data) // 2]))
            raise OSError(errno.EIO, "Input/output error")
        return real(descriptor, data)

    return write


@pytest.mark.parametrize("where, n", [("write", 2), ("fsync", 3), ("replace", 2), ("half write", 0)])
def test_a_failure_mid_upload_leaves_every_file_whole(built, tmp_path, monkeypatch, where, n):
    """(fsync: the 3rd, the second file's own; the 2nd is the folder's, whose failure some FAT drivers report and the
    upload passes over.)"""
    drive = _drive(tmp_path)
    upload_drive(built["first"], drive, progress=_quiet)
    old, new = _app_files(built["first"]), _app_files(built["second"])
    if where == "half write":
        monkeypatch.setattr(drive_module.os, "write", _half_write(os.write))
    else:
        monkeypatch.setattr(drive_module.os, where, Failing(getattr(os, where), n, errno.EIO, drive))
    with pytest.raises(UserError) as failed:
        upload_drive(built["second"], drive, progress=_quiet)
    assert "is as it was (each file is renamed into place whole)" in failed.value.message
    monkeypatch.undo()
    now = _snapshot(drive)
    for rel in new:
        assert now[rel] in (old[rel], new[rel]), f"{rel} is neither the old nor the new file"
    assert not list(drive.rglob(f"*{PART_SUFFIX}")), "a partial file was left on the drive"
    upload_drive(built["second"], drive, progress=_quiet)  # plugged in again: the same command finishes the job
    assert {rel: d for rel, d in _snapshot(drive).items() if rel in new} == new


def test_a_drive_pulled_out_mid_file_and_plugged_in_again(built, tmp_path, monkeypatch):
    """The drive goes away during a write (its temporary file cannot even be removed): the target is untouched, the
    next upload clears the leftover and completes."""
    drive = _drive(tmp_path)
    upload_drive(built["first"], drive, progress=_quiet)
    old, new = _app_files(built["first"]), _app_files(built["second"])
    monkeypatch.setattr(drive_module.os, "fsync", Failing(os.fsync, 3, errno.ENODEV, drive))
    monkeypatch.setattr(drive_module.os, "unlink", Failing(os.unlink, 1, errno.ENODEV, drive))
    with pytest.raises(UserError, match="the drive may have gone away"):
        upload_drive(built["second"], drive, progress=_quiet)
    monkeypatch.undo()
    leftovers = list(drive.rglob(f"*{PART_SUFFIX}"))
    assert len(leftovers) == 1
    now = _snapshot(drive)
    assert all(now[rel] in (old[rel], new[rel]) for rel in new)
    upload_drive(built["second"], drive, progress=_quiet)
    assert not list(drive.rglob(f"*{PART_SUFFIX}"))
    assert {rel: d for rel, d in _snapshot(drive).items() if rel in new} == new


def test_a_read_only_drive_says_how_to_get_it_back(built, tmp_path, monkeypatch):
    drive = _drive(tmp_path)
    before = _snapshot(drive)
    real_open = os.open

    def read_only(path, flags, *args):  # a read-only mount: reads work, opening for writing fails
        if str(path).startswith(str(drive)) and flags & (os.O_WRONLY | os.O_RDWR):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real_open(path, flags, *args)

    monkeypatch.setattr(drive_module.os, "open", read_only)
    with pytest.raises(UserError) as failed:
        upload_drive(built["first"], drive, progress=_quiet)
    assert "is read-only" in failed.value.message and "nothing was changed" in failed.value.message
    assert "hold the button its boot.py names while the board starts" in failed.value.hint
    monkeypatch.undo()
    assert _snapshot(drive) == before


def test_links_on_the_drive_are_not_written_through(built, tmp_path):
    drive = _drive(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (drive / "lib").symlink_to(elsewhere)
    with pytest.raises(UserError, match="is a link where the app puts a folder"):
        upload_drive(built["first"], drive, progress=_quiet)
    assert not any(elsewhere.iterdir())


def test_a_stale_build_is_refused(built, tmp_path):
    out = built["first"].parent / "stale"  # beside the board file its manifest names
    shutil.copytree(built["first"], out)
    (out / "app" / "lib" / "nmea.py").write_text("# edited after the build\n")
    drive = _drive(tmp_path)
    with pytest.raises(UserError, match="older than its generated sources"):
        upload_drive(out, drive, progress=_quiet)
