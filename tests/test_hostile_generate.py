"""Hostile output folders: `deadreckon generate -o OUT` never touches a path outside OUT, and never a file in it that
deadreckon did not write.

A MANIFEST.json is deadreckon's only with its seal (the SHA-256 of the rest of it) and paths under app/ and
native/; folders and files on the way are never followed through a symbolic link; special files (FIFOs, devices)
are never opened. Each case: exit 2, a clear message, no traceback, within the bound, and everything outside OUT
(and, since the refusal comes first, inside it) unchanged, with and without --force.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from codegen import __version__
from codegen.generate import seal
from hostilekit import assert_refused, run_cli, snapshot, user_files

VICTIM = "victim.txt"  # a user's file beside the output folder: home/victim.txt, OUT is home/work/out
VICTIM_TEXT = "the user's own file\n"


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def sealed(files: dict) -> str:
    """A manifest with a valid seal, as a forger who read deadreckon's source would write it."""
    return json.dumps(seal({"generator": f"deadreckon {__version__}", "board": "ttgo-tbeam-v1.1", "files": files}))


def generated(out: Path, home: Path) -> None:
    assert run_cli("generate", "-o", str(out), cwd=home).returncode == 0


def write_manifest(text):
    """A setup writing OUT/MANIFEST.json: `text`, or `text(home)` for manifests naming absolute paths."""
    def setup(out: Path, home: Path) -> None:
        out.mkdir(parents=True)
        (out / "MANIFEST.json").write_text(text(home) if callable(text) else text)
    return setup


def user_app(out: Path, home: Path) -> None:
    """A user's own project that happens to have app/main.py, and a foreign {"files": {}} manifest."""
    (out / "app").mkdir(parents=True)
    (out / "app" / "main.py").write_text("print('the user's app')\n")
    (out / "MANIFEST.json").write_text('{"files": {}}')


def link_app_outside(out: Path, home: Path) -> None:
    generated(out, home)
    for path in sorted((out / "app").iterdir()):
        path.unlink()
    (out / "app").rmdir()
    (home / "elsewhere").mkdir()
    (home / "elsewhere" / "main.py").write_text("mine\n")
    (out / "app").symlink_to(home / "elsewhere")


def link_native_outside(out: Path, home: Path) -> None:
    generated(out, home)
    for path in sorted((out / "native").rglob("*"), reverse=True):
        path.rmdir() if path.is_dir() else path.unlink()
    (out / "native").rmdir()
    (out / "native").symlink_to(home)


def link_generated_file_outside(out: Path, home: Path) -> None:
    generated(out, home)
    (out / "app" / "main.py").unlink()
    (out / "app" / "main.py").symlink_to(home / VICTIM)


def link_manifest(out: Path, home: Path) -> None:
    generated(out, home)
    (home / "kept-manifest.json").write_text((out / "MANIFEST.json").read_text())
    (out / "MANIFEST.json").unlink()
    (out / "MANIFEST.json").symlink_to(home / "kept-manifest.json")


def manifest_is(kind: str):
    def setup(out: Path, home: Path) -> None:
        generated(out, home)
        manifest = out / "MANIFEST.json"
        manifest.unlink()
        if kind == "fifo":
            os.mkfifo(manifest)
        elif kind == "dev-zero":
            manifest.symlink_to("/dev/zero")
        elif kind == "huge":
            manifest.write_text(" " * (2 * 1024 * 1024) + "{}")
        elif kind == "deep":
            manifest.write_text("[" * 100_000 + "]" * 100_000)
        elif kind == "folder":
            manifest.mkdir()
    return setup


def generated_file_is_fifo(out: Path, home: Path) -> None:
    generated(out, home)
    (out / "app" / "main.py").unlink()
    os.mkfifo(out / "app" / "main.py")


