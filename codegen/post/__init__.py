"""`deadreckon post`: accelerations + GPS-Doppler velocities -> orientation, delay, smoothed trajectory.

    load_log(LOG, gps=None) -> PostLog          readers: CSV pair, RTKLIB recording folder, device log
    process(log, PostOptions()) -> PostResult   the method: delay, LM orientation per interval, Slerp, KF + RTS
    run_post(LOG, OUTDIR, gps=None, ...)        both, plus trajectory CSV/GPX, angles, report, plots
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from codegen.post.loader import load_log
from codegen.post.pipeline import PostOptions, PostResult, check_log, process

__all__ = ["PostOptions", "PostResult", "load_log", "process", "run_post"]


def run_post(log_path: Path, out_dir: Path, gps: Optional[Path] = None, options: PostOptions = PostOptions(),
             progress=None) -> tuple[PostResult, dict[str, Path]]:
    from codegen.post.outdir import check_output_folder
    from codegen.post.outputs import write_outputs

    inputs = [Path(log_path)] + ([Path(gps)] if gps is not None else [])
    check_output_folder(Path(out_dir), inputs)  # before the work: a refusal costs nothing
    log = load_log(Path(log_path), Path(gps) if gps is not None else None)
    check_log(log, where=" and ".join(map(str, inputs)))  # the message names the files, not only the run
    result = process(log, options, progress=progress)
    files = write_outputs(result, Path(out_dir), plots_too=options.plots)
    return result, files
