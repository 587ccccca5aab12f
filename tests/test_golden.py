"""Golden generated trees: every bundled board's output, file by file, as reviewed.

A change to a template, the kernel sources or a bundled board changes these hashes on purpose; regenerate them with
`DEADRECKON_UPDATE_GOLDEN=1 python -m pytest tests/test_golden.py` and review the diff of tests/golden/ with the change.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from codegen.board.loader import bundled_boards, load_board
from codegen.generate import render_tree

GOLDEN = Path(__file__).parent / "golden"
UPDATE = os.environ.get("DEADRECKON_UPDATE_GOLDEN") == "1"


@pytest.mark.parametrize("name", [name for name, _, _ in bundled_boards()])
def test_generated_tree_matches_golden(name):
    tree = render_tree(load_board(name))
    digest = {path: hashlib.sha256(f.content).hexdigest() for path, f in sorted(tree.items())}
    golden = GOLDEN / f"{name}.json"
    if UPDATE:
        golden.write_text(json.dumps(digest, indent=1, sort_keys=True) + "\n")
    expected = json.loads(golden.read_text())
    changed = sorted(p for p in set(digest) | set(expected) if digest.get(p) != expected.get(p))
    assert not changed, f"generated files differ from tests/golden/{name}.json: {changed} (see this file's docstring)"
