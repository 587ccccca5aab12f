"""From a board YAML path to a validated `Board`, in two phases (each part alone, then the whole board).

    load_board(path)         -> LoadedBoard, or raises a UserError listing every located error
    load_board_report(path)  -> BoardReport with all diagnostics (what `deadreckon validate` prints)

`extends: NAME` (a bundled board) or `extends: ./other.yaml` (relative to the file) starts from another board and
overrides its keys: mappings merge key by key, anything else is replaced whole, and `key: null` removes the
base's value (so the default applies).
"""

from __future__ import annotations

import difflib
import errno
import hashlib
import os
import re
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, TextIO

from pydantic import BaseModel, ValidationError

from codegen.board.circuitpython import BOARDS as CIRCUITPYTHON_BOARDS
from codegen.board.circuitpython import close_board_ids, find_board
from codegen.board.diagnostics import (
    Diagnostic,
    DiagnosticsError,
    error,
    print_all,
    sort_key,
)
from codegen.board.flashlayout import (
    AUTO_VFS_SINCE,
    ROM_BOOTLOADER_OFFSET,
    FlashLayout,
    read_partition_csv,
    version_tuple,
)
from codegen.board.model import CIRCUITPYTHON_PINS, Board, PinSpec
from codegen.board.yamlsource import KeyPath, SourceMap, YamlError, read_yaml
from codegen.errors import Location, UserError
from codegen.paths import board_configs_dir, default_board_path

MAX_EXTENDS_DEPTH = 8
MAX_BUNDLED_NAME = 64
BUNDLED_NAME = re.compile(rf"[A-Za-z0-9][A-Za-z0-9._-]{{0,{MAX_BUNDLED_NAME - 1}}}")
BOUND_KINDS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}


@dataclass
class LoadedBoard:
    """A validated board and everything needed to point back into its files."""

    board: Board
    source: SourceMap
    files: list[Path]  # the board file first, then each file it extends
    data: dict[str, Any]  # the merged YAML data, before defaults
    lines_by_file: dict[str, list[str]]
    warnings: list[Diagnostic] = field(default_factory=list)
    extra_files: list[Path] = field(default_factory=list)  # files the board names (its partition table CSV)

    @property
    def source_name(self) -> str:
        return display_name(self.files[0])

    @property
    def content_sha256(self) -> str:
        digest = hashlib.sha256()
        for path in [*self.files, *self.extra_files]:
            digest.update(path.read_bytes())
        return digest.hexdigest()


@dataclass
class BoardReport:
    source_name: str
    diagnostics: list[Diagnostic]
    lines_by_file: dict[str, list[str]]
    loaded: Optional[LoadedBoard] = None

    @property
    def board(self) -> Board:
        assert self.loaded is not None
        return self.loaded.board

    def failed(self, strict: bool = False) -> bool:
        bad = {"error", "warning"} if strict else {"error"}
        return self.loaded is None or any(d.severity in bad for d in self.diagnostics)

    def print(self, stream: TextIO = sys.stderr, strict: bool = False) -> None:
        shown = [
            Diagnostic("error", d.message, d.location, d.hint) if strict and d.severity == "warning" else d
            for d in self.diagnostics
        ]
        print_all(shown, self.lines_by_file, stream)


def display_name(path: Path) -> str:
    """How a file is named in messages: relative to the working folder when inside it."""
    try:
        return os.path.relpath(path) if not os.path.relpath(path).startswith("..") else str(path)
    except ValueError:
        return str(path)


def bundled_boards(target: Optional[str] = None) -> list[tuple[str, Path, str]]:
    """(name, path, description) of each board YAML shipped with deadreckon, default first; only those generated
    for `target` (micropython, circuitpython) when given."""
    boards = []
    for path in sorted(board_configs_dir().glob("*.yaml")):
        try:
            data = read_yaml(path).data
        except UserError:
            data = {"description": "(unreadable)"}
        if target is not None and data.get("target", "micropython") != target:
            continue
        boards.append((path.stem, path, str(data.get("description", ""))))
    boards.sort(key=lambda item: item[1] != default_board_path())
    return boards


