"""Reading a board YAML into plain data while remembering where every key and value stood.

The result is plain dicts/lists/scalars plus a `SourceMap` from key paths (tuples of keys and list indexes) to
`Location`s, so any later stage (schema, rules, generator provenance) can point at file:line:col.
Every way a file can be unreadable (missing, too large, not UTF-8, tabs, duplicate keys, bad syntax, empty, not
a mapping) becomes a located `UserError`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.constructor import DuplicateKeyError
from ruamel.yaml.error import MarkedYAMLError, YAMLError

from codegen.errors import Location, UserError

MAX_BOARD_FILE_BYTES = 256 * 1024  # a board YAML is a few KB; anything this large is not one

KeyPath = tuple[Union[str, int], ...]


@dataclass
class SourceMap:
    """Locations of keys and values by key path, for one file or a merged `extends:` chain."""

    keys: dict[KeyPath, Location] = field(default_factory=dict)
    values: dict[KeyPath, Location] = field(default_factory=dict)

    def value(self, path: KeyPath) -> Location | None:
        """Where the value at `path` is written, or the nearest enclosing value that is."""
        for end in range(len(path), -1, -1):
            found = self.values.get(path[:end])
            if found:
                return found
        return None

    def key(self, path: KeyPath) -> Location | None:
        """Where the key of `path` is written; falls back to the value, then to the enclosing key."""
        for end in range(len(path), 0, -1):
            found = self.keys.get(path[:end]) or self.values.get(path[:end])
            if found:
                return found
        return self.values.get(())

    def update(self, other: "SourceMap") -> None:
        self.keys.update(other.keys)
        self.values.update(other.values)

    def drop_below(self, path: KeyPath) -> None:
        """Forget locations under `path` (its value was replaced whole by an overriding file)."""
        for table in (self.keys, self.values):
            for key in [k for k in table if len(k) > len(path) and k[: len(path)] == path]:
                del table[key]


@dataclass
class YamlDocument:
    path: Path
    data: dict[str, Any]
    source: SourceMap
    lines: list[str]


def _located(file: str, line0: int, col0: int) -> Location:
    return Location(file, line0 + 1, col0 + 1)


def _line_col_of_offset(raw: bytes, offset: int) -> tuple[int, int]:
    before = raw[:offset]
    line = before.count(b"\n")
    col = offset - (before.rfind(b"\n") + 1)
    return line, col


def read_yaml(path: Path, display_name: str | None = None) -> YamlDocument:
    """Parse one YAML file into plain data plus a source map; raise a located UserError when it can't."""
    name = display_name or str(path)
    start = Location(name, 1, 1)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise UserError(f"no such board file: {name}", hint="`deadreckon boards` lists the bundled boards") from None
    except IsADirectoryError:
        raise UserError(f"{name} is a folder, not a board YAML file") from None
    except OSError as error:
        raise UserError(f"cannot read {name}: {error.strerror}") from None

    if len(raw) > MAX_BOARD_FILE_BYTES:
        raise UserError(
            f"file is {len(raw) / 1e6:.1f} MB; a board YAML is a few KB (limit {MAX_BOARD_FILE_BYTES // 1024} KB)",
            location=start,
            hint="is this the right file?",
        )
    nul = raw.find(b"\x00")
    if nul >= 0:
        line, col = _line_col_of_offset(raw, nul)
        raise UserError("binary data (a NUL byte) in a board YAML", location=_located(name, line, col))
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        line, col = _line_col_of_offset(raw, error.start)
        raise UserError(
            f"not UTF-8 text (byte 0x{raw[error.start]:02X})",
            location=_located(name, line, col),
            hint="save the board file as UTF-8",
        ) from None
    lines = text.splitlines()

    for number, line_text in enumerate(lines):
        indent = len(line_text) - len(line_text.lstrip(" \t"))
        tab = line_text.find("\t", 0, indent)
        if tab >= 0:
            raise UserError(
                "tab character in indentation",
                location=_located(name, number, tab),
                hint="YAML indents with spaces only; replace the tab with spaces",
            )

    yaml = YAML(typ="rt")
    yaml.allow_duplicate_keys = False
    try:
        tree = yaml.load(text)
    except DuplicateKeyError as error:
        mark = error.problem_mark
        key = _duplicate_key_name(error)
        raise UserError(
            f"duplicate key {key!r}" if key else "duplicate key",
            location=_located(name, mark.line, mark.column),
            hint=f"the first {key!r} is on line {error.context_mark.line + 1}" if error.context_mark else None,
        ) from None
    except MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        location = _located(name, mark.line, mark.column) if mark else start
        problem = " ".join(str(part) for part in (error.context, error.problem) if part)
        raise UserError(f"YAML syntax: {problem or 'cannot parse'}", location=location) from None
    except (YAMLError, RecursionError, ValueError) as error:
        raise UserError(f"YAML syntax: {error}", location=start) from None

    if tree is None:
        raise UserError("empty board file", location=start, hint="start from `deadreckon config` of a bundled board")
    if not isinstance(tree, CommentedMap):
        raise UserError(
            f"a board file is a mapping of keys (name:, chip:, imu:, ...), not a {_kind(tree)}", location=start
        )
    source = SourceMap()
    source.values[()] = start
    data = _plain(tree, (), name, source)
    return YamlDocument(path=path, data=data, source=source, lines=lines)


def _duplicate_key_name(error: DuplicateKeyError) -> str | None:
    text = str(error.problem or "")
    if '"' in text:
        return text.split('"')[1]
    return None


def _kind(value: Any) -> str:
    if isinstance(value, (list, CommentedSeq)):
        return "list"
    if isinstance(value, str):
        return "string"
    return type(value).__name__


def _plain(node: Any, path: KeyPath, name: str, source: SourceMap) -> Any:
    """Turn ruamel's round-trip nodes into plain Python values, recording locations on the way."""
    if isinstance(node, CommentedMap):
        result: dict[Any, Any] = {}
        for key in node:
            child = path + (key,)
            try:
                key_line, key_col, value_line, value_col = node.lc.data[key]
            except (KeyError, TypeError, ValueError):
                key_line = value_line = None
            if key_line is not None:
                source.keys[child] = _located(name, key_line, key_col)
                source.values[child] = _located(name, value_line, value_col)
            result[key] = _plain(node[key], child, name, source)
        return result
    if isinstance(node, CommentedSeq):
        items = []
        for index, item in enumerate(node):
            child = path + (index,)
            try:
                line, col = node.lc.data[index]
                source.values[child] = _located(name, line, col)
            except (KeyError, TypeError, IndexError):
                pass
            items.append(_plain(item, child, name, source))
        return items
    if isinstance(node, bool) or node is None:
        return node
    if isinstance(node, int):
        return int(node)
    if isinstance(node, float):
        return float(node)
    if isinstance(node, str):
        return str(node)
    return node
