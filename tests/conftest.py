"""Shared test helpers.

`require(condition, reason)`: a test that needs a tool skips locally with the reason, and fails under CI=true,
so a missing install step can never hide behind a skip.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"
IN_CI = os.environ.get("CI", "").lower() == "true"


def require(condition: bool, reason: str) -> None:
    if condition:
        return
    if IN_CI:
        pytest.fail(f"required under CI=true: {reason}")
    pytest.skip(reason)


def require_tool(name: str) -> str:
    path = shutil.which(name)
    require(path is not None, f"{name} is not installed (scripts/setup.sh installs it)")
    return path


def require_shared_data(*parts: str) -> Path:
    path = SHARED_DATA.joinpath(*parts)
    require(path.exists(), f"shared recording {path} is missing")
    return path