def resolve_board_path(board: Optional[str | Path]) -> Path:
    """A path, a bundled board's name, or None for the default board."""
    if board is None:
        return default_board_path()
    path = Path(board)
    if path.exists() or path.suffix in (".yaml", ".yml") or os.sep in str(board):
        return path
    bundled = board_configs_dir() / f"{board}.yaml"
    if bundled.exists():
        return bundled
    names = [p.stem for p in board_configs_dir().glob("*.yaml")]
    close = difflib.get_close_matches(str(board), names, n=1)
    raise UserError(
        f"no board file or bundled board named {board!r}",
        hint=f"did you mean `{close[0]}`?" if close else "`deadreckon boards` lists the bundled boards",
    )


def _merge(base: Any, override: Any, path: KeyPath, source: SourceMap) -> Any:
    if isinstance(base, dict) and isinstance(override, dict):
        merged = dict(base)
        for key, value in override.items():
            if value is None and key in base:
                del merged[key]  # `key: null` in an extending file removes the base's value (back to default)
                source.drop_below(path + (key,))
            else:
                merged[key] = _merge(base[key], value, path + (key,), source) if key in base else value
        return merged
    source.drop_below(path)
    return override


def _real_path(path: Path, via: Optional[Location]) -> str:
    """The file a path names once links are followed; a loop of links is a located error, not a traceback."""
    try:
        return os.path.realpath(path, strict=True)
    except FileNotFoundError:
        return os.path.realpath(path)  # read_yaml says it is missing, with the place
    except OSError as problem:
        hint = {errno.ELOOP: "a link that points back at itself (directly or through others) names no file; "
                             "point it at the board YAML",
                errno.ENAMETOOLONG: "the file system takes names of at most 255 bytes; give the file a shorter "
                                    "name"}.get(problem.errno, "is the name right, and is the file readable?")
        raise UserError(f"{display_name(path)[:300]}: {problem.strerror}", location=via, hint=hint) from None


def _is_bundled(path: Path) -> bool:
    """A bundled board file: the project's own description of a PCB (a revision may extend another's)."""
    return path.resolve().parent == board_configs_dir().resolve()


def _read_chain(path: Path, lines_by_file: dict[str, list[str]]) -> tuple[dict, SourceMap, list[Path]]:
    chain: list[Path] = []
    documents = []
    current: Optional[Path] = path
    via: Optional[Location] = None
    while current is not None:
        resolved = _real_path(current, via)
        if resolved in [_real_path(p, via) for p in chain]:
            raise UserError("`extends:` forms a cycle", location=via, hint=" -> ".join(map(display_name, chain)))
        if len(chain) >= MAX_EXTENDS_DEPTH:
            raise UserError(f"`extends:` chain deeper than {MAX_EXTENDS_DEPTH} files", location=via)
        try:
            document = read_yaml(current, display_name(current))
        except YamlError as problem:
            if problem.lines:  # the message shows the offending line and a caret, as every other error does
                lines_by_file[display_name(current)] = problem.lines
            if via and problem.location is None:
                problem.location = via
            raise
        except UserError as problem:  # unreadable (a folder, a device, a name too long): say which extends: named it
            if via and problem.location is None:
                problem.location = via
            raise
        lines_by_file[display_name(current)] = document.lines
        chain.append(current)
        documents.append(document)
        parent = document.data.pop("extends", None)
        via = document.source.value(("extends",))
        if parent is not None and "wired" in document.data and not _is_bundled(current):
            raise UserError(
                f"`wired:` says what the PCB of the board this file extends ({parent}) solders to fixed pins; "
                "a file that extends it cannot change that",
                location=document.source.key(("wired",)),
                hint="leave `wired:` out; if your board really is wired differently, describe it in a file of its "
                     "own (copy the bundled board without `extends:`)",
            )
        if parent is None:
            current = None
        elif not isinstance(parent, str):
            raise UserError("`extends:` names a bundled board or a path to a board YAML", location=via)
        elif "\0" in parent:
            raise UserError("`extends:` contains a NUL character, which no file name can hold", location=via,
                            hint="write the bundled board's name or the path of a .yaml file")
        else:
            candidate = (current.parent / parent) if parent.endswith((".yaml", ".yml")) else None
            if candidate is None and not BUNDLED_NAME.fullmatch(parent):
                raise UserError(
                    f"`extends: {parent[:60]}{'...' if len(parent) > 60 else ''}` is neither a bundled board's name "
                    f"(letters, digits, '.', '_', '-', at most {MAX_BUNDLED_NAME} characters) nor a .yaml file",
                    location=via,
                    hint="`deadreckon boards` lists the bundled boards; a file of your own is named with its "
                         ".yaml ending, relative to this file (extends: ./base.yaml)",
                )
            if candidate is None:
                candidate = board_configs_dir() / f"{parent}.yaml"
                if not candidate.exists():
                    names = [p.stem for p in board_configs_dir().glob("*.yaml")]
                    close = difflib.get_close_matches(parent, names, n=1)
                    raise UserError(
                        f"`extends: {parent}`: no bundled board by that name",
                        location=via,
                        hint=f"did you mean `{close[0]}`?" if close else "`deadreckon boards` lists them",
                    )
            current = candidate

    data: dict[str, Any] = {}
    source = SourceMap()
    for document in reversed(documents):  # base first, then each override
        data = _merge(data, document.data, (), source)
        source.update(document.source)
    source.values[()] = documents[0].source.values[()]
    return data, source, chain


