"""Instructions per window on the boards' instruction sets, for benchmarks/kernel.py (seed) and fused.py (fused).

    python3 benchmarks/device.py [--algorithm seed|fused|eskf] [--windows N] [--before REV] [--scenario S]
    python3 benchmarks/device.py --algorithm fused --scenario replay-car   # a vehicle's windows (the real car)

ARM: MicroPython 1.28's QEMU port (codegen.natmod.qemu_arm; MICROBIT = Cortex-M0, the RP2040's armv6m; MPS2_AN385 =
Cortex-M3, armv7m) runs the board's dr_native.mpy built for that arch and the generated dr_fallback compiled by
mpy-cross for it (plain; @micropython.native; for the seed kernel also @viper sort/median), through the same driver
(codegen/natmod/device_driver.py) on the recorded walk (--scenario replay-car: the real car, whose fused windows
take the vehicle's branch; after each fused window the last GPS fix before its end). Counts are exact: QEMU runs
with -icount shift=0 (one instruction per virtual ns) and the driver reads a hardware timer of the emulated SoC
around each call.
Xtensa: the ESP32 code of the same dr_native.mpy (LLVM route) on qemu-system-xtensa de233_fpu, the kernel called
by a bare-metal harness, counted by the core's ICOUNT register (codegen.natmod.qemu_xtensa).

eskf: the error-state filter's C (native_ext/dr_eskf.c; in dr_native.mpy for eskf boards), measured alone:
compiled for the ESP32 by the same LLVM route with the natmod's flags and run by its own bare-metal harness
(codegen.natmod.xtensa_eskf) on a simulated vehicle drive (--scenario, default car; seed 0), a GPS fix every second; a window counts its 512 samples
and the fixes that fall in it. Its positions are checked against the same C built for the host (cffi).

ESP32 time per window is estimated from the Xtensa count: the LX6 is a single-issue 5-stage pipeline, the natmod's
code sits in IRAM (MicroPython's ESP32 port commits native code there: no flash cache misses) and its data in DRAM,
so one instruction per cycle is the floor; FPU latencies, load-use stalls and taken branches raise it, which the
table brackets with two cycles per instruction. Both at 240 MHz.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from codegen.tools import micropython_tree, tool_env  # noqa: E402

ESP32_HZ = 240e6
QEMU_ARM = (("MICROBIT", "armv6m", "Cortex-M0 (armv6m: RP2040)"), ("MPS2_AN385", "armv7m", "Cortex-M3 (armv7m)"),
            ("MPS2_AN500", "armv7emsp", "Cortex-M7 FPU (armv7emsp)"))


def _native_dir(folder: Path, files) -> Path:
    native = folder / "native"
    for name, rendered in files.items():
        if name.startswith("native/"):
            (native / name[7:]).parent.mkdir(parents=True, exist_ok=True)
            (native / name[7:]).write_bytes(rendered.content)
    return native


def natmod(files, arch: str, folder: Path) -> tuple[bytes | None, str]:
    """dr_native.mpy of the rendered tree for `arch` (make against the MicroPython tree), or (None, why)."""
    from codegen.tools import find_mpy_cross

    tree = micropython_tree()
    if tree is None:
        return None, "no MicroPython tree"
    native = _native_dir(folder / arch, files)
    done = subprocess.run(["make", f"MPY_DIR={tree}", f"ARCH={arch}", f"MPY_CROSS={find_mpy_cross('1.28.0')}",
                           f"PYTHON={sys.executable}"], cwd=native, capture_output=True, text=True, env=tool_env())
    if done.returncode:
        return None, f"natmod build failed: {(done.stdout + done.stderr).strip().splitlines()[-1][:60]}"
    return (native / "dr_native.mpy").read_bytes(), ""


def fallback_variants(source: str, algorithm: str) -> dict:
    """label -> the fallback's source with that emitter on its hot functions."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from mpbench import variant

    if algorithm == "seed":
        return {"plain": source, "@native": variant(source, "native", ("process",)),
                "@viper sort/median": variant(source, "viper", ("process",))}
    native = "import micropython\n" + re.sub(r"^def ", "@micropython.native\ndef ", source, flags=re.M)
    return {"plain": source, "@native": native}


