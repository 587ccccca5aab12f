"""A small CSV reader that knows where every value came from, so a bad log gets a FILE:LINE:COL error.

A last line without its newline and with too few fields is what a log cut off by a power loss looks like: it is
dropped with a note, not an error. Anything malformed before the end is an error at its place.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from codegen.errors import Location, UserError


@dataclass
class Table:
    path: str
    columns: dict[str, np.ndarray]
    lines: np.ndarray  # (N,) 1-based line number of each row
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.lines)

    def location(self, row: int, column: Optional[str] = None) -> Location:
        return Location(self.path, int(self.lines[row]), 1)


MAX_INPUT_BYTES = 1 << 30  # 1 GiB: hours of 400 Hz IMU text; more is not a log this command should hold in memory


def check_input_file(path: Path, what: str) -> None:
    """A regular file of a size this command can hold, else a clear error (before a byte is read: a device or a
    pipe never ends, and reading one would hang)."""
    if not path.exists():
        raise UserError(f"{what} {path} does not exist", hint="check the path")
    if path.is_dir():
        raise UserError(f"{what} {path} is a folder, expected a file")
    if not path.is_file():
        raise UserError(f"{what} {path} is not a regular file (a device, pipe or socket)",
                        hint="copy the log into a file first")
    size = path.stat().st_size
    if size > MAX_INPUT_BYTES:
        raise UserError(f"{what} {path} is {size / 2**30:.1f} GiB; this command reads logs of up to "
                        f"{MAX_INPUT_BYTES / 2**30:.0f} GiB", hint="split the log into shorter runs")


def read_bytes(path: Path, what: str) -> bytes:
    check_input_file(path, what)
    try:
        return path.read_bytes()
    except OSError as error:
        raise UserError(f"cannot read {what} {path}: {error.strerror}") from None


def read_text(path: Path, what: str) -> str:
    text = read_bytes(path, what).decode("utf-8", errors="replace")
    if not text.strip():
        raise UserError(f"{what} {path} is empty", location=Location(str(path), 1, 1),
                        hint="the logger wrote nothing: was the SD card/flash full or the run too short?")
    return text


def read_table(path: Path, what: str, required: Sequence[str], optional: Sequence[str] = ()) -> Table:
    """Read a header-first CSV; returns float columns for `required` (all) and `optional` (those present)."""
    text = read_text(path, what)
    name = str(path)
    lines = text.split("\n")
    # header: the first non-empty, non-comment line
    index = 0
    while index < len(lines) and (not lines[index].strip() or lines[index].lstrip().startswith("#")):
        index += 1
    header = [h.strip().lower() for h in lines[index].strip().split(",")]
    missing = [c for c in required if c not in header]
    if missing:
        raise UserError(
            f"{what} header lacks column(s) {', '.join(missing)} (found: {','.join(header)})",
            location=Location(name, index + 1, 1),
            hint=f"the first line must name the columns: {','.join(required)}",
        )
    wanted = list(required) + [c for c in optional if c in header]
    positions = [header.index(c) for c in wanted]
    rows: list[list[float]] = []
    numbers: list[int] = []
    notes: list[str] = []
    ends_with_newline = text.endswith("\n")
    last = len(lines) - 1
    while last > index and not lines[last].strip():
        last -= 1
    for number in range(index + 1, last + 1):
        raw = lines[number].strip()
        if not raw or raw.startswith("#"):
            continue
        fields = raw.split(",")
        is_cut_tail = number == last and not ends_with_newline
        if len(fields) < len(header):
            if is_cut_tail or (number == last and any(not f.strip() for f in fields[-1:])):
                notes.append(f"{name}:{number + 1}: dropped a truncated last line ({len(fields)} of {len(header)} fields)")
                continue
            raise UserError(
                f"{what} line has {len(fields)} fields, the header has {len(header)}",
                location=Location(name, number + 1, len(raw) + 1),
                hint="the log is damaged or truncated here",
            )
        row = []
        for column, pos in zip(wanted, positions):
            value = fields[pos].strip()
            try:
                row.append(float(value))
            except ValueError:
                if is_cut_tail:
                    row = None
                    break
                col = sum(len(f) + 1 for f in fields[:pos]) + 1
                raise UserError(
                    f"{what}: {column} is {value!r}, not a number",
                    location=Location(name, number + 1, col),
                    hint="the log is damaged here; remove or repair the line",
                ) from None
        if row is None:
            notes.append(f"{name}:{number + 1}: dropped a truncated last line")
            continue
        rows.append(row)
        numbers.append(number + 1)
    data = np.array(rows, dtype=float).reshape(-1, len(wanted))
    bad = ~np.isfinite(data)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise UserError(f"{what}: {wanted[c]} is not finite", location=Location(name, numbers[r], 1))
    return Table(name, {c: data[:, i] for i, c in enumerate(wanted)}, np.array(numbers, dtype=int), notes)


def check_increasing(table: Table, what: str, column: str = "t", strict: bool = True) -> None:
    t = table.columns[column]
    step = np.diff(t)
    bad = np.flatnonzero(step <= 0 if strict else step < 0)
    if bad.size:
        i = int(bad[0]) + 1
        relation = "repeats" if step[bad[0]] == 0 else "goes back in time"
        raise UserError(
            f"{what}: time {t[i]:.6g} s {relation} (previous line {int(table.lines[i - 1])}: {t[i - 1]:.6g} s)",
            location=Location(table.path, int(table.lines[i]), 1),
            hint="time must increase line by line; was the log appended to, or did the clock wrap/reset?",
        )


def check_range(table: Table, what: str, column: str, low: float, high: float, unit: str, hint: str) -> None:
    """Every value of `column` within [low, high], else an error at the first row that is not."""
    values = table.columns[column]
    bad = np.flatnonzero((values < low) | (values > high))
    if bad.size:
        i = int(bad[0])
        raise UserError(f"{what}: {column} is {values[i]:g} {unit}, outside {low:g}..{high:g}",
                        location=table.location(i), hint=hint)
