"""Reading a board YAML into plain data while remembering where every key and value stood.

The result is plain dicts/lists/scalars plus a `SourceMap` from key paths (tuples of keys and list indexes) to
`Location`s, so any later stage (schema, rules, generator provenance) can point at file:line:col.
Every way a file can be unreadable (missing, not a regular file, too large, not UTF-8, tabs, duplicate keys, bad
syntax, an alias bomb, nesting too deep, a foreign tag, empty, not a mapping) becomes a located `YamlError`, which
carries the file's lines so the message can show the line and a caret.

Hostile files are bounded before they cost anything: the size is taken from the open file's status before a byte is
read (a FIFO or a device such as /dev/zero is refused without reading), and the YAML event stream is walked once,
before anything is built, to count what aliases would expand to (a "billion laughs" file of 2 KB names 10^9 values).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.constructor import DuplicateKeyError
from ruamel.yaml.error import MarkedYAMLError, YAMLError
from ruamel.yaml.events import (
    AliasEvent,
    CollectionEndEvent,
    CollectionStartEvent,
    NodeEvent,
)

from codegen.errors import Location, UserError
from codegen.safeio import read_bounded

MAX_BOARD_FILE_BYTES = 256 * 1024  # a board YAML is a few KB; anything this large is not one
# A bundled board holds about 150 values, 4 levels deep. Aliases may repeat a part, but what they expand to stays
# within these bounds (the "billion laughs" file expands to 10^9 values from 2 KB).
MAX_EXPANDED_VALUES = 10_000
MAX_NESTING = 32
PLAIN_TAGS = {f"tag:yaml.org,2002:{name}" for name in ("str", "int", "float", "bool", "null", "map", "seq")}

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


class YamlError(UserError):
    """A located problem reading one YAML file; `lines` are the file's text lines (empty if it is not text)."""

    def __init__(self, message: str, *, location: Optional[Location] = None, hint: Optional[str] = None,
                 lines: Optional[list[str]] = None):
        super().__init__(message, location=location, hint=hint)
        self.lines = lines or []


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
    """Parse one YAML file into plain data plus a source map; raise a located YamlError when it can't."""
    name = display_name or str(path)
    start = Location(name, 1, 1)
    try:
        raw = read_bounded(path, name, MAX_BOARD_FILE_BYTES, what="board YAML")
    except UserError as problem:
        if problem.message.startswith("no such file"):
            raise YamlError(f"no such board file: {name}",
                            hint="`deadreckon boards` lists the bundled boards") from None
        raise YamlError(problem.message, location=problem.location, hint=problem.hint) from None
    nul = raw.find(b"\x00")
    if nul >= 0:
        line, col = _line_col_of_offset(raw, nul)
        raise YamlError("binary data (a NUL byte) in a board YAML", location=_located(name, line, col))
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        line, col = _line_col_of_offset(raw, error.start)
        raise YamlError(
            f"not UTF-8 text (byte 0x{raw[error.start]:02X})",
            location=_located(name, line, col),
            hint="save the board file as UTF-8",
        ) from None
    lines = text.splitlines()

    def located_error(message: str, line0: int, col0: int, hint: Optional[str] = None) -> YamlError:
        return YamlError(message, location=_located(name, line0, col0), hint=hint, lines=lines)

    for number, line_text in enumerate(lines):
        indent = len(line_text) - len(line_text.lstrip(" \t"))
        tab = line_text.find("\t", 0, indent)
        if tab >= 0:
            raise located_error("tab character in indentation", number, tab,
                                "YAML indents with spaces only; replace the tab with spaces")

    yaml = YAML(typ="rt")
    yaml.allow_duplicate_keys = False
    try:
        _check_expansion(yaml, text, located_error)
        tree = yaml.load(text)
    except DuplicateKeyError as error:
        mark = error.problem_mark
        key = _duplicate_key_name(error)
        raise located_error(
            f"duplicate key {key!r}" if key else "duplicate key", mark.line, mark.column,
            f"the first {key!r} is on line {error.context_mark.line + 1}" if error.context_mark else None,
        ) from None
    except MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        problem = " ".join(str(part) for part in (error.context, error.problem) if part)
        message = f"YAML syntax: {problem or 'cannot parse'}"
        if mark is None:
            raise YamlError(message, location=start, lines=lines) from None
        raise located_error(message, mark.line, mark.column) from None
    except (YAMLError, RecursionError, ValueError) as error:
        raise YamlError(f"YAML syntax: {error}", location=start, lines=lines) from None

    if tree is None:
        raise YamlError("empty board file", location=start, hint="start from `deadreckon config` of a bundled board",
                        lines=lines)
    if not isinstance(tree, CommentedMap):
        raise YamlError(
            f"a board file is a mapping of keys (name:, chip:, imu:, ...), not a {_kind(tree)}", location=start,
            lines=lines,
        )
    source = SourceMap()
    source.values[()] = start
    data = _plain(tree, (), name, source)
    return YamlDocument(path=path, data=data, source=source, lines=lines)


def _check_expansion(yaml: YAML, text: str, located_error) -> None:
    """Walk the event stream once and refuse, at the offending place, a document whose aliases would expand to
    more than MAX_EXPANDED_VALUES values or MAX_NESTING levels, or that uses a tag other than the plain ones.

    Each open collection counts the values under it; an anchored node remembers its count and height, so an alias
    costs what it would expand to, without expanding anything."""
    anchors: dict[str, tuple[int, int]] = {}  # anchor -> (values, height) of the node it names
    open_nodes: list[list] = []  # per open collection: [values so far, height of the tallest child, anchor]
    for event in yaml.parse(text):
        if not isinstance(event, (NodeEvent, CollectionEndEvent)):
            continue
        mark = event.start_mark
        tag = getattr(event, "tag", None)
        if tag is not None and str(tag) not in PLAIN_TAGS:
            raise located_error(f"YAML tag {str(tag)!r}: board files use plain values only", mark.line, mark.column,
                                "remove the tag; write the value as a number, a string, true/false, a list or a "
                                "mapping")
        if isinstance(event, CollectionStartEvent):
            if len(open_nodes) + 1 > MAX_NESTING:
                raise located_error(f"nested more than {MAX_NESTING} levels deep; a board YAML is a few levels",
                                    mark.line, mark.column)
            open_nodes.append([1, 0, event.anchor])
            continue
        if isinstance(event, CollectionEndEvent):
            values, height, anchor = open_nodes.pop()
            height += 1
        elif isinstance(event, AliasEvent):
            if event.anchor not in anchors:
                raise located_error(f"alias *{event.anchor} names no anchor defined before it", mark.line,
                                    mark.column)
            values, height = anchors[event.anchor]
            anchor = None
            if len(open_nodes) + height > MAX_NESTING:
                raise located_error(f"alias *{event.anchor} nests the document more than {MAX_NESTING} levels deep",
                                    mark.line, mark.column)
        else:  # a scalar
            values, height, anchor = 1, 0, event.anchor
        if anchor is not None:
            anchors[anchor] = (values, height)
        if open_nodes:
            open_nodes[-1][0] += values
            open_nodes[-1][1] = max(open_nodes[-1][1], height)
        expanded = sum(node[0] for node in open_nodes) if open_nodes else values
        if expanded > MAX_EXPANDED_VALUES:
            raise located_error(
                f"the aliases here expand the document to more than {MAX_EXPANDED_VALUES} values",
                mark.line, mark.column,
                "a board YAML has a few hundred values; is this an alias bomb (billion laughs)?",
            )


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
