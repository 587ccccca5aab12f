"""A non-editable install ships templates/, native_ext/ and board_configs/ and works away from the checkout."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile

from conftest import ROOT


def test_wheel_ships_data_and_generates(tmp_path):
    wheels = tmp_path / "wheels"
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(wheels), str(ROOT)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    (wheel,) = wheels.glob("deadreckon-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "codegen/board_configs/ttgo-tbeam-v1.1.yaml" in names
    assert "codegen/templates/micropython/board_config.py.j2" in names
    assert any(name.startswith("codegen/native_ext/") and name.endswith(".md") for name in names)

    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--target", str(target), str(wheel)],
        check=True, capture_output=True, timeout=300,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(target)
    result = subprocess.run(
        [sys.executable, "-c", "import codegen, sys; print(codegen.__file__); "
         "from codegen.cli import main; sys.exit(main(['generate', '-o', 'out']))"],
        cwd=elsewhere, env=env, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(str(target)), "the test must run the installed copy, not the checkout"
    assert (elsewhere / "out" / "app" / "board_config.py").is_file()
    assert (target / "bin" / "deadreckon").is_file()
