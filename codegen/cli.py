"""The `deadreckon` command: parses arguments and calls library functions (which tests call too).

Every command turns a `UserError` into a located message and exit status 2; no traceback reaches the user.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from codegen import __version__
from codegen.errors import UserError
from codegen.sim import SCENARIOS


def _board_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "board", nargs="?", default=None, help="board YAML (default: the bundled ttgo-tbeam-v1.1)"
    )


def cmd_validate(args: argparse.Namespace) -> int:
    from codegen.board.diagnostics import sort_key
    from codegen.board.loader import load_board_report
    from codegen.deploy.capacity import fit_diagnostics
    from codegen.generate import app_contents, render_tree

    report = load_board_report(args.board)
    if report.loaded is not None and not report.failed():  # the rendered app against the board's filesystem
        fits = fit_diagnostics(report.loaded, app_contents(render_tree(report.loaded)))
        report.diagnostics = sorted(report.diagnostics + fits, key=sort_key)
    report.print(sys.stderr, strict=args.strict)
    if report.failed(strict=args.strict):
        return 2
    print(f"{report.source_name}: ok ({report.board.name})")
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from codegen.board.loader import load_board
    from codegen.generate import generate

    loaded = load_board(args.board, strict=args.strict)
    result = generate(loaded, Path(args.output), force=args.force)
    print(f"generated {len(result.files)} files for {loaded.board.name} in {result.root}")
    if result.kept:
        print(f"kept {len(result.kept)} edited file(s) deadreckon no longer generates: {', '.join(result.kept)}",
              file=sys.stderr)
    return 0


def cmd_boards(args: argparse.Namespace) -> int:
    import shutil

    from codegen.board.loader import bundled_boards
    from codegen.board.listing import board_table

    width = shutil.get_terminal_size((80, 24)).columns
    for line in board_table([(name, description) for name, _, description in bundled_boards()], width):
        print(line)
    return 0


def cmd_schema(args: argparse.Namespace) -> int:
    import json

    from codegen.board.schema import board_json_schema

    print(json.dumps(board_json_schema(), indent=2, sort_keys=True))
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    from codegen.board.loader import load_board
    from codegen.board.schema import resolved_config_lines

    loaded = load_board(args.board)
    for line in resolved_config_lines(loaded):
        print(line)
    return 0


def cmd_build(args: argparse.Namespace) -> int:
    from codegen.deploy.build import build

    result = build(Path(args.out))
    print(f"built {len(result.files)} files into {result.app_dir}" + (f" and {result.image}" if result.image else ""))
    if args.require_native and result.native is None:
        why = result.native_note or f"{result.tree.board.name} runs CircuitPython, which loads no native module"
        print(f"error: --require-native: no native module was built: {why}", file=sys.stderr)
        print("  hint: install the board's compiler (docs/cli.md lists them), or drop --require-native to use the "
              "pure-Python fallback (about 170x slower)", file=sys.stderr)
        return 1
    return 0


def cmd_flash(args: argparse.Namespace) -> int:
    from codegen.deploy.flash import flash

    flash(Path(args.out), args.port, firmware=Path(args.firmware) if args.firmware else None, erase=args.erase,
          stub=not args.no_stub)
    return 0


def cmd_upload(args: argparse.Namespace) -> int:
    if args.drive is not None:
        from codegen.deploy.drive import upload_drive

        upload_drive(Path(args.out), Path(args.drive), force=args.force)
        return 0
    from codegen.deploy.ports import choose_port
    from codegen.deploy.upload import upload

    upload(Path(args.out), choose_port(args.port), force=args.force)
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    from codegen.deploy.monitor import monitor
    from codegen.deploy.ports import choose_port

    monitor(choose_port(args.port), raw=args.raw)
    return 0


def cmd_pull(args: argparse.Namespace) -> int:
    from codegen.deploy.ports import choose_port
    from codegen.deploy.pull import post_pulled, pull

    output = Path(args.output)
    result = pull(choose_port(args.port), output, folder=args.folder, delete=args.delete)
    if args.post:
        posted = post_pulled(output, result.copied)
        if len(posted) < len(result.copied):
            return 1
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from codegen.deploy.run import run_device

    done = run_device(args.board, Path(args.output), port=args.port,
                      firmware=Path(args.firmware) if args.firmware else None,
                      drive=Path(args.drive) if args.drive else None, force=args.force)
    if done.port is not None and not args.no_monitor:
        from codegen.deploy.monitor import monitor

        monitor(done.port, raw=args.raw, wait_s=10.0)
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from codegen.board.loader import load_board
    from codegen.sim.simulate import check_options, simulate

    check_options(args.outage, args.seed, args.step, Path(args.plot) if args.plot else None)
    loaded = load_board(args.board)
    if args.on_micropython:
        if args.data:
            raise UserError("--data is for --scenario replay-walk, which --on-micropython does not run",
                            hint="leave out --on-micropython to replay the recorded walk")
        from codegen.sim.onmicropython import run_on_micropython
        from codegen.sim.simulate import horizons_for

        run_on_micropython(loaded, args.scenario, args.outage, horizons_for(args.outage), seed=args.seed,
                           quality=args.gps)
        return 0
    simulate(loaded.board, args.scenario, args.outage, seed=args.seed, quality=args.gps, step=args.step,
             plot=Path(args.plot) if args.plot else None, methods=args.method,
             data=Path(args.data) if args.data else None)
    return 0


def cmd_post(args: argparse.Namespace) -> int:
    from codegen.post.cli import run_from_args

    return run_from_args(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deadreckon",
        description="Generate, build and flash a GPS + IMU dead-reckoning device from one board YAML.",
    )
    parser.add_argument("--version", action="version", version=f"deadreckon {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("validate", help="check a board YAML; every problem as FILE:LINE:COL")
    _board_arg(p)
    p.add_argument("--strict", action="store_true", help="treat warnings as errors")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("generate", help="render the MicroPython app and native module sources")
    _board_arg(p)
    p.add_argument("-o", "--output", default="out", help="output folder (default: out)")
    p.add_argument("--strict", action="store_true", help="treat warnings as errors")
    p.add_argument("--force", action="store_true", help="replace a generated folder even if files were edited")
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("boards", help="list the bundled boards")
    p.set_defaults(func=cmd_boards)

    p = sub.add_parser("schema", help="print the board YAML's JSON Schema")
    p.set_defaults(func=cmd_schema)

    p = sub.add_parser("config", help="print the resolved board config and where each value came from")
    _board_arg(p)
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("build", help="compile a generated tree for its board: .mpy files and a filesystem image "
                                     "(CircuitPython: checked .py files for its drive)")
    p.add_argument("out", help="the generated tree (from `deadreckon generate`)")
    p.add_argument("--require-native", action="store_true",
                   help="exit 1 when the native module cannot be built (instead of falling back to pure Python)")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("flash", help="write the firmware (optional) and the app's filesystem image with esptool")
    p.add_argument("out", help="the built tree (from `deadreckon build`)")
    p.add_argument("--port", required=True, help="serial port: /dev/ttyUSB0, COM3, or a pyserial URL (socket://...)")
    p.add_argument("--firmware", help="MicroPython .bin to write at the bootloader offset (0x1000 on ESP32)")
    p.add_argument("--erase", action="store_true", help="erase the whole flash first")
    p.add_argument("--no-stub", action="store_true", help="talk to the ROM loader only (slower; for odd adapters)")
    p.set_defaults(func=cmd_flash)

    p = sub.add_parser("upload", help="copy the built app onto a running board: its raw REPL (--port) or a "
                                      "CircuitPython board's CIRCUITPY drive (--drive)")
    p.add_argument("out", help="the built tree (from `deadreckon build`)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--port", help="serial port: /dev/ttyUSB0, COM3, or a pyserial URL (socket://...); default: "
                                      "the one board plugged in, found by its USB id")
    where.add_argument("--drive", help="where the computer mounts a CircuitPython board's CIRCUITPY drive, e.g. "
                                       "/media/$USER/CIRCUITPY")
    p.add_argument("--force", action="store_true", help="send every file, even those already on the board")
    p.set_defaults(func=cmd_upload)

    p = sub.add_parser("run", help="generate, build, flash (--firmware) or upload the app, then monitor the board")
    _board_arg(p)
    p.add_argument("-o", "--output", default="out", help="the generated tree's folder (default: out)")
    p.add_argument("--port", help="serial port or pyserial URL (default: the one board plugged in, found by its "
                                  "USB id)")
    p.add_argument("--firmware", help="MicroPython .bin to flash with the app (a blank board needs it)")
    p.add_argument("--drive", help="a CircuitPython board's CIRCUITPY drive")
    p.add_argument("--force", action="store_true", help="regenerate over edited files; send every file")
    p.add_argument("--no-monitor", action="store_true", help="stop once the app is on the board")
    p.add_argument("--raw", action="store_true", help="monitor the bytes as they come, nothing decoded")
    p.set_defaults(func=cmd_run)

    for name in ("monitor", "logs"):
        p = sub.add_parser(name, help="the board's console decoded into a live status (mode, fix, position, speed, "
                                      "drops, heap, kernel, warnings); Ctrl-] quits" if name == "monitor" else
                           "the same as monitor")
        p.add_argument("--port", help="serial port or pyserial URL (default: the one board plugged in, found by its "
                                      "USB id)")
        p.add_argument("--raw", action="store_true", help="print the bytes as they come, nothing decoded")
        p.set_defaults(func=cmd_monitor)

    p = sub.add_parser("pull", help="copy the board's logs to this computer, each checked by SHA-256; resumes "
                                    "after a drop, never overwrites a different local file")
    p.add_argument("--port", help="serial port or pyserial URL (default: the one board plugged in)")
    p.add_argument("-o", "--output", default="logs", help="local folder (default: logs)")
    p.add_argument("--folder", default="/logs", help="the board's log folder (logging.directory; default /logs)")
    p.add_argument("--delete", action="store_true", help="remove each log from the board once its copy is verified")
    p.add_argument("--post", action="store_true", help="run `deadreckon post` on each log copied (into NAME-post/)")
    p.set_defaults(func=cmd_pull)

    p = sub.add_parser("simulate", help="simulated sensors through the board's pipeline; outage metrics and plots")
    _board_arg(p)
    p.add_argument("--scenario", default="walk", choices=SCENARIOS)
    p.add_argument("--outage", type=float, default=30.0, help="seconds without GPS (default 30)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the scenario and sensor models")
    p.add_argument("--gps", default="open-sky", choices=("open-sky", "poor", "rtk"), help="NEO-6M error profile")
    p.add_argument("--step", type=float, default=5.0, help="seconds between outage starts (default 5)")
    p.add_argument("--method", action="append", help="only this method (repeatable; default: all registered)")
    p.add_argument("--plot", help="write a PNG: truth vs estimate, and error against time since GPS loss")
    p.add_argument("--data", metavar="DIR", help="replay-walk: the recorded walk's folder (imu_1730_sf.csv, "
                   "gnss_1730_sf.pos; default ../shared/data/gnss-imu-walk beside a checkout)")
    p.add_argument("--on-micropython", action="store_true",
                   help="run the generated app on the unix-port MicroPython with emulated peripherals (one outage)")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("post", help="align a logged run to ENU from GPS Doppler; delay, angles, smoothed trajectory")
    from codegen.post.cli import add_arguments as _post_arguments

    _post_arguments(p)
    p.set_defaults(func=cmd_post)

    p = sub.add_parser("completion", help="print a shell completion script: "
                                          "`source <(deadreckon completion bash)` in ~/.bashrc")
    p.add_argument("shell", choices=("bash",))
    p.set_defaults(func=cmd_completion)

    return parser


def cmd_completion(args: argparse.Namespace) -> int:
    from codegen.completion import bash_script

    print(bash_script(build_parser()), end="")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except UserError as error:
        print(error.render(), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `deadreckon schema | head`: the reader left, which is not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as error:  # the file system said no (read-only, full, gone): say where, not a traceback
        where = f": {error.filename}" if error.filename else ""
        print(f"error: {error.strerror or error}{where}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
