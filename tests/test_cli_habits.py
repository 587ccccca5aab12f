"""The CLI's habits: --version, build --require-native, shell completion, `boards` at 80 columns."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from codegen import __version__
from codegen.board.listing import board_table
from codegen.board.loader import bundled_boards
from codegen.cli import build_parser, main
from codegen.completion import bash_script
from conftest import require


def test_version(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out == f"deadreckon {__version__}\n"


@pytest.mark.parametrize("width", [80, 60])
def test_boards_fit_the_terminal(width):
    boards = [(name, description) for name, _, description in bundled_boards()]
    lines = board_table(boards, width)
    assert all(len(line) <= width for line in lines), [line for line in lines if len(line) > width]
    starts = [line for line in lines if not line.startswith(" ")]
    assert [line.split()[0] for line in starts] == [name for name, _ in boards]
    # every word of every description is there, in order
    assert " ".join(lines).split() == [w for name, d in boards for w in [name, *d.split()]]


def test_build_require_native_fails_without_a_compiler(tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    assert main(["generate", "-o", str(out)]) == 0
    monkeypatch.setenv("CROSS", str(tmp_path / "nowhere" / "xtensa-esp32-elf-"))  # no route to a native module
    assert main(["build", str(out)]) == 0  # the fallback is a build, said plainly
    assert "pure-Python fallback" in capsys.readouterr().out
    assert main(["build", str(out), "--require-native"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: --require-native: no native module was built: no cross compiler for xtensawin")
    assert "hint:" in err and "Traceback" not in err


def complete(words: list[str]) -> list[str]:
    """What bash offers after `words` (the last one being completed), with our script loaded."""
    require(shutil.which("bash") is not None, "bash is not installed")
    script = bash_script(build_parser())
    quoted = " ".join("'" + w + "'" for w in words)
    program = (f"{script}\nCOMP_WORDS=({quoted}); COMP_CWORD={len(words) - 1}; _deadreckon; "
               'printf "%s\\n" "${COMPREPLY[@]}"')
    done = subprocess.run(["bash", "--norc", "-c", program], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    return [line for line in done.stdout.splitlines() if line]


def test_bash_completion():
    assert complete(["deadreckon", "sim"]) == ["simulate"]
    assert complete(["deadreckon", "--ver"]) == ["--version"]
    assert complete(["deadreckon", "build", "out", "--req"]) == ["--require-native"]
    assert complete(["deadreckon", "simulate", "--scenario", "walk-"]) == ["walk-pocket", "walk-backpack", "walk-stand"]
    assert sorted(complete(["deadreckon", "pull", "--"])) == sorted(
        ["--port", "--output", "--folder", "--delete", "--post", "--help"])
    assert complete(["deadreckon", "completion", ""]) == ["bash"]


def test_completion_command(capsys):
    assert main(["completion", "bash"]) == 0
    assert "complete -o filenames -o bashdefault -F _deadreckon deadreckon" in capsys.readouterr().out
