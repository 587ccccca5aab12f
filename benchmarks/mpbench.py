"""The kernels on the unix-port `micropython`, for benchmarks/kernel.py and benchmarks/fused.py: time per window and
bytes allocated per window, for the generated fallback (as rendered now, with decorator variants, and as rendered
from the template of an older git revision, side by side) and the x64 natmod.

Bytes: how far `gc.mem_alloc()` grows over one window with the collector off (the whole window fits the 64 MB heap),
i.e. everything the window allocates. On this 64-bit port a boxed float takes one 32-byte GC block; on the ESP32 and
RP2040 (32-bit, MICROPY_OBJ_REPR_A) one 16-byte block, so a board allocates about half these bytes for the same code.
Time: best of `repeat` windows, each after a gc.collect(): the collector does not run inside a window here, while on
a board's ~100 KB heap it runs every few hundred samples. Times on a shared machine vary by tens of percent from run
to run; the instruction count per window (valgrind callgrind: the interpreter running 3 windows minus running 1, /2)
does not, so before/after ratios are quoted from it.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from codegen.generate import render_template_text  # noqa: E402
from codegen.tools import find_tool  # noqa: E402

FALLBACK_TEMPLATE = "micropython/dr_fallback.py.j2"

MP_SCRIPT = """
import gc, sys, time
from array import array
sys.path.insert(0, {folder!r})
import {module} as dr
n = {n}
samples = array('h', bytes(12 * n))
dt = array('i', bytes(4 * n))
with open({samples!r}, 'rb') as f:
    f.readinto(samples)
with open({dt!r}, 'rb') as f:
    f.readinto(dt)
out = array('f', [0.0] * dr.OUT_LEN)
if {fused}:
    st = array('f', [0.0] * dr.FUSED_STATE_LEN)
    dr.fused_init(st)

    def window():
        dr.fused_process(st, samples, dt, out)
        dr.fused_position(st, 1.0, 0.5, 1.0, 0.5)
        dr.fused_gps(st, 1.0, 0.5)
else:
    st = array('f', [0.0] * dr.STATE_LEN)
    dr.init(st)

    def window():
        dr.process(st, samples, dt, out)
window()
if {windows}:
    for _ in range({windows}):
        window()
    sys.exit(0)
gc.collect()
gc.disable()
start = gc.mem_alloc()
window()
grown = gc.mem_alloc() - start
gc.enable()
best = None
for _ in range({repeat}):
    gc.collect()
    t0 = time.ticks_us()
    window()
    t = time.ticks_diff(time.ticks_us(), t0)
    best = t if best is None or t < best else best
print('US', best, 'BYTES', grown)
"""


def fallback_at(loaded, revision: str) -> tuple[str | None, str]:
    """The board's dr_fallback.py rendered from the template as it was at git `revision`: (source, note)."""
    done = subprocess.run(["git", "-C", str(ROOT), "show", f"{revision}:templates/{FALLBACK_TEMPLATE}"],
                          capture_output=True, text=True)
    if done.returncode:
        return None, f"no template at {revision}: {done.stderr.strip()[:60]}"
    return render_template_text(loaded, done.stdout, FALLBACK_TEMPLATE), ""


def short_revision(revision: str) -> str:
    done = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", revision], capture_output=True, text=True)
    return done.stdout.strip() or revision


def variant(source: str, decorator: str | None, hot: tuple[str, ...]) -> str:
    """The fallback with `decorator` on its hot functions `hot` (and _median, _sort). Viper needs machine-int
    arguments and cannot mix them with float objects (it has no float type), so its variant types the sort/median
    indices as int and puts the float arithmetic (`hot`) under @micropython.native."""
    if decorator is None:
        return source
    if decorator == "viper":
        for name in ("_sort", "_median"):
            source = source.replace(f"\ndef {name}(x, start, count):",
                                    f"\n@micropython.viper\ndef {name}(x, start: int, count: int):", 1)
        decorator, names = "native", hot
    else:
        names = hot + ("_median", "_sort")
    for name in names:
        source = source.replace(f"\ndef {name}(", f"\n@micropython.{decorator}\ndef {name}(", 1)
    return "import micropython\n" + source


