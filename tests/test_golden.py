"""Golden generated trees: every bundled board's output, as reviewed text.

tests/golden/<board>/<path> holds each file rendered from a template (app/*.py, native/dr_board.h, native/dr_layout.h,
...) exactly as `deadreckon generate` writes it, so a change in output shows in review as the lines that changed.
Files copied byte for byte from native_ext/ are listed in tests/golden/<board>/COPIED.txt (path <- source) and
checked against their source here, not stored: their diff is the source's own.

A change to a template, the declaration (codegen/kernel/layout.py) or a bundled board changes these files on purpose;
regenerate them with

    DEADRECKON_UPDATE_GOLDEN=1 python -m pytest tests/test_golden.py

and review `git diff tests/golden/` with the change.
"""

from __future__ import annotations

import difflib
import os
import shutil
from pathlib import Path

import pytest

from codegen.board.loader import bundled_boards, load_board
from codegen.generate import render_tree
from codegen.paths import native_ext_dir

GOLDEN = Path(__file__).parent / "golden"
COPIED = "COPIED.txt"
UPDATE = os.environ.get("DEADRECKON_UPDATE_GOLDEN") == "1"
COPIED_PREFIX = "native_ext/"


def _split(tree):
    """(rendered: path -> bytes, copied: path -> source path relative to the project)."""
    rendered, copied = {}, {}
    for path, f in sorted(tree.items()):
        if f.origin.startswith(COPIED_PREFIX):
            copied[path] = f.origin
        else:
            rendered[path] = f.content
    return rendered, copied


def _write(folder: Path, rendered: dict[str, bytes], copied: dict[str, str]) -> None:
    if folder.exists():
        shutil.rmtree(folder)
    for path, content in rendered.items():
        target = folder / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(content)
    (folder / COPIED).write_text("".join(f"{path} <- {source}\n" for path, source in copied.items()))


def _diff(path: str, want: bytes, got: bytes, limit: int = 60) -> str:
    lines = list(difflib.unified_diff(want.decode(errors="replace").splitlines(),
                                      got.decode(errors="replace").splitlines(),
                                      f"golden/{path}", f"generated/{path}", lineterm="", n=1))
    more = f"\n... {len(lines) - limit} more diff lines" if len(lines) > limit else ""
    return "\n".join(lines[:limit]) + more


@pytest.mark.parametrize("name", [name for name, _, _ in bundled_boards()])
def test_generated_tree_matches_golden(name):
    rendered, copied = _split(render_tree(load_board(name)))
    folder = GOLDEN / name
    if UPDATE:
        _write(folder, rendered, copied)
    assert folder.is_dir(), f"no golden tree tests/golden/{name}/ (see this file's docstring to create it)"
    stored = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()} - {COPIED}
    problems = []
    for path in sorted(stored - set(rendered)):
        problems.append(f"{path}: in tests/golden/{name}/ but no longer generated")
    for path in sorted(set(rendered) - stored):
        problems.append(f"{path}: generated but not in tests/golden/{name}/")
    for path in sorted(stored & set(rendered)):
        want = (folder / path).read_bytes()
        if want != rendered[path]:
            problems.append(_diff(path, want, rendered[path]))
    listed = (folder / COPIED).read_text().splitlines() if (folder / COPIED).exists() else []
    if listed != [f"{path} <- {source}" for path, source in copied.items()]:
        problems.append(f"the copied files changed: {COPIED} lists {listed}, the tree copies {sorted(copied)}")
    assert not problems, (f"generated files differ from tests/golden/{name}/ (regenerate as this file's docstring "
                          "says, then review the diff):\n" + "\n".join(problems))


def test_copied_files_are_their_sources():
    """What the tree copies from native_ext/ is byte for byte the source (so the golden tree need not store it)."""
    tree = render_tree(load_board())
    copied = {path: f for path, f in tree.items() if f.origin.startswith(COPIED_PREFIX)}
    assert copied, "the tree copies nothing from native_ext/"
    for path, f in copied.items():
        source = native_ext_dir() / f.origin[len(COPIED_PREFIX):]
        assert f.content == source.read_bytes(), f"{path} is not a byte copy of {f.origin}"
