"""Golden generated trees: every bundled board's output, as reviewed text.

The default board's tree is stored as text, file by file: tests/golden/<default>/<path> holds each file rendered from
a template (app/*.py, native/dr_board.h, native/dr_layout.h, ...) exactly as `deadreckon generate` writes it. Every
other bundled board is stored as what it changes: tests/golden/<board>.diff, the unified diff from the default
board's rendered files to its own. So a template change shows in review once, as the lines that changed in the
default board's files, and in a board's diff only where it meets what that board does differently; a board change
shows in that board's diff alone. Files copied byte for byte from native_ext/ are listed (COPIED.txt in the default
tree, a pseudo-file in each diff) and checked against their source here, not stored: their diff is the source's own.
A CircuitPython board's tree (target: circuitpython) is laid out otherwise (code.py, boot.py, lib/, no native/): each
of its files is diffed against the default board's file of the same template (app/lib/app.py against app/app.py,
under the CircuitPython path), and its own files (code.py, boot.py, lib/hal.py, ...) show whole.

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
from codegen.paths import DEFAULT_BOARD, native_ext_dir

GOLDEN = Path(__file__).parent / "golden"
COPIED = "COPIED.txt"
UPDATE = os.environ.get("DEADRECKON_UPDATE_GOLDEN") == "1"
COPIED_PREFIX = "native_ext/"
OTHER_BOARDS = [name for name, _, _ in bundled_boards() if name != DEFAULT_BOARD]


def _split(tree) -> dict[str, bytes]:
    """The rendered files (path -> bytes), and COPIED.txt listing the copied ones (path <- source)."""
    rendered, copied = {}, []
    for path, f in sorted(tree.items()):
        if f.origin.startswith(COPIED_PREFIX):
            copied.append(f"{path} <- {f.origin}\n")
        else:
            rendered[path] = f.content
    rendered[COPIED] = "".join(copied).encode()
    return rendered


def _lines(content: bytes) -> list[str]:
    return content.decode(errors="replace").splitlines(keepends=True)


def _diff_text(before: str, after: str, old: dict[str, bytes], new: dict[str, bytes]) -> str:
    """The unified diff from tree `old` (named before) to tree `new` (named after), file by file, in path order."""
    out = []
    for path in sorted(set(old) | set(new)):
        a, b = old.get(path), new.get(path)
        if a == b:
            continue
        out += difflib.unified_diff(_lines(a or b""), _lines(b or b""),
                                    f"{before}/{path}" if a is not None else "/dev/null",
                                    f"{after}/{path}" if b is not None else "/dev/null", n=2)
    return "".join(line if line.endswith("\n") else line + "\n\\ No newline at end of file\n" for line in out)


def _report(name: str, want: str, got: str, limit: int = 80) -> str:
    lines = list(difflib.unified_diff(want.splitlines(), got.splitlines(), f"golden/{name}", f"generated/{name}",
                                      lineterm="", n=1))
    more = f"\n... {len(lines) - limit} more diff lines" if len(lines) > limit else ""
    return "\n".join(lines[:limit]) + more


@pytest.fixture(scope="module")
def default_tree() -> dict[str, bytes]:
    return _split(render_tree(load_board(DEFAULT_BOARD)))


def test_default_board_matches_its_golden_tree(default_tree):
    folder = GOLDEN / DEFAULT_BOARD
    if UPDATE:
        if folder.exists():
            shutil.rmtree(folder)
        for path, content in default_tree.items():
            (folder / path).parent.mkdir(parents=True, exist_ok=True)
            (folder / path).write_bytes(content)
    assert folder.is_dir(), f"no golden tree tests/golden/{DEFAULT_BOARD}/ (see this file's docstring to create it)"
    stored = {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    difference = _diff_text("golden", "generated", stored, default_tree)
    assert not difference, (f"generated files differ from tests/golden/{DEFAULT_BOARD}/ (regenerate as this file's "
                            "docstring says, then review the diff):\n" + difference[:6000])


def _same_templates(default_tree: dict[str, bytes], tree) -> dict[str, bytes]:
    """The default board's files under the paths `tree` (a CircuitPython board's) renders the same templates to."""
    return {path: default_tree[f.origin.replace("templates/micropython/", "app/")[: -len(".j2")]]
            for path, f in tree.items() if f.origin.startswith("templates/micropython/")}


@pytest.mark.parametrize("name", OTHER_BOARDS)
def test_board_differs_from_the_default_as_reviewed(name, default_tree):
    loaded = load_board(name)
    tree = render_tree(loaded)
    before = _same_templates(default_tree, tree) if loaded.board.target == "circuitpython" else default_tree
    got = _diff_text(DEFAULT_BOARD, name, before, _split(tree))
    golden = GOLDEN / f"{name}.diff"
    if UPDATE:
        golden.write_text(got)
    assert golden.is_file(), f"no tests/golden/{name}.diff (see this file's docstring to create it)"
    want = golden.read_text()
    assert want == got, (f"{name}'s files differ from the default board's otherwise than tests/golden/{name}.diff "
                         "says (regenerate as this file's docstring says, then review the diff):\n"
                         + _report(f"{name}.diff", want, got))


def test_golden_folder_holds_only_the_bundled_boards():
    expected = {DEFAULT_BOARD} | {f"{name}.diff" for name in OTHER_BOARDS}
    assert {p.name for p in GOLDEN.iterdir()} == expected


def test_copied_files_are_their_sources():
    """What the tree copies from native_ext/ is byte for byte the source (so the golden tree need not store it)."""
    tree = render_tree(load_board())
    copied = {path: f for path, f in tree.items() if f.origin.startswith(COPIED_PREFIX)}
    assert copied, "the tree copies nothing from native_ext/"
    for path, f in copied.items():
        source = native_ext_dir() / f.origin[len(COPIED_PREFIX):]
        assert f.content == source.read_bytes(), f"{path} is not a byte copy of {f.origin}"


def test_a_changed_line_shows_in_the_diff():
    """The comparison sees one changed byte, and names the file and line."""
    tree = {"app/x.py": b"a = 1\nb = 2\n"}
    changed = {"app/x.py": b"a = 1\nb = 3\n"}
    text = _diff_text("golden", "generated", tree, changed)
    assert "-b = 2\n+b = 3\n" in text and "golden/app/x.py" in text
    assert _diff_text("golden", "generated", tree, dict(tree)) == ""