def measure(folder: Path, module: str, samples: np.ndarray, dt_us: np.ndarray, fused: bool,
            repeat: int) -> tuple[float | None, int | None, float | None, str]:
    """(seconds per window, bytes allocated per window, x86-64 instructions per window or None without valgrind,
    why not) of `module` importable from `folder`."""
    exe = find_tool("micropython")
    if exe is None:
        return None, None, None, "micropython not installed"
    raw = folder / "samples.bin"
    raw.write_bytes(np.ascontiguousarray(samples, dtype="<i2").tobytes())
    (folder / "dt.bin").write_bytes(np.ascontiguousarray(dt_us, dtype="<i4").tobytes())

    def script(windows: int) -> Path:
        path = folder / f"bench_{module}_{windows}.py"
        path.write_text(MP_SCRIPT.format(folder=str(folder), module=module, n=len(dt_us), samples=str(raw),
                                         dt=str(folder / "dt.bin"), fused=fused, repeat=repeat, windows=windows))
        return path

    done = subprocess.run([exe, "-X", "heapsize=64M", str(script(0))], capture_output=True, text=True, timeout=1800)
    found = re.search(r"US (\d+) BYTES (\d+)", done.stdout)
    if not found:
        return None, None, None, (done.stderr.strip().splitlines() or ["failed"])[-1][:70]
    return int(found.group(1)) * 1e-6, int(found.group(2)), instructions(exe, folder, script), ""


def instructions(exe: str, folder: Path, script) -> float | None:
    """Instructions per window: callgrind's total for 3 windows minus that for 1, halved (None without valgrind)."""
    if not shutil.which("valgrind"):
        return None
    totals = []
    for windows in (1, 3):
        out = folder / f"callgrind.{windows}"
        done = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", exe, "-X",
                               "heapsize=64M", str(script(windows))], capture_output=True, text=True, timeout=3600)
        found = re.search(r"^(?:summary|totals): (\d+)", out.read_text(), re.M) if done.returncode == 0 else None
        if not found:
            return None
        totals.append(int(found.group(1)))
    return (totals[1] - totals[0]) / 2


def fallback_rows(loaded, files, folder: Path, samples, dt_us, fused: bool, repeat: int, before: str | None,
                  hot: tuple[str, ...]):
    """Rows (label, seconds, bytes, instructions, note) for the fallback: `before`'s (plain), then today's plain,
    @native and viper variants."""
    sources = []
    if before:
        old, note = fallback_at(loaded, before)
        sources.append((f"dr_fallback before ({short_revision(before)}), plain", old, note))
    now = files["app/dr_fallback.py"].content.decode()
    for label, decorator in (("plain", None), ("@micropython.native", "native"),
                             ("@viper sort/median, @native the rest", "viper")):
        sources.append((f"dr_fallback now, {label}", variant(now, decorator, hot), ""))
    rows = []
    for k, (label, source, note) in enumerate(sources):
        if source is None:
            rows.append((label, None, None, None, note))
            continue
        sub = folder / f"fallback-{k}"
        sub.mkdir()
        (sub / "dr_fallback.py").write_text(source)
        rows.append((label, *measure(sub, "dr_fallback", samples, dt_us, fused, repeat)))
    return rows


def print_table(rows, n: int) -> None:
    """(label, seconds or None, bytes or None, instructions or None, why) rows: time per window, its ratio to the
    first row (the C), bytes allocated per window and per sample, x86-64 instructions per window."""
    c_host = rows[0][1]
    print(f"{'implementation':58s} {'time/window':>12s} {'x C':>8s} {'bytes/window':>13s} {'bytes/sample':>13s} "
          f"{'instr/window':>14s}")
    for label, seconds, grown, count, why in rows:
        if seconds is None:
            print(f"{label:58s} {'-':>12s} {'':>8s} {'':>13s} {'':>13s} {'':>14s}  ({why})")
            continue
        size = f"{grown:13,d} {grown / n:13.0f}" if grown is not None else f"{'-':>13s} {'-':>13s}"
        counted = f"{count:14,.0f}" if count is not None else f"{'-':>14s}"
        print(f"{label:58s} {seconds * 1e3:9.3f} ms {seconds / c_host:7.1f}x {size} {counted}")