def out_is_a_file(out: Path, home: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("not a folder\n")


def user_folder(out: Path, home: Path) -> None:
    out.mkdir(parents=True)
    (out / "thesis.tex").write_text("\\documentclass{article}\n")


def edited_then_sealed_with_traversal(out: Path, home: Path) -> None:
    """A real generated folder whose manifest was rewritten, seal and all, to list a file outside it."""
    generated(out, home)
    manifest = json.loads((out / "MANIFEST.json").read_text())
    manifest.pop("seal")
    manifest["files"]["app/../../../victim.txt"] = {"sha256": sha(VICTIM_TEXT)}
    (out / "MANIFEST.json").write_text(json.dumps(seal(manifest)))


# (id, setup(out, home), generate arguments beyond -o OUT, phrases)
CASES = [
    ("issue-dotdot-force", write_manifest('{"files": {"../../victim.txt": {}}}'), ["--force"],
     ["was not written by deadreckon", "--force does not override this"]),
    ("issue-dotdot-matching-hash",
     write_manifest(json.dumps({"files": {"../../victim.txt": {"sha256": sha(VICTIM_TEXT)}}})),
     [], ["was not written by deadreckon"]),
    ("absolute-path", write_manifest(lambda home: json.dumps({"files": {f"{home}/{VICTIM}": {}}})), ["--force"],
     ["was not written by deadreckon"]),
    ("foreign-empty-manifest-over-users-app", user_app, ["--force"], ["no generator field of deadreckon"]),
    ("forged-seal-dotdot", write_manifest(sealed({"../../victim.txt": {"sha256": sha(VICTIM_TEXT)}})), ["--force"],
     ["it names '../../victim.txt', outside app/ and native/"]),
    ("forged-seal-absolute", write_manifest(lambda home: sealed({f"{home}/{VICTIM}": {}})), ["--force"],
     ["outside app/ and native/"]),
    ("forged-seal-app-dotdot", edited_then_sealed_with_traversal, ["--force"], ["outside app/ and native/"]),
    ("forged-seal-other-folder", write_manifest(sealed({"build/app/main.py": {}})), ["--force"],
     ["it names 'build/app/main.py'"]),
    ("forged-seal-backslash", write_manifest(sealed({"app\\..\\..\\victim.txt": {}})), ["--force"],
     ["outside app/ and native/"]),
    ("stale-seal", write_manifest(json.dumps({"generator": "deadreckon 0.1.0", "files": {}, "seal": "sha256:00"})),
     ["--force"], ["its seal does not match its content"]),
    ("app-links-outside", link_app_outside, ["--force"], ["app is a symbolic link", "writes only inside"]),
    ("native-links-outside", link_native_outside, ["--force"], ["native is a symbolic link"]),
    ("generated-file-links-outside", link_generated_file_outside, ["--force"],
     ["app/main.py is not a regular file"]),
    ("generated-file-links-outside-no-force", link_generated_file_outside, [], ["were edited since: app/main.py"]),
    ("manifest-is-a-link", link_manifest, ["--force"], ["it is a symbolic link"]),
    ("manifest-is-a-fifo", manifest_is("fifo"), ["--force"], ["is a FIFO, not a regular file"]),
    ("manifest-links-dev-zero", manifest_is("dev-zero"), ["--force"], ["it is a symbolic link"]),
    ("manifest-2-MB", manifest_is("huge"), ["--force"], ["limit 1024 KB"]),
    ("manifest-nested-100000-deep", manifest_is("deep"), ["--force"], ["not JSON"]),
    ("manifest-is-a-folder", manifest_is("folder"), ["--force"], ["is a folder"]),
    ("generated-file-is-a-fifo", generated_file_is_fifo, ["--force"], ["app/main.py is not a regular file"]),
    ("out-is-a-file", out_is_a_file, ["--force"], ["exists and is not a folder"]),
    ("out-is-a-users-folder", user_folder, ["--force"], ["is not empty and was not generated by deadreckon"]),
]


@pytest.mark.parametrize("setup,extra,phrases", [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_hostile_output_folder_is_refused(tmp_path, setup, extra, phrases):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    (home / VICTIM).write_text(VICTIM_TEXT)
    out = home / "work" / "out"
    setup(out, home)
    before = snapshot(home)
    outcome = run_cli("generate", "-o", str(out), *extra, cwd=home)
    assert_refused(outcome, *phrases)
    assert snapshot(home) == before  # outside OUT and inside it: the refusal comes before any write
    assert (home / VICTIM).read_text() == VICTIM_TEXT


def test_an_output_folder_the_system_refuses(tmp_path):
    """A folder the file system will not create (here under /proc): the OS's reason, not a traceback."""
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    before = snapshot(home)
    assert_refused(run_cli("generate", "-o", "/proc/deadreckon-out", cwd=home), "/proc/deadreckon-out")
    assert snapshot(home) == before
