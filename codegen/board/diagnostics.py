"""Diagnostics: located errors and warnings, printed as FILE:LINE:COL: severity: message, the line, a caret."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, TextIO

from codegen.errors import Location, UserError


@dataclass(frozen=True)
class Diagnostic:
    severity: str  # "error" or "warning"
    message: str
    location: Optional[Location] = None
    hint: Optional[str] = None

    def render(self, lines_by_file: dict[str, list[str]]) -> str:
        where = f"{self.location}: " if self.location else ""
        out = [f"{where}{self.severity}: {self.message}"]
        if self.location:
            lines = lines_by_file.get(self.location.file, [])
            if 0 < self.location.line <= len(lines):
                text = lines[self.location.line - 1]
                out.append(f"    {text}")
                out.append("    " + " " * (self.location.col - 1) + "^")
        if self.hint:
            out.append(f"  hint: {self.hint}")
        return "\n".join(out)


def error(message: str, location: Optional[Location] = None, hint: Optional[str] = None) -> Diagnostic:
    return Diagnostic("error", message, location, hint)


def warning(message: str, location: Optional[Location] = None, hint: Optional[str] = None) -> Diagnostic:
    return Diagnostic("warning", message, location, hint)


def sort_key(diagnostic: Diagnostic) -> tuple:
    loc = diagnostic.location
    return (loc.file, loc.line, loc.col) if loc else ("", 0, 0)


class DiagnosticsError(UserError):
    """Several diagnostics at once (the CLI prints them all)."""

    def __init__(self, diagnostics: list[Diagnostic], lines_by_file: dict[str, list[str]]):
        errors = [d for d in diagnostics if d.severity == "error"]
        super().__init__(f"{len(errors)} error(s) in the board file")
        self.diagnostics = diagnostics
        self.lines_by_file = lines_by_file

    def render(self) -> str:
        return "\n".join(d.render(self.lines_by_file) for d in self.diagnostics)


def print_all(diagnostics: list[Diagnostic], lines_by_file: dict[str, list[str]], stream: TextIO) -> None:
    for diagnostic in diagnostics:
        print(diagnostic.render(lines_by_file), file=stream)
