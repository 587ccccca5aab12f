"""What a CircuitPython app imports, checked against what the board has: its own modules (the app's root and lib/)
and the modules built into the board's CircuitPython (codegen/board/circuitpython.py). An import that is neither
would stop the app at boot with ImportError on the board; `deadreckon build` refuses it, naming the module and the
file. Imports inside a `try` that catches ImportError are the app's optional ones (it carries on without them).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass, field
from pathlib import Path

from codegen.board.circuitpython import find_board
from codegen.board.model import Board
from codegen.errors import UserError


@dataclass
class Imports:
    builtin: set[str] = field(default_factory=set)  # modules the firmware has
    local: set[str] = field(default_factory=set)  # the app's own modules
    optional: set[str] = field(default_factory=set)  # imported where an ImportError is caught


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    names = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return handler.type is None or any(isinstance(n, ast.Name) and n.id in ("ImportError", "Exception")
                                       for n in names)


def imported_modules(source: str, filename: str) -> list[tuple[str, int, bool]]:
    """(top-level module, line, optional) of every import in a module's source."""
    tree = ast.parse(source, filename)
    optional_lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(_catches_import_error(h) for h in node.handlers):
            for inner in node.body:
                for sub in ast.walk(inner):
                    if hasattr(sub, "lineno"):
                        optional_lines.add(sub.lineno)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.append((alias.name.split(".")[0], node.lineno, node.lineno in optional_lines))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.module.split(".")[0], node.lineno, node.lineno in optional_lines))
    return found


def check_imports(app_dir: Path, board: Board) -> Imports:
    """Every import of every .py under APP_DIR resolved, or a UserError naming the first that cannot be."""
    cp = find_board(board.circuitpython.board)
    local = {p.stem for folder in (app_dir, app_dir / "lib") if folder.is_dir() for p in folder.glob("*.py")}
    local |= {p.name for p in (app_dir / "lib").glob("*") if (p / "__init__.py").is_file()}
    result = Imports()
    for path in sorted(app_dir.rglob("*.py")):
        rel = path.relative_to(app_dir).as_posix()
        for module, line, optional in imported_modules(path.read_text(encoding="utf-8"), rel):
            if module in local:
                result.local.add(module)
            elif module in cp.builtin_modules:
                result.builtin.add(module)
            elif optional:
                result.optional.add(module)
            else:
                raise UserError(
                    f"{rel}:{line} imports {module!r}, which is neither part of the app nor built into "
                    f"CircuitPython on the {cp.title}",
                    hint="the board would stop at boot with ImportError; put the library's .py into the app's lib/",
                )
    return result