def compile_for(source: str, arch: str, folder: Path) -> tuple[bytes | None, str]:
    from codegen.tools import find_mpy_cross

    folder.mkdir(parents=True, exist_ok=True)
    py = folder / "dr_fallback.py"
    py.write_text(source)
    done = subprocess.run([find_mpy_cross("1.28.0"), f"-march={arch}", str(py)], capture_output=True, text=True)
    if done.returncode:
        return None, (done.stderr.strip().splitlines() or ["mpy-cross failed"])[-1][:60]
    return py.with_suffix(".mpy").read_bytes(), ""


RECORDED = {"replay-walk": "recorded walk", "replay-car": "real car (car-comma2k19, driving at 14-20 m/s)"}


def recorded_steps(board, algorithm: str, windows: int, scenario: str = "replay-walk") -> list:
    """The app's calibration then `windows` windows of a recording (RECORDED: the walk, or the real car, whose
    fused windows take the vehicle's branch), and, for fused, after each window the last GPS fix before its end."""
    from codegen.sim.run import build_run

    run = build_run(scenario, board)
    t = run.t_us * 1e-6
    dt = np.diff(run.t_us).astype(np.int32)
    k = board.calibration_samples
    n = board.algorithm.window
    steps = [("C", run.counts[:k])]
    vel = run.gps.device_velocity()
    for j in range(windows):
        steps.append(("P", run.counts[k + j * n:k + (j + 1) * n], dt[k + j * n:k + (j + 1) * n]))
        if algorithm == "fused":
            fix = int(run.gps.last_valid_before(np.array([t[k + (j + 1) * n]]))[0])
            d = run.gps.enu[fix, :2] - run.gps.enu[fix - 1, :2]
            steps.append(("G", float(vel[fix, 0]), float(vel[fix, 1]), float(d[0]), float(d[1])))
    return steps


def per_window(answers, steps) -> float:
    """Median instructions of the window steps (a fused window counts its GPS fix with it)."""
    counts = []
    for item, answer in zip(steps, answers):
        if item[0] == "P":
            counts.append(answer.instructions)
        elif item[0] == "G":
            counts[-1] += answer.instructions
    return float(np.median(counts))


def arm_row(board_name: str, arch: str, modules: dict, algorithm: str, steps_all: list, fallback_windows: int,
            state_floats: int) -> dict:
    """label -> (instructions per window or None, why)."""
    from codegen.natmod import qemu_arm, windows

    elf = qemu_arm.firmware(micropython_tree(), board_name, log=lambda m: print(f"  ({m})", file=sys.stderr))
    row = {}
    for label, (mpy, why) in modules.items():
        if mpy is None:
            row[label] = (None, why)
            continue
        module = "dr_native" if label == "natmod" else "dr_fallback"
        steps = steps_all if label == "natmod" else _first_windows(steps_all, fallback_windows)
        try:
            with qemu_arm.Session(elf, board_name, timeout=900) as session:
                session.put_file(f"{module}.mpy", mpy)
                answers = windows.run(session, module, algorithm, steps, state_floats)
            row[label] = (per_window(answers, steps), "")
        except Exception as exc:  # a failed variant is a row with its reason, not a crashed benchmark
            row[label] = (None, str(exc).strip().splitlines()[-1][:60])
    return row


def _first_windows(steps: list, windows: int) -> list:
    kept, seen = [], 0
    for item in steps:
        seen += item[0] == "P"
        if seen > windows:
            break
        kept.append(item)
    return kept


def xtensa_count(files, algorithm: str, steps: list, state_floats: int, folder: Path) -> tuple[float | None, str]:
    from codegen.natmod import linkmap, mpyfile, qemu_xtensa
    from codegen.natmod.build import LOG_NAME, NoRoute, build_module

    try:
        built = build_module(_native_dir(folder / "xtensa", files), folder / "xtensa-build", "xtensawin", "1.28.0",
                             progress=lambda _: None)
        work = folder / "xtensa-build"
        link = linkmap.parse((work / LOG_NAME).read_text(), work)
        harness = qemu_xtensa.build_harness(work, built.tree, folder / "harness")
        module = mpyfile.parse(built.module.read_bytes())
        answers = qemu_xtensa.run(module, link, harness, steps, algorithm, state_floats)
    except (NoRoute, Exception) as exc:
        return None, str(exc).strip().splitlines()[0][:70]
    return per_window(answers, steps), ""


