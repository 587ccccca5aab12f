"""The board schema as JSON Schema (for editors) and the resolved config with where each value came from."""

from __future__ import annotations

from typing import Any, Iterator

from codegen.board.loader import LoadedBoard
from codegen.board.model import Board
from codegen.board.yamlsource import KeyPath

# Keys whose numbers read best in hexadecimal
HEX_KEYS = {"address", "offset", "size", "bootloader", "partition_table", "app"}


def board_json_schema() -> dict:
    """JSON Schema (draft 2020-12) of a board YAML; `extends:` is allowed at the top level."""
    schema = Board.model_json_schema(mode="validation")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "deadreckon board"
    schema["properties"]["extends"] = {
        "type": "string",
        "description": "a bundled board's name or a path to a board YAML whose keys this file overrides",
    }
    # A file that extends another may leave out anything its base provides: it is checked against a copy of the
    # schema with no required keys at any depth; a standalone file must be complete.
    partial_defs = {f"Partial{name}": _without_required(part) for name, part in schema["$defs"].items()}
    schema["$defs"].update(partial_defs)
    whole = {key: schema.pop(key) for key in ("properties", "additionalProperties", "type", "required") if key in schema}
    schema["$defs"]["Board"] = whole
    schema["$defs"]["PartialBoard"] = _without_required(whole)
    schema["type"] = "object"
    schema["if"] = {"required": ["extends"]}
    schema["then"] = {"$ref": "#/$defs/PartialBoard"}
    schema["else"] = {"$ref": "#/$defs/Board"}
    return schema


def _without_required(node: Any) -> Any:
    if isinstance(node, dict):
        out = {}
        for key, value in node.items():
            if key == "required":
                continue
            if key == "$ref" and isinstance(value, str) and value.startswith("#/$defs/"):
                value = "#/$defs/Partial" + value[len("#/$defs/"):]
            value = _without_required(value)
            # `key: null` in an extending file removes the base's value
            if key == "properties":
                value = {name: {"anyOf": [child, {"type": "null"}]} for name, child in value.items()}
            elif key == "additionalProperties" and isinstance(value, dict):
                value = {"anyOf": [value, {"type": "null"}]}
            out[key] = value
        return out
    if isinstance(node, list):
        return [_without_required(item) for item in node]
    return node


PIN_KEYS = {"pin", "name", "strapping_by_design"}


def _leaves(value: Any, path: KeyPath) -> Iterator[tuple[KeyPath, Any]]:
    if isinstance(value, dict) and value.keys() == PIN_KEYS:
        written = value["name"] or value["pin"]  # a CircuitPython board.* name, else the GPIO number
        if not value["strapping_by_design"]:
            yield path, written
        else:
            yield path + ("pin",), written
            yield path + ("strapping_by_design",), True
    elif isinstance(value, dict) and value:
        for key, child in value.items():
            yield from _leaves(child, path + (key,))
    elif isinstance(value, list) and value and any(isinstance(item, (dict, list)) for item in value):
        for index, child in enumerate(value):
            yield from _leaves(child, path + (index,))
    else:
        yield path, value


def _format(path: KeyPath, value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return {True: "true", False: "false", None: "null"}[value]
    if isinstance(value, int) and path and path[-1] in HEX_KEYS:
        return f"{value:#x}"
    if isinstance(value, list):
        return "[" + ", ".join(_format(path, item) for item in value) + "]"
    return str(value)


def _given(data: Any, path: KeyPath) -> bool:
    for key in path:
        if isinstance(data, dict) and key in data:
            data = data[key]
        elif isinstance(data, list) and isinstance(key, int) and key < len(data):
            data = data[key]
        else:
            return False
    return True


def resolved_config_lines(loaded: LoadedBoard) -> list[str]:
    """`key: value    # file:line:col` for every value of the board, `# default` where the YAML is silent."""
    dumped = loaded.board.model_dump(mode="python")
    if loaded.board.target == "circuitpython":
        del dumped["micropython"]  # MicroPython's firmware settings do not apply (codegen/board/circuitpython_rules)
    rows = []
    for path, value in _leaves(dumped, ()):
        dotted = ".".join(str(part) for part in path)
        if _given(loaded.data, path):
            where = loaded.source.value(path)
            origin = str(where) if where else "board file"
        else:
            origin = "default"
        rows.append((f"{dotted}: {_format(path, value)}", origin))
    width = max(len(text) for text, _ in rows)
    return [f"{text.ljust(width)}  # {origin}" for text, origin in rows]
