"""Fuzz the CLI with seeded mutations of its inputs: the bundled board files (`validate`), a device log, and a
run's CSV pair, NMEA and GPX logs (`post`), and a raw REPL's replies (`upload`), in this process (tests/fuzzkit.py says how each input is made).

    python benchmarks/hostile_fuzz.py [--count 1000] [--seed 1] [--kind board --kind nmea ...]

Oracle, per input: no traceback, exit status 0 or 2 (2 with an `error:`), within the time bound. Prints a table of
inputs, accepted (0), refused (2), failures, the slowest run and the total time per kind, then each failure with
its kind, index and first bytes; exits 1 on any failure.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    sys.path.insert(0, str(ROOT / "tests"))
    sys.path.insert(0, str(ROOT))
    import fuzzkit

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=1000, help="inputs per kind (default 1000)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--kind", action="append", choices=fuzzkit.KINDS, help="only this kind (repeatable)")
    parser.add_argument("--bound", type=float, default=None,
                        help=f"seconds one run may take (default {fuzzkit.BOUND_S:g}, a REPL upload {fuzzkit.BOUNDS['repl']:g})")
    args = parser.parse_args()
    tallies = []
    with tempfile.TemporaryDirectory(prefix="deadreckon-fuzz-") as folder:
        for kind in args.kind or fuzzkit.KINDS:
            tally = fuzzkit.fuzz(kind, args.count, args.seed, Path(folder), bound_s=args.bound)
            tallies.append(tally)
            print(f"{kind}: {tally.inputs} inputs, {len(tally.failures)} failures", file=sys.stderr, flush=True)
    print(f"{'kind':10s} {'inputs':>7s} {'exit 0':>7s} {'exit 2':>7s} {'failed':>7s} {'slowest s':>10s} "
          f"{'total s':>8s}")
    for t in tallies:
        print(f"{t.kind:10s} {t.inputs:7d} {t.accepted:7d} {t.refused:7d} {len(t.failures):7d} {t.slowest_s:10.2f} "
              f"{t.seconds:8.1f}")
    failures = [f for t in tallies for f in t.failures]
    for f in failures:
        print(f"\n{f.kind} #{f.index} (seed {args.seed}): {f.reason}\n  input starts {f.sample[:120]!r}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