def device_table(loaded, algorithm: str, windows: int = 4, fallback_windows: int = 2, before: str = "",
                 scenario: str = "replay-walk") -> None:
    """Print the device-ISA table of one algorithm for the board `loaded` on a recording (RECORDED); `before` (a git
    revision): its fallback (plain) in a column beside today's, run in the same sessions."""
    from codegen.generate import render_tree
    from codegen.kernel import fused as F

    board = loaded.board
    files = render_tree(loaded)
    state_floats = 10 if algorithm == "seed" else F.STATE_LEN
    steps = recorded_steps(board, algorithm, windows, scenario)
    n = board.algorithm.window
    what = "window" if algorithm == "seed" else "window + its GPS fix"
    print(f"\non the boards' instruction sets ({algorithm}): instructions per {what} of {n} x 6 samples, "
          f"{RECORDED[scenario]}, exact counts in QEMU")
    header = f"{'core':34s} {'natmod':>10s}"
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        variants = fallback_variants(files["app/dr_fallback.py"].content.decode(), algorithm)
        if before:
            sys.path.insert(0, str(Path(__file__).resolve().parent))
            from mpbench import fallback_at, short_revision

            old, note = fallback_at(loaded, before)
            if old is None:
                print(f"(fallback before: {note})")
            else:
                variants = {f"before {short_revision(before)}": old, **variants}
        for label in variants:
            header += f" {'fallback ' + label:>20s}"
        print(header + f" {'best fallback / natmod':>23s}")
        for board_name, arch, core in QEMU_ARM:
            modules = {"natmod": natmod(files, arch, folder)}
            for label, source in variants.items():
                modules[label] = compile_for(source, arch, folder / f"{arch}-{label.strip('@').split()[0]}")
            row = arm_row(board_name, arch, modules, algorithm, steps, fallback_windows, state_floats)
            line = f"{core + ' MicroPython':34s}"
            notes = []
            for label in modules:
                value, why = row[label]
                width = 10 if label == "natmod" else 20
                line += f" {value / 1e6:>{width - 2}.2f} M" if value else f" {'-':>{width}s}"
                if why:
                    notes.append(f"{label}: {why}")
            natmod_count = row["natmod"][0]
            best = min((v for label, (v, _) in row.items() if label != "natmod" and not label.startswith("before")
                        and v), default=None)
            line += f" {best / natmod_count:>22.0f}x" if best and natmod_count else f" {'-':>23s}"
            print(line + (f"   ({'; '.join(notes)})" if notes else ""))
        count, why = xtensa_count(files, algorithm, steps, state_floats, folder)
    if count is None:
        print(f"{'ESP32 code, de233_fpu (bare kernel)':34s} {'-':>10s}   ({why})")
        return
    print(f"{'ESP32 code, de233_fpu (bare kernel)':34s} {count / 1e6:>8.3f} M")
    print(f"ESP32 at 240 MHz (estimate from the Xtensa count, code in IRAM): {count / ESP32_HZ * 1e3:.2f} ms per "
          f"{what} at 1 cycle/instruction, {2 * count / ESP32_HZ * 1e3:.2f} ms at 2 (goal <= 5 ms); the app's "
          f"MicroPython call around it adds a few thousand instructions")


