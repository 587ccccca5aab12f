"""Errors meant for the user: a message, the place it concerns, and a hint. Never a traceback."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class Location:
    """A place in a text file, 1-based line and column as editors count them."""

    file: str
    line: int
    col: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.col}"


class UserError(Exception):
    """A problem the user can fix; `render()` gives the text the CLI prints."""

    def __init__(self, message: str, *, location: Optional[Location] = None, hint: Optional[str] = None):
        super().__init__(message)
        self.message = message
        self.location = location
        self.hint = hint

    def render(self) -> str:
        where = f"{self.location}: " if self.location else ""
        text = f"{where}error: {self.message}"
        if self.hint:
            text += f"\n  hint: {self.hint}"
        return text
