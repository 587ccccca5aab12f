"""Where the data folders that ship with the package live.

In a source checkout (and an editable install) templates/, native_ext/ and board_configs/ sit beside codegen/;
an installed wheel carries them inside the package (pyproject maps them to codegen.templates etc.).
"""

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def resource_dir(name: str) -> Path:
    """Return the folder `name` (templates, native_ext, board_configs) of this installation."""
    for candidate in (_PACKAGE / name, _PACKAGE.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"deadreckon installation is missing its {name}/ folder (looked beside {_PACKAGE})")


def templates_dir() -> Path:
    return resource_dir("templates")


def native_ext_dir() -> Path:
    return resource_dir("native_ext")


def board_configs_dir() -> Path:
    return resource_dir("board_configs")


DEFAULT_BOARD = "ttgo-tbeam-v1.1"


def default_board_path() -> Path:
    return board_configs_dir() / f"{DEFAULT_BOARD}.yaml"