def eskf_steps(board, scenario: str, seed: int, duration: float) -> tuple[list, list]:
    """The calibration, then the drive cut into windows of the board's size with a fix step ("G", t, e, n, u, ve,
    vn) wherever a fix falls: (steps, the window index of each step, -1 for the calibration)."""
    from codegen.sim.run import build_run

    run = build_run(scenario, board, seed=seed, duration=duration)
    t = run.t_us * 1e-6
    dt = np.diff(run.t_us).astype(np.int32)
    k = int(np.searchsorted(t, board.algorithm.calibration_s))
    n = board.algorithm.window
    gps, vel = run.gps, run.gps.device_velocity()
    fixes = [(int(np.searchsorted(t, gps.t[j], side="left")), j) for j in np.flatnonzero(gps.valid & (gps.t >= t[k]))]
    steps, window_of = [("C", run.counts[:k])], [-1]
    w = 0
    while k + n <= len(dt):
        end = k + n
        for stop, j in fixes:
            if k <= stop < end:
                if stop > k:
                    steps.append(("P", run.counts[k:stop], dt[k:stop]))
                    window_of.append(w)
                steps.append(("G", float(gps.t[j]), *(float(x) for x in gps.enu[j]), float(vel[j, 0]),
                              float(vel[j, 1])))
                window_of.append(w)
                k = stop
        steps.append(("P", run.counts[k:end], dt[k:end]))
        window_of.append(w)
        k, w = end, w + 1
    return steps, window_of


def _host_positions(steps: list, cov_dt_s: float, nhc_dt_s: float) -> np.ndarray:
    """The same steps through the host build of the C (cffi): the position after each."""
    from dataclasses import replace

    from codegen.kernel.eskf import EskfConfig
    from codegen.kernel.hosteskf import load_eskf

    s = load_eskf().session(replace(EskfConfig(), cov_dt_s=cov_dt_s, nhc_dt_s=nhc_dt_s))
    out = []
    for item in steps:
        if item[0] == "C":
            s.calibrate(item[1])
        elif item[0] == "P":
            s.process(item[1], item[2])
        else:
            s.gps(item[1], item[2:5], item[5:7])
        out.append(list(s.st.pos))
    return np.array(out)


def eskf_table(loaded, scenario: str = "car", seed: int = 0, duration: float = 120.0, cov_dt_s: float = 0.0,
               nhc_dt_s: float = 0.0) -> None:
    """Instructions per window of the error-state filter's ESP32 code on qemu-system-xtensa (cadences in s; 0: the
    defaults of codegen.kernel.eskf.EskfConfig, which dr_eskf_config_init holds too)."""
    from codegen.kernel.eskf import EskfConfig

    cov_dt_s = cov_dt_s or EskfConfig().cov_dt_s
    nhc_dt_s = nhc_dt_s or EskfConfig().nhc_dt_s
    from codegen.generate import render_tree
    from codegen.natmod import xtensa_eskf

    board = loaded.board
    n = board.algorithm.window
    steps, window_of = eskf_steps(board, scenario, seed, duration)
    alone = [("Q",), ("K",), ("N",), ("U",)]  # single steps on the final state, undone after each
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        try:
            image = xtensa_eskf.build(_native_dir(folder, render_tree(loaded)), micropython_tree(), folder / "eskf")
            answers = xtensa_eskf.run(image, steps + alone, cov_dt_s=cov_dt_s, nhc_dt_s=nhc_dt_s)
        except Exception as exc:  # a missing tool is a row with its reason, not a crashed benchmark
            print(f"\neskf on ESP32 code: - ({str(exc).strip().splitlines()[0][:90]})")
            return
    single = {item[0]: answer.instructions for item, answer in zip(alone, answers[len(steps):])}
    answers = answers[:len(steps)]
    windows = max(window_of) + 1
    per = np.zeros(windows)
    fixes = np.zeros(windows)
    started = np.zeros(windows, dtype=bool)
    for item, w, answer in zip(steps, window_of, answers):
        if w >= 0:
            per[w] += answer.instructions
            fixes[w] += item[0] == "G"
            started[w] = answer.started
    running = per[started]
    host = _host_positions(steps, cov_dt_s, nhc_dt_s)
    device = np.array([a.position for a in answers])
    print(f"\nthe error-state filter (eskf, 23 states) on ESP32 code, de233_fpu, bare filter: simulated {scenario} "
          f"seed {seed}, {duration:.0f} s, covariance every {cov_dt_s:g} s, pseudo-measurements every {nhc_dt_s:g} s, instructions per window of {n} samples and its fixes (exact ICOUNT)")
    print(f"code: {image.filter_text_bytes} bytes (dr_eskf.o text + literals, -Os); state {xtensa_eskf_state_bytes()} "
          f"bytes; config {xtensa_eskf_config_bytes()} bytes")
    print(f"{'windows':24s} {'count':>6s} {'median':>10s} {'p90':>10s} {'max':>10s} {'ms @240MHz, 1-2 cyc/insn':>26s}")
    for label, values in (("before the start", per[~started]), ("filter running", running)):
        if len(values) == 0:
            continue
        med, p90, top = np.median(values), np.percentile(values, 90), np.max(values)
        print(f"{label:24s} {len(values):6d} {med / 1e6:8.3f} M {p90 / 1e6:8.3f} M {top / 1e6:8.3f} M "
              f"{med / ESP32_HZ * 1e3:>11.2f}-{2 * med / ESP32_HZ * 1e3:.2f} (max {top / ESP32_HZ * 1e3:.2f}-"
              f"{2 * top / ESP32_HZ * 1e3:.2f})")
    kinds = {"P": [], "G": []}
    for item, w, answer in zip(steps, window_of, answers):
        if w >= 0 and started[w] and item[0] in kinds:
            kinds[item[0]].append(answer.instructions / (len(item[1]) if item[0] == "P" else 1))
    print(f"per sample (mechanisation + its share of propagation and pseudo-measurements): "
          f"{np.mean(kinds['P']):.0f} instructions; per fix: {np.median(kinds['G']):.0f}; fixes per window "
          f"{np.median(fixes):.0f}")
    print(f"single steps: propagation {single['Q']:.0f}, covariance check {single['K']:.0f}, constraint rows "
          f"{single['N']:.0f}, one scalar update (8 non-zeros) {single['U'] - single['N']:.0f} instructions")
    print(f"goal <= 5 ms per window; the ESP32 code's positions against the host C (cffi): max "
          f"{np.max(np.abs(device - host)):.2e} m over {len(steps)} steps, {answers[-1].repairs:.0f} repairs")