# --- phase 1: the schema ------------------------------------------------------------------------------------


def _field_model(model: type[BaseModel], path: KeyPath) -> Optional[type[BaseModel]]:
    """The schema part (model class) that `path` (relative to `model`) lands in, if it is a mapping part."""
    current: Any = model
    for key in path:
        if isinstance(current, type) and issubclass(current, BaseModel):
            info = current.model_fields.get(str(key))
            if info is None:
                return None
            current = info.annotation
        elif typing.get_origin(current) is dict:
            current = typing.get_args(current)[1]
        else:
            return None
        current = _unwrap(current)
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def _unwrap(annotation: Any) -> Any:
    """Optional[X] / Annotated[X, ...] / Union[int, X] -> the mapping part X where there is one."""
    while True:
        origin = typing.get_origin(annotation)
        if origin is typing.Annotated:
            annotation = typing.get_args(annotation)[0]
        elif origin is typing.Union or str(origin) == "types.UnionType":
            options = [a for a in typing.get_args(annotation) if a is not type(None)]
            models = [a for a in map(_unwrap, options) if isinstance(a, type) and issubclass(a, BaseModel)]
            annotation = models[0] if models else options[0]
        else:
            return annotation


def _dotted(path: KeyPath) -> str:
    text = ""
    for key in path:
        text += f"[{key}]" if isinstance(key, int) else (f".{key}" if text else str(key))
    return text or "(top level)"


def _schema_diagnostics(exc: ValidationError, data: dict, source: SourceMap) -> list[Diagnostic]:
    found: list[Diagnostic] = []
    seen: set[tuple] = set()
    for item in exc.errors(include_url=False):
        loc = tuple(part for part in item["loc"] if isinstance(part, (str, int)))
        path = _data_path(data, loc)
        kind = item["type"]
        last = loc[-1] if loc else None
        hint = None
        if kind == "extra_forbidden":
            parent_model = _field_model(Board, path[:-1]) or Board
            close = difflib.get_close_matches(str(last), list(parent_model.model_fields), n=1)
            hint = f"did you mean `{close[0]}`?" if close else (
                f"allowed here: {', '.join(parent_model.model_fields)}"
            )
            diagnostic = error(f"unknown key {last!r} in {_dotted(path[:-1])}", source.key(path), hint)
        elif kind == "missing":
            parent = path[:-1] if path and path[-1] == last else path
            diagnostic = error(f"{_dotted(parent)} is missing required key {last!r}", source.key(parent))
        else:
            message = item["msg"]
            if kind in ("model_type", "dict_type", "model_attributes_type"):
                message = "should be a mapping of keys"
                if _field_model(Board, path) is PinSpec:
                    diagnostic = _pin_type_diagnostic(path, item.get("input"), source)
                    if diagnostic.message not in {d.message for d in found}:
                        found.append(diagnostic)
                    continue
            elif message.startswith("Input should be "):
                message = "should be " + message[len("Input should be "):]
            elif message.startswith("Value error, "):
                message = message[len("Value error, "):]
            hint = (item.get("ctx") or {}).get("hint", hint)
            if hint is None and kind == "finite_number":
                hint = "YAML's .inf and .nan are not values a board can run with; write a finite number"
            if hint is None and kind in BOUND_KINDS:
                hint = "`deadreckon schema` states every key's range"
            got = item.get("input")
            shown = "" if isinstance(got, (dict, list)) or kind == "missing" else f" (got {got!r})"
            diagnostic = error(f"{_dotted(path)}: {message}{shown}", source.value(path), hint)
        signature = (diagnostic.message, diagnostic.location)
        if signature not in seen:
            seen.add(signature)
            found.append(diagnostic)
    return found


