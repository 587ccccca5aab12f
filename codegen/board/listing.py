"""`deadreckon boards`: the bundled boards as a two-column table that fits a terminal's width."""

from __future__ import annotations

import textwrap

NAME_COLUMN_MAX = 26  # a longer name takes its own line, its description goes below it


def board_table(boards: list[tuple[str, str]], width: int = 80) -> list[str]:
    """Lines of `name  description`, descriptions wrapped to `width` columns under their own column."""
    width = max(width, 40)
    column = min(max((len(name) for name, _ in boards), default=0), NAME_COLUMN_MAX) + 2
    lines = []
    for name, description in boards:
        wrapped = textwrap.wrap(description, width - column) or [""]
        if len(name) + 2 > column:
            lines.append(name)
            lines += [" " * column + part for part in wrapped]
        else:
            lines.append(f"{name:<{column}}{wrapped[0]}".rstrip())
            lines += [" " * column + part for part in wrapped[1:]]
    return lines