def xtensa_eskf_state_bytes() -> int:
    from codegen.kernel.hosteskf import load_eskf

    ek = load_eskf()
    return ek.ffi.sizeof("dr_eskf_state")


def xtensa_eskf_config_bytes() -> int:
    from codegen.kernel.hosteskf import load_eskf

    ek = load_eskf()
    return ek.ffi.sizeof("dr_eskf_config")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--board", default=None, help="board YAML (default: the bundled default board)")
    parser.add_argument("--algorithm", choices=("seed", "fused", "eskf"), default=None,
                        help="default: seed and fused")
    parser.add_argument("--scenario", default=None, help="eskf: the simulated vehicle drive (default car); seed and "
                        f"fused: the recording, {' or '.join(RECORDED)} (default replay-walk)")
    parser.add_argument("--duration", type=float, default=120.0, help="eskf: its length, s")
    parser.add_argument("--cov-dt", type=float, default=0.0, help="eskf: s between covariance propagations "
                        "(default: the filter's)")
    parser.add_argument("--nhc-dt", type=float, default=0.0, help="eskf: s between pseudo-measurements (default: "
                        "the filter's)")
    parser.add_argument("--windows", type=int, default=4, help="natmod windows per run (the median is reported)")
    parser.add_argument("--fallback-windows", type=int, default=2, help="fallback windows per run")
    parser.add_argument("--before", default="", help="git revision whose fallback template (plain) to run beside "
                        "today's in the same QEMU sessions (default: none)")
    args = parser.parse_args(argv)
    from codegen.board.loader import load_board
    from codegen.sim.run import require_recordings

    loaded = load_board(args.board)
    if args.algorithm == "eskf":
        eskf_table(loaded, args.scenario or "car", 0, args.duration, args.cov_dt, args.nhc_dt)
        return 0
    scenario = args.scenario or "replay-walk"
    if scenario not in RECORDED:
        parser.error(f"--scenario {scenario}: seed and fused run on a recording, {' or '.join(RECORDED)}")
    require_recordings([scenario])
    for algorithm in ([args.algorithm] if args.algorithm else ["seed", "fused"]):
        device_table(loaded, algorithm, args.windows, args.fallback_windows, args.before, scenario)
    return 0


if __name__ == "__main__":
    sys.exit(main())