def _pin_type_diagnostic(path: KeyPath, got: Any, source: SourceMap) -> Diagnostic:
    """A pin written as something other than a GPIO number: say so in terms of pins, with the fix."""
    where = source.value(path)
    if isinstance(got, bool):
        return error(f"{_dotted(path)}: a pin is a GPIO number, not {str(got).lower()} (a boolean)", where,
                     "true and false are booleans in YAML; write the GPIO number, e.g. `pin: 21`")
    if isinstance(got, float):
        whole = got.is_integer()
        return error(f"{_dotted(path)}: a pin is a whole GPIO number, not {got!r}", where,
                     f"write `{int(got)}`" if whole else "GPIO numbers are whole numbers")
    if isinstance(got, str):
        digits = got.strip()
        hint = (f"write {digits} without quotes: quoted, YAML reads it as text" if digits.isdigit()
                else "write the GPIO number, e.g. 21; board names such as 'GP4' or 'IO21' are CircuitPython's "
                     "(`target: circuitpython` with `circuitpython: {board: ...}`)")
        return error(f"{_dotted(path)}: a pin is a GPIO number, not the string {got!r}", where, hint)
    if isinstance(got, list):
        return error(f"{_dotted(path)}: a pin is one GPIO number, not a list", where)
    return error(f"{_dotted(path)}: a pin is a GPIO number or {{pin: N, strapping_by_design: true}} (got {got!r})",
                 where)


def _data_path(data: Any, loc: tuple) -> KeyPath:
    """The longest prefix of pydantic's error location that exists in the data (drops validator tags)."""
    path: list = []
    current = data
    for part in loc:
        if isinstance(current, dict) and part in current:
            current = current[part]
            path.append(part)
        elif isinstance(current, list) and isinstance(part, int) and 0 <= part < len(current):
            current = current[part]
            path.append(part)
        elif isinstance(current, dict) and isinstance(part, str) and part[:1].isalpha():
            path.append(part)  # a missing or unknown key: name it, its location falls back to the parent
            break
        else:
            break
    return tuple(path)


def _own_partition_table(board: Board, source: SourceMap, chain: list[Path], lines_by_file: dict[str, list[str]]
                         ) -> tuple[Optional[FlashLayout], list[Path]]:
    """The partition table CSV the board names (relative to the file that names it), read into a layout."""
    table = board.micropython.partitions.table
    if table is None:
        return None, []
    where = source.value(("micropython", "partitions", "table"))
    named_in = next((p for p in chain if where and display_name(p) == where.file), chain[0])
    path = named_in.parent / table
    name = display_name(path)
    try:
        rows, lines = read_partition_csv(path, name, board.micropython.partitions.partition_table)
    except YamlError as problem:
        if problem.lines:
            lines_by_file[name] = problem.lines
        if problem.location is None:
            problem.location = where
            problem.message = f"micropython.partitions.table: {problem.message}"
        raise
    lines_by_file[name] = lines
    chip_rom = ROM_BOOTLOADER_OFFSET.get(board.chip)
    layout = FlashLayout(f"the partition table {name}", chip_rom, board.micropython.partitions.partition_table,
                         tuple(rows), auto_filesystem=version_tuple(board.micropython.version) >= AUTO_VFS_SINCE)
    return layout, [path]


