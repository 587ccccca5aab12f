"""A user's install: the wheel, installed with its `[sim]` extra into a fresh virtualenv outside the checkout, runs
the README's commands from a folder that is not the checkout (no ../shared beside it, no PYTHONPATH).

The wheel must carry every file the package folders hold (templates, the C kernel, the boards, the emulated boards'
MicroPython and CircuitPython modules, the board clock's table): a file left out of package-data works in a checkout
and fails only after `pip install`. pip's own cache is used, so a second run installs in well under a minute.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

from conftest import ROOT, require_shared_data

# pyproject's package-dir: the source folder of each package that ships data files
PACKAGE_FOLDERS = {"codegen": "codegen", "templates": "codegen/templates", "native_ext": "codegen/native_ext",
                   "board_configs": "codegen/board_configs"}


def source_files() -> set[str]:
    """Every file in the package folders, named as the wheel names it (the checkout's own caches left out)."""
    names = set()
    for folder, package in PACKAGE_FOLDERS.items():
        for path in (ROOT / folder).rglob("*"):
            if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
                names.add(f"{package}/{path.relative_to(ROOT / folder).as_posix()}")
    return names


def build_wheel(into: Path) -> Path:
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(into), str(ROOT)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    (wheel,) = into.glob("deadreckon-*.whl")
    return wheel


def test_wheel_with_sim_extra_runs_the_readme_commands_outside_the_checkout(tmp_path):
    walk = require_shared_data("gnss-imu-walk")
    wheel = build_wheel(tmp_path / "wheels")
    missing = sorted(source_files() - set(zipfile.ZipFile(wheel).namelist()))
    assert not missing, f"in the package folders but not in the wheel (pyproject package-data): {missing}"

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True, timeout=120)
    python, deadreckon = venv / "bin" / "python", venv / "bin" / "deadreckon"
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "VIRTUAL_ENV", "MPY_DIR", "CROSS") and not k.startswith("PYTEST")}
    env["PATH"] = "/usr/bin:/bin"  # nothing of the checkout's virtualenv
    done = subprocess.run([str(python), "-m", "pip", "install", "-q", f"{wheel}[sim]"],
                          capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr[-3000:]

    # away from the checkout: a build finds no MicroPython tree beside it and (offline by design here) no download
    home = tmp_path / "user"
    home.mkdir()
    env["DEADRECKON_CACHE"] = str(tmp_path / "cache")
    env["DEADRECKON_MICROPYTHON_URL"] = (tmp_path / "no-mirror" / "micropython-{version}.tar.xz").as_uri()

    def run(*args: str, timeout: int = 180) -> subprocess.CompletedProcess:
        result = subprocess.run([str(deadreckon), *args], cwd=home, env=env, capture_output=True, text=True,
                                timeout=timeout)
        assert result.returncode == 0, f"deadreckon {' '.join(args)}:\n{result.stdout[-2000:]}{result.stderr[-3000:]}"
        assert "Traceback" not in result.stderr
        return result

    where = subprocess.run([str(python), "-c", "import codegen; print(codegen.__file__)"], cwd=home, env=env,
                           capture_output=True, text=True, timeout=60)
    assert where.stdout.startswith(str(venv)), "the test must run the installed copy, not the checkout"

    assert "ttgo-tbeam-v1.1" in run("boards").stdout
    run("validate", "ttgo-tbeam-v1.1")
    run("generate", "-o", "out")
    assert (home / "out" / "app" / "board_config.py").is_file()
    built = run("build", "out")
    assert (home / "out" / "build" / "fs.img").is_file()
    assert "pure-Python fallback" in built.stdout + built.stderr  # said plainly, not an error
    run("simulate", "--scenario", "static", "--outage", "20", "--plot", "static.png", "--method", "hold-last-fix")
    assert (home / "static.png").stat().st_size > 10_000
    # the emulated board: board_clock.json and mpsim/ from the wheel, `micropython` from the [sim] extra
    emulated = run("simulate", "--scenario", "walk", "--outage", "10", "--on-micropython")
    assert "app screen mode" in emulated.stdout, emulated.stdout[-2000:]
    replayed = run("simulate", "--scenario", "replay-walk", "--data", str(walk), "--outage", "10",
                   "--method", "fused")
    assert "replay-walk" in replayed.stdout
    refused = subprocess.run([str(deadreckon), "simulate", "--scenario", "replay-walk"], cwd=home, env=env,
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--data" in refused.stderr and "Traceback" not in refused.stderr
    run("post", str(walk), "-o", "walk")
    assert (home / "walk" / "trajectory.gpx").is_file()
