"""Run a benchmark script and keep what it printed as its last output, the source of the figures in README/docs.
    python3 benchmarks/record.py device.py --algorithm fused      # prints as it runs; then benchmarks/results/device.txt
    python3 benchmarks/record.py --as kernel-host kernel.py --no-device
The results file starts with the command, the date and the host, then holds the script's standard output as it
printed it. It is written only when the script exits 0, so a failed run never replaces the last good figures.
tests/test_doc_figures.py checks every figure block of README.md and docs/*.md against the file it names.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import platform
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"


def header(command: list[str]) -> str:
    when = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    host = f"{platform.machine()} {platform.system()}, Python {platform.python_version()}"
    return f"# command: python3 {' '.join(command)}\n# date: {when}\n# host: {host}\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--as", dest="name", help="results file name (default: the script's name)")
    parser.add_argument("script", help="a script in benchmarks/, e.g. device.py")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="its arguments")
    args = parser.parse_args(argv)
    script = HERE / args.script
    if not script.is_file() or script.parent != HERE or script.name == Path(__file__).name:
        print(f"error: {args.script}: not a benchmark script in {HERE}", file=sys.stderr)
        return 2
    command = [f"benchmarks/{script.name}", *args.args]
    process = subprocess.Popen([sys.executable, str(script), *args.args], stdout=subprocess.PIPE, text=True)
    printed = []
    assert process.stdout is not None
    for line in process.stdout:
        sys.stdout.write(line)
        printed.append(line)
    if process.wait() != 0:
        print(f"error: {' '.join(command)} exited {process.returncode}: the last results are kept", file=sys.stderr)
        return process.returncode
    RESULTS.mkdir(exist_ok=True)
    target = RESULTS / f"{args.name or script.stem}.txt"
    partial = target.with_suffix(".txt.partial")
    partial.write_text(header(command) + "".join(printed))
    partial.replace(target)
    print(f"results: {target.relative_to(HERE.parent)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