def pin_context(data: dict, source: SourceMap) -> tuple[dict, list[Diagnostic]]:
    """The validation context pins are read in: for `target: circuitpython`, the board whose board.* names they
    use (None, with a located error, when circuitpython.board is missing or not a board deadreckon knows)."""
    if data.get("target") != "circuitpython":
        return {}, []
    section = data.get("circuitpython")
    board_id = section.get("board") if isinstance(section, dict) else None
    if not isinstance(board_id, str):
        if isinstance(section, dict) and "board" in section:
            return {CIRCUITPYTHON_PINS: None}, []  # a board id of the wrong kind: the schema says so
        known = ", ".join(CIRCUITPYTHON_BOARDS)
        return {CIRCUITPYTHON_PINS: None}, [error(
            "target: circuitpython needs circuitpython.board, the board's CircuitPython board_id",
            source.value(("circuitpython",)) if isinstance(section, dict) else source.value(("target",)),
            f"add `circuitpython: {{board: raspberry_pi_pico}}`; deadreckon knows {known}",
        )]
    board = find_board(board_id)
    if board is None:
        close = close_board_ids(board_id)
        return {CIRCUITPYTHON_PINS: None}, [error(
            f"circuitpython.board: deadreckon has no pin table for the CircuitPython board {board_id!r}",
            source.value(("circuitpython", "board")),
            f"did you mean `{close[0]}`?" if close else f"deadreckon knows {', '.join(CIRCUITPYTHON_BOARDS)}",
        )]
    return {CIRCUITPYTHON_PINS: board}, []


# --- both phases ----------------------------------------------------------------------------------------------


def load_board_report(board: Optional[str | Path] = None) -> BoardReport:
    """Read, merge and validate a board; every problem becomes a diagnostic (nothing raises but I/O-free bugs)."""
    lines_by_file: dict[str, list[str]] = {}
    path = resolve_board_path(board) if not isinstance(board, Path) else board
    name = display_name(path)
    try:
        data, source, chain = _read_chain(path, lines_by_file)
    except UserError as problem:
        return BoardReport(name, [error(problem.message, problem.location, problem.hint)], lines_by_file)

    context, board_problems = pin_context(data, source)
    try:
        model = Board.model_validate(data, context=context)
    except ValidationError as exc:
        diagnostics = sorted(board_problems + _schema_diagnostics(exc, data, source), key=sort_key)
        return BoardReport(name, diagnostics, lines_by_file)
    if board_problems:
        return BoardReport(name, board_problems, lines_by_file)

    from codegen.board.rules import check_board

    try:
        own_layout, table_files = _own_partition_table(model, source, chain, lines_by_file)
    except UserError as problem:
        return BoardReport(name, [error(problem.message, problem.location, problem.hint)], lines_by_file)
    diagnostics = sorted(check_board(model, source, own_layout), key=sort_key)
    loaded = LoadedBoard(model, source, chain, data, lines_by_file, extra_files=table_files)
    loaded.warnings = [d for d in diagnostics if d.severity == "warning"]
    return BoardReport(name, diagnostics, lines_by_file, loaded)


def load_board(board: Optional[str | Path] = None, strict: bool = False) -> LoadedBoard:
    """The validated board, or a UserError carrying every located diagnostic. Warnings print to stderr."""
    report = load_board_report(board)
    if report.failed(strict=strict):
        if strict:
            report.diagnostics = [
                Diagnostic("error", d.message, d.location, d.hint) if d.severity == "warning" else d
                for d in report.diagnostics
            ]
        raise DiagnosticsError(report.diagnostics, report.lines_by_file)
    assert report.loaded is not None
    if report.loaded.warnings:
        print_all(report.loaded.warnings, report.lines_by_file, sys.stderr)
    return report.loaded


def default_board() -> Board:
    """The default board's model (T-Beam v1.1), for library callers and tests."""
    return load_board(None).board
