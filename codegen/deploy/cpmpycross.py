"""CircuitPython's own mpy-cross for the release a CircuitPython board declares (its .mpy start with b'C').

MicroPython's mpy-cross will not do: CircuitPython refuses its .mpy ("MicroPython .mpy file; use CircuitPython
mpy-cross"), and no package registry carries CircuitPython's. In order:

    DEADRECKON_CP_MPY_CROSS   a CircuitPython mpy-cross the user gives (a path); its --version must name the
                              board's release
    CIRCUITPY_DIR             a CircuitPython source tree of the board's release: its mpy-cross is built once per
                              content into the cache (codegen/portbuild.py), as the tests build the shared tree's
    ../shared/circuitpython   the tree beside a source checkout, when its SOURCE.txt names the board's release

None found: the build ships .py (CircuitPython compiles them as it imports them, in the heap the app needs) and says
how to get the compiler.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path
from typing import Callable, Optional

from codegen import portbuild, tools
from codegen.errors import UserError

PATH_ENV = "DEADRECKON_CP_MPY_CROSS"
TREE_ENV = "CIRCUITPY_DIR"
MPY_MAGIC = b"C"  # CircuitPython's .mpy header; MicroPython's is b"M"

Progress = Callable[[str], None]


def _reported_release(mpy_cross: str) -> Optional[str]:
    try:
        done = subprocess.run([mpy_cross, "--version"], capture_output=True, text=True, timeout=30)
    except OSError:
        return None
    found = re.match(r"CircuitPython (\S+) ", done.stdout)
    return found.group(1) if found else None


def shared_tree_release(tree: Path) -> Optional[str]:
    """The release the shared tree's SOURCE.txt names ("CircuitPython 10.2.1 (github.com/..."), or None."""
    try:
        first = (tree / "SOURCE.txt").read_text().split("\n", 1)[0]
    except OSError:
        return None
    found = re.match(r"CircuitPython (\d+\.\d+\.\d+) ", first)
    return found.group(1) if found else None


def find(version: str, progress: Progress = print) -> tuple[Optional[str], str]:
    """(CircuitPython mpy-cross for `version`, where it came from), or (None, why not and how to get one)."""
    given = os.environ.get(PATH_ENV)
    if given:
        release = _reported_release(given)
        if release is None:
            raise UserError(f"{PATH_ENV}={given} is not CircuitPython's mpy-cross (its --version does not say "
                            "CircuitPython)", hint="build it from CircuitPython's source: make -C mpy-cross")
        if release != version:
            raise UserError(f"{PATH_ENV}={given} is CircuitPython {release}'s mpy-cross; the board declares "
                            f"{version}", hint=f"give the mpy-cross of CircuitPython {version}, or declare "
                                               f"circuitpython.version: {release}")
        return given, f"{PATH_ENV} ({given})"
    tree_given = os.environ.get(TREE_ENV)
    if tree_given:
        tree, where = Path(tree_given), f"{TREE_ENV} ({tree_given})"
    elif shared_tree_release(tools.SHARED_CIRCUITPYTHON) == version:
        tree, where = tools.SHARED_CIRCUITPYTHON, f"{tools.SHARED_CIRCUITPYTHON} ({version})"
    else:
        return None, (f"no CircuitPython {version} mpy-cross: set {PATH_ENV} to one, or {TREE_ENV} to the "
                      f"CircuitPython {version} source tree to build it from")
    built = portbuild.build(portbuild.CIRCUITPYTHON_MPY_CROSS, tree, version=version, log=progress)
    return str(built), f"built from {where}"


def compile_module(mpy_cross: str, source: Path, target: Path, rel: str) -> None:
    """One .py to CircuitPython .mpy; a UserError with the compiler's message when it does not compile."""
    target.parent.mkdir(parents=True, exist_ok=True)
    done = subprocess.run([mpy_cross, "-o", str(target), "-s", rel, str(source)], capture_output=True, text=True)
    if done.returncode != 0 or not target.is_file():
        message = (done.stderr or done.stdout).strip() or f"exit status {done.returncode}"
        raise UserError(f"{rel} does not compile: {message}", hint="this is a bug in deadreckon's templates")
    with open(target, "rb") as f:
        if f.read(1) != MPY_MAGIC:
            raise UserError(f"{mpy_cross} wrote {target.name} that is not a CircuitPython .mpy",
                            hint=f"{PATH_ENV} must be CircuitPython's mpy-cross, not MicroPython's")
