"""The guide and the docs site: built strictly, generated pages current, figures from the benchmarks' last output.

- docs/boards.md is what scripts/boards_doc.py makes of board_configs/*.yaml;
- `mkdocs build --strict` passes (a broken link or a page missing from the nav fails it);
- the quick start reads the same in the README and on the site's home page;
- every picture sits beside the command that makes it;
- every number inside a figure block (`<!-- figures: benchmarks/results/NAME.txt -->` ... `<!-- end figures -->`)
  appears in that results file, which `benchmarks/record.py` writes from the benchmark's own output, and the block
  names the benchmark's command: a figure that the last run no longer prints fails here;
- no issue numbers in the product's code, templates or docs (they mean nothing to a user).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from codegen.tools import find_tool
from conftest import ROOT, require

DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [ROOT / "README.md", *DOCS]
FIGURES = re.compile(r"<!-- figures: (?P<results>\S+) -->\n(?P<body>.*?)<!-- end figures -->", re.S)
NUMBER = re.compile(r"(?<![A-Za-z0-9_.])\d+(?:\.\d+)?")
QUICK_START = re.compile(r"<!-- quick start:[^>]*-->\n(?P<body>.*?)<!-- end quick start -->", re.S)
ISSUE_NUMBER = re.compile(r"(?<![\w-])issues?[ -]#?\d+", re.I)  # "issue 19", "issue-20"; not "single-issue 5-stage"
PRODUCT = ["codegen", "templates", "native_ext", "board_configs", "benchmarks", "scripts", "docs"]


def figure_blocks():
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for match in FIGURES.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            yield pytest.param(page, line, match["results"], match["body"], id=f"{page.name}:{line}")


def test_boards_page_is_what_the_board_files_say():
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "boards_doc.py"), "--check"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_the_docs_site_builds_strictly(tmp_path):
    mkdocs = find_tool("mkdocs")
    require(mkdocs is not None, "mkdocs is not installed (pip install -e '.[docs]')")
    done = subprocess.run([mkdocs, "build", "--strict", "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "site" / "boards" / "index.html").is_file()


def test_every_docs_page_is_in_the_site_nav():
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    missing = [page.name for page in DOCS if f": {page.name}" not in nav]
    assert not missing, f"docs pages the site's nav leaves out: {missing}"


def test_the_quick_start_is_the_same_in_the_readme_and_on_the_site():
    readme = QUICK_START.search((ROOT / "README.md").read_text(encoding="utf-8"))
    site = QUICK_START.search((ROOT / "docs" / "index.md").read_text(encoding="utf-8"))
    assert readme and site, "the quick start markers are missing"
    assert readme["body"].replace("](docs/", "](") == site["body"]


def test_every_picture_sits_beside_the_command_that_makes_it():
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
            image = (page.parent / target).resolve()
            assert image.is_file(), f"{page.name}: {target} does not exist"
            named = f"docs/img/{image.name}"
            assert re.search(rf"deadreckon \S.*{re.escape(named)}", text), \
                f"{page.name}: no command beside {target} says how it is made"


@pytest.mark.parametrize("page, line, results, body", list(figure_blocks()))
def test_figures_are_the_benchmarks_last_output(page, line, results, body):
    path = ROOT / results
    assert path.is_file(), f"{page.name}:{line}: {results} is missing (benchmarks/record.py writes it)"
    recorded = path.read_text(encoding="utf-8")
    command = re.search(r"^# command: python3 (?P<command>.+)$", recorded, re.M)
    assert command, f"{results} does not say which command printed it"
    assert command["command"] in body, f"{page.name}:{line}: the block does not show `{command['command']}`"
    printed = set(NUMBER.findall(recorded))
    shown = NUMBER.findall(body.replace(command["command"], ""))
    stale = sorted({n for n in shown if n not in printed}, key=float)
    assert shown, f"{page.name}:{line}: a figure block without figures"
    assert not stale, f"{page.name}:{line}: not in the last output of {results}: {stale}"


def test_the_figure_blocks_exist():
    """The QEMU table and the ESP32 estimate, which had gone stale once, are checked."""
    blocks = [(page.name, results) for page in PAGES for results in FIGURES.findall(page.read_text("utf-8"))]
    assert ("kernel.md", "benchmarks/results/device.txt") in [(name, r[0]) for name, r in blocks]


def test_no_issue_numbers_in_the_product():
    found = []
    for folder in PRODUCT:
        for path in sorted((ROOT / folder).rglob("*")):
            if not path.is_file() or path.suffix not in {".py", ".j2", ".md", ".c", ".h", ".yaml", ".txt", ".sh"}:
                continue
            for number, text in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
                if ISSUE_NUMBER.search(text):
                    found.append(f"{path.relative_to(ROOT)}:{number}: {text.strip()[:80]}")
    for path in (ROOT / "README.md", ROOT / "mkdocs.yml", ROOT / "pyproject.toml"):
        for number, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if ISSUE_NUMBER.search(text):
                found.append(f"{path.name}:{number}: {text.strip()[:80]}")
    assert not found, "issue numbers mean nothing to a user:\n" + "\n".join(found)
