"""A full disk under `generate` and `post`: the error names the file that could not be written (not a bare "No
space left on device"), exit 2, no traceback; what was there before is as it was; and once there is room, the same
`generate` finishes the folder the full disk interrupted.

The disk is a real one: a small tmpfs mounted in a private mount namespace (`unshare -rm`, no root needed where
user namespaces are allowed), gone when the command ends. Where it cannot be made the test skips, and fails under
CI=true.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from hostilekit import QUICK_BOUND_S, ROOT, snapshot, user_files
from inputkit import device_log


def _on_small_disk(home, script: str, timeout: float = 3 * QUICK_BOUND_S) -> subprocess.CompletedProcess:
    """Run `script` (sh) in `home` with a fresh tmpfs mounted at home/disk, in a private mount namespace;
    $DR is the CLI."""
    (home / "disk").mkdir(exist_ok=True)
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {home / 'disk'}"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        if os.environ.get("CI") == "true":
            pytest.fail(f"cannot mount a tmpfs in a user namespace: {probe.stderr.strip()}")
        pytest.skip(f"cannot mount a tmpfs in a user namespace here: {probe.stderr.strip()}")
    env = dict(os.environ, PYTHONPATH=str(ROOT), DR=f"{sys.executable} -m codegen")
    return subprocess.run(["unshare", "-rm", "sh", "-c", script], cwd=home, env=env, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def _status(done: subprocess.CompletedProcess, marker: str) -> int:
    for line in done.stdout.splitlines():
        if line.startswith(marker + "="):
            return int(line.split("=", 1)[1])
    raise AssertionError(f"no {marker} in\n{done.stdout}\n{done.stderr}")


def test_generate_on_a_full_disk_names_the_file_and_finishes_once_there_is_room(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    before = snapshot(home)
    done = _on_small_disk(home, """
        mount -t tmpfs -o size=96k tmpfs disk
        $DR generate -o disk/out; echo full=$?
        mount -o remount,size=8m disk
        $DR generate -o disk/out; echo room=$?
        $DR generate -o disk/out; echo again=$?
        test -f disk/out/MANIFEST.json && ! grep -q '"unfinished"' disk/out/MANIFEST.json; echo finished=$?
        ls -a disk/out/app | grep -c '\\.tmp$'; true
    """)
    assert _status(done, "full") == 2, done.stderr
    assert "No space left on device" in done.stderr and "error: writing disk/out/" in done.stderr, done.stderr
    assert "hint: free some space on the disk holding disk/out" in done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    assert _status(done, "room") == 0 and _status(done, "again") == 0, done.stderr
    assert _status(done, "finished") == 0 and done.stdout.strip().endswith("0"), done.stdout
    assert {k: v for k, v in snapshot(home).items() if not k.startswith("disk")} == \
        {k: v for k, v in before.items() if not k.startswith("disk")}


def test_post_on_a_full_disk_names_the_file(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    (home / "dr00001.bin").write_bytes(device_log())
    before = snapshot(home)
    done = _on_small_disk(home, """
        mount -t tmpfs -o size=12k tmpfs disk
        $DR post dr00001.bin -o disk/post-out --no-plots; echo full=$?
    """, timeout=180)
    assert _status(done, "full") == 2, done.stderr
    assert "No space left on device" in done.stderr and "error: writing disk/post-out/" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    assert {k: v for k, v in snapshot(home).items() if not k.startswith("disk")} == \
        {k: v for k, v in before.items() if not k.startswith("disk")}
