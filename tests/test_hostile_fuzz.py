"""A few hundred generated hostile inputs through the CLI (tests/fuzzkit.py): mutated bundled boards through
`validate`, mutated device logs, CSV pairs, NMEA and GPX logs through `post`, mutated raw-REPL replies through
`upload`. Every one must end with exit 0 or 2
(2 with an `error:`), without a traceback, within the bound. benchmarks/hostile_fuzz.py runs thousands."""

from __future__ import annotations

import pytest

import fuzzkit

# inputs per kind: together about 40 s on an idle 2-core host (a valid NMEA run posts in ~0.6 s, a board in 0.1 s)
# (a REPL upload takes 1-3 s: it enters raw mode and waits out what the peer leaves unfinished)
COUNTS = {"board": 80, "devicelog": 50, "csv": 60, "nmea": 25, "gpx": 60, "repl": 12}


@pytest.mark.parametrize("kind", fuzzkit.KINDS)
def test_generated_inputs_end_cleanly(kind, tmp_path):
    tally = fuzzkit.fuzz(kind, COUNTS[kind], seed=7, folder=tmp_path)
    assert tally.inputs == COUNTS[kind]
    shown = "\n".join(f"#{f.index}: {f.reason}\n  input starts {f.sample[:120]!r}" for f in tally.failures)
    assert not tally.failures, shown
    assert tally.refused > 0
    if kind != "repl":  # a damaged REPL never completes an upload: every input there is refused
        assert tally.accepted > 0, "the mutations should give both kinds of input"


def test_the_oracle_catches_a_traceback(tmp_path, monkeypatch):
    """A CLI that raises is a failure, not a pass (the fuzzer can fail)."""
    from codegen.board import loader

    def broken(*args, **kwargs):
        raise ZeroDivisionError("planted")

    monkeypatch.setattr(loader, "load_board_report", broken)
    tally = fuzzkit.fuzz("board", 2, seed=7, folder=tmp_path)
    assert len(tally.failures) == 2 and "ZeroDivisionError: planted" in tally.failures[0].reason
