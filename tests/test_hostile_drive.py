"""`upload OUT --drive PATH` against a hostile CIRCUITPY drive: a record on the drive is anyone's to write, so it
never decides alone what is deleted.

Each case runs the CLI with the user's files around the drive hashed before and after: the upload succeeds (the
app lands on the drive), and nothing but the app's own files and the two upload records changed; in particular no
user's file on the drive (settings.toml) or outside it (through a link on the drive) is deleted, whatever the
drive's record says, even sealed as deadreckon seals its own.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from codegen.deploy.buildrecord import UPLOAD_RECORD
from codegen.deploy.drive import RECORD, upload_record
from hostilekit import run_cli, snapshot, user_files

BOOT_OUT = "Adafruit CircuitPython 10.2.1 on 2025-11-04; Raspberry Pi Pico with rp2040\nBoard ID:raspberry_pi_pico\n"
SETTINGS = 'CIRCUITPY_WEB_API_PASSWORD = "mine"\n'


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A generated and built CircuitPython tree (through the CLI), copied afresh for each case."""
    root = tmp_path_factory.mktemp("drive")
    assert run_cli("generate", "pico-gy521-circuitpython", "-o", "out", cwd=root, timeout=120).returncode == 0
    done = run_cli("build", "out", cwd=root, timeout=300)
    assert done.returncode == 0, done.stderr
    return root / "out"


@pytest.fixture
def home(built, tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    shutil.copytree(built, home / "out", symlinks=True)
    drive = home / "CIRCUITPY"
    drive.mkdir()
    (drive / "boot_out.txt").write_text(BOOT_OUT)
    (drive / "settings.toml").write_text(SETTINGS)
    (home / "outside").mkdir()
    (home / "outside" / "thesis.tex").write_text("\\title{four years}\n")
    return home


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _forge_drive_record(home: Path, files: dict[str, str], sealed: bool) -> None:
    record = upload_record(files) if sealed else (
        '{"generator": "deadreckon upload", "files": {%s}}' % ", ".join(f'"{k}": "{v}"' for k, v in files.items())
    ).encode()
    (home / "CIRCUITPY" / RECORD).write_bytes(record)


def _upload_and_compare(home: Path) -> None:
    drive = home / "CIRCUITPY"
    app = home / "out" / "build" / "app"
    app_files = {p.relative_to(app).as_posix() for p in app.rglob("*") if p.is_file()}
    before = snapshot(home, skip=(home / "out",))
    done = run_cli("upload", "out", "--drive", "CIRCUITPY", cwd=home)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stdout + done.stderr and "removed " not in done.stdout, done.stdout
    after = snapshot(home, skip=(home / "out",))
    ours = {f"CIRCUITPY/{rel}" for rel in app_files} | {f"CIRCUITPY/{RECORD}", "CIRCUITPY/lib"}
    assert {k: v for k, v in before.items() if k not in ours} == {k: v for k, v in after.items() if k not in ours}
    for rel in app_files:
        assert _sha256(drive / rel) == _sha256(app / rel), rel


@pytest.mark.parametrize("sealed", [False, True], ids=["as the issue wrote it", "sealed as deadreckon seals"])
def test_a_record_on_the_drive_alone_deletes_nothing(home, sealed):
    """The issue's case: the drive's record names the user's settings.toml with its very hash."""
    _forge_drive_record(home, {"settings.toml": _sha256(home / "CIRCUITPY" / "settings.toml")}, sealed)
    _upload_and_compare(home)
    assert (home / "CIRCUITPY" / "settings.toml").read_text() == SETTINGS


def test_a_link_on_the_drive_never_leads_a_deletion_outside(home):
    """Both records name escape/thesis.tex with its hash (as if this tree had once uploaded it), and escape/ is a
    link out of the drive: the file outside stays."""
    (home / "CIRCUITPY" / "escape").symlink_to("../outside")
    files = {"escape/thesis.tex": _sha256(home / "outside" / "thesis.tex")}
    _forge_drive_record(home, files, sealed=True)
    (home / "out" / "build" / UPLOAD_RECORD).write_bytes(upload_record(files))
    _upload_and_compare(home)
    assert (home / "outside" / "thesis.tex").exists()


def test_a_users_file_with_a_recorded_hash_stays_unless_this_tree_uploaded_it(home):
    """A sealed drive record naming a user's file on the drive by path and hash, and a tree record of another
    upload: neither is this tree's word that it wrote that file, so it stays."""
    drive = home / "CIRCUITPY"
    (drive / "lib").mkdir()
    (drive / "lib" / "mine.py").write_text("mine = True\n")
    _forge_drive_record(home, {"lib/mine.py": _sha256(drive / "lib" / "mine.py")}, sealed=True)
    (home / "out" / "build" / UPLOAD_RECORD).write_bytes(upload_record({"lib/other.py": "0" * 64}))
    _upload_and_compare(home)
    assert (drive / "lib" / "mine.py").exists()
