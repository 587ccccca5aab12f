"""One simulated run (sensors + GPS + truth) and the outage metrics every method is measured by.

    run = build_run("walk", board, seed=1)                  # or "replay-walk" for the real recording
    result = evaluate(run, horizons=(10, 30, 60))            # every registered method, many outage starts
    print(format_table([result]))

Metrics: for outages starting every `step` seconds (fixed by the seed, never inside the calibration),
the horizontal error |p_est - p_true| at each horizon after GPS loss; median and 90th percentile per method.
The "0 s" column is the error of the last fix itself (where every method starts). The drift variant measures
the displacement since the last fix instead, |(p_est(t) - p_est(t_fix)) - (p(t) - p(t_fix))|, which takes the
fix's own (metre-level, slowly varying) error out. For the push scenario also
the seed's error E = |p_e - p| / |p_e| per push, p_e the true and p the estimated displacement over the push.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import numpy as np

from codegen.sim import SCENARIOS as ALL_SCENARIOS
from codegen.sim import mpu6050, neo6m, trajectory
from codegen.sim.methods import registered_methods

SCENARIOS = ALL_SCENARIOS
DEFAULT_HORIZONS = (10.0, 30.0, 60.0)
# Seeds: algorithms are tuned on TUNING_SEEDS and judged on REPORT_SEEDS, never the other way round. The replayed
# real walk is one recording (its degradation seeds only vary the sensor errors): it was used for tuning, so its
# figures are in-sample and labelled so. So is the real car's since the speed/bias filter's noises were chosen on
# its tuning degradations (100-103) beside the simulated vehicles' tuning seeds (docs/fused.md).
TUNING_SEEDS = range(100, 200)
REPORT_SEEDS = range(0, 30)
# car-comma2k19 (codegen.sim.comma): 60 s, too short for 60 s outages, so not among SCENARIOS; build_run takes it
REAL_CAR = "replay-car"
IN_SAMPLE = {"replay-walk", REAL_CAR}
REAL_CAR_ROWS = "car-comma"  # the real car's rows are named "car-comma <outage length> s"


def in_sample(scenario: str) -> bool:
    """Whether a result row's scenario was used for tuning (the real car's rows by their prefix)."""
    return scenario in IN_SAMPLE or (REAL_CAR in IN_SAMPLE and scenario.startswith(REAL_CAR_ROWS))


@dataclass
class RunData:
    """Everything a method may see (IMU stream, GPS fixes) plus the truth it is judged against."""

    scenario: str
    board: object  # codegen.board.model.Board
    seed: int
    t_us: np.ndarray  # (N,) int64
    counts: np.ndarray  # (N, 6) int16, sensor frame
    gps: neo6m.GpsTrack
    truth: object  # .at(times) -> (K, 3) ENU m; .duration; .rest_s
    events: dict = field(default_factory=dict)
    cache: dict = field(default_factory=dict)  # per-run memo for methods (GPS-independent work only)

    @property
    def duration(self) -> float:
        return float(min(self.t_us[-1] * 1e-6, self.truth.duration))

    def trusted(self, times) -> np.ndarray:
        check = getattr(self.truth, "trusted", None)
        return np.ones(np.shape(times), dtype=bool) if check is None else check(times)


def build_run(scenario: str, board, seed: int = 0, quality: str = "open-sky", duration: float | None = None,
              errors: mpu6050.MpuErrors | None = None, walk_dir=None, car_dir=None) -> RunData:
    """Simulate (or replay) one run on `board`. `quality`: the GPS profile of codegen.sim.neo6m.QUALITY (the real
    car, REAL_CAR, keeps its own u-blox fixes: no profile)."""
    if scenario == "replay-walk":
        from codegen.sim import replay

        t_s, accel_g, gyro, truth = replay.load_walk(walk_dir)
        t_us, counts = mpu6050.degrade_recording(t_s, accel_g, gyro, board, seed=seed, errors=errors)
        gps = neo6m.simulate_gps(truth, seed=seed + 1000, quality=quality, rate_hz=board.gps.rate_hz,
                                 origin=truth.origin, times=truth.epochs(board.gps.rate_hz))
        return RunData(scenario, board, seed, t_us, counts, gps, truth)
    if scenario == REAL_CAR:
        return _replay_car(board, seed, errors, car_dir)
    if scenario not in trajectory.SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    traj = trajectory.make_scenario(scenario, seed=seed, duration=duration)
    t_us, counts = mpu6050.simulate_imu(traj, board, seed=seed, errors=errors)
    gps = neo6m.simulate_gps(traj, seed=seed + 1000, quality=quality, rate_hz=board.gps.rate_hz)
    return RunData(scenario, board, seed, t_us, counts, gps, traj, dict(traj.events))


def _replay_car(board, seed: int, errors, car_dir) -> RunData:
    """The real car (codegen.sim.comma): its IMU read at the board's rate in the board's frame and degraded to an
    MPU-6050 (the recording's own noise kept, the MPU-6050's whole density added: its phone-grade IMU's is not
    known), its u-blox fixes at the board's GPS rate, the pose as truth. The device calibrates on the first
    calibration_s of driving (the segment never stands)."""
    from codegen.sim import comma

    car = comma.load_car(car_dir)
    t_s, accel_g, gyro = comma.device_imu(car, board.imu.sample_rate_hz)
    t_us, counts = mpu6050.degrade_recording(t_s, accel_g, gyro, board, seed=seed, errors=errors,
                                             already_ug_rthz=0.0)
    return RunData(REAL_CAR, board, seed, t_us, counts, comma.device_fixes(car, board.gps.rate_hz), car.truth)


def missing_recordings(scenarios) -> str | None:
    """None if every recording that `scenarios` replay (replay-walk, REAL_CAR) is where build_run reads it (beside
    the checkout, ../shared/data), else what is missing, named, and where the recordings come from: for a
    benchmark to say before its first job rather than as a traceback minutes into a run."""
    from codegen.sim import comma, replay

    wanted = {"replay-walk": (replay.default_walk_dir(), (replay.IMU_FILE, replay.POS_FILE)),
              REAL_CAR: (comma.default_car_dir(), comma.CAR_FILES)}
    lines = []
    for scenario in dict.fromkeys(scenarios):
        if scenario not in wanted:
            continue
        folder, files = wanted[scenario]
        absent = [name for name in files if not (folder / name).is_file()]
        if absent:
            what = f"the folder {folder} is missing" if not folder.is_dir() else (
                f"{folder} lacks {', '.join(absent[:3])}{' ...' if len(absent) > 3 else ''}")
            lines.append(f"{scenario}: {what}")
    if not lines:
        return None
    return ("the recorded runs are not where this checkout reads them:\n  " + "\n  ".join(lines) + "\nhint: a "
            "checkout reads them from ../shared/data (shared/data/README.md says where each comes from); from a git "
            "worktree elsewhere, link shared/ beside it, or leave those scenarios out")


def require_recordings(scenarios) -> None:
    """Stop a benchmark (SystemExit, the message of missing_recordings) unless its recorded runs are all there."""
    missing = missing_recordings(scenarios)
    if missing:
        raise SystemExit(missing)


def outage_starts(run: RunData, longest: float, step: float = 5.0) -> np.ndarray:
    """Outage start times: after calibration and a few fixes, every `step` s, leaving `longest` s to run.
    Starts fall half-way between 1 Hz fixes, so the last fix is 0.5 s old when the GPS goes."""
    first = max(run.board.algorithm.calibration_s + 5.0, 10.0) + 0.5
    last = run.duration - longest
    if last < first:
        raise ValueError(f"{run.scenario}: a run of {run.duration:.0f} s is too short for {longest:.0f} s outages")
    return np.arange(first, last + 1e-9, step)


@dataclass
class Result:
    scenario: str
    horizons: tuple[float, ...]
    errors: dict[str, np.ndarray]  # method -> (S, H+1) m: column 0 is at the moment of loss, NaN where untrusted
    drift: dict[str, np.ndarray] = field(default_factory=dict)  # method -> (S, H+1) m: displacement error
    push_e: dict[str, np.ndarray] = field(default_factory=dict)  # method -> (P,) seed error E per push
    starts: np.ndarray | None = None
    seeds: int = 1
    seed_of_row: np.ndarray | None = None  # (S,) the run (seed) each outage row came from: the bootstrap's clusters

    def merge(self, other: "Result") -> "Result":
        errors = {m: np.vstack([self.errors[m], other.errors[m]]) for m in self.errors}
        drift = {m: np.vstack([self.drift[m], other.drift[m]]) for m in self.drift}
        push_e = {m: np.concatenate([self.push_e.get(m, []), other.push_e.get(m, [])]) for m in self.errors}
        rows = np.concatenate([self.row_seeds(), other.row_seeds()])
        return Result(self.scenario, self.horizons, errors, drift, push_e, None, self.seeds + other.seeds, rows)

    def row_seeds(self) -> np.ndarray:
        rows = len(next(iter(self.errors.values())))
        return np.zeros(rows, dtype=int) if self.seed_of_row is None else self.seed_of_row


def evaluate(run: RunData, horizons=DEFAULT_HORIZONS, methods=None, step: float = 5.0) -> Result:
    """Run every method on every outage start of `run`; errors against truth at each horizon."""
    methods = registered_methods() if methods is None else methods
    horizons = tuple(float(h) for h in horizons)
    starts = outage_starts(run, max(horizons), step)
    fix_idx = run.gps.last_valid_before(starts)
    t_fix = run.gps.t[fix_idx]
    times = np.hstack([t_fix[:, None], starts[:, None] + np.array(horizons)[None, :]])
    truth = run.truth.at(times)[..., :2]
    ok = run.trusted(times)
    errors, drift = {}, {}
    for name, fn in methods.items():
        est = fn(run, starts, times)
        err = np.linalg.norm(est - truth, axis=-1)
        errors[name] = np.where(ok, err, np.nan)
        moved = np.linalg.norm((est - est[:, :1]) - (truth - truth[:, :1]), axis=-1)
        drift[name] = np.where(ok & ok[:, :1], moved, np.nan)
    result = Result(run.scenario, horizons, errors, drift, starts=starts,
                    seed_of_row=np.full(len(starts), run.seed, dtype=int))
    pushes = run.events.get("pushes")
    if pushes:
        p_start = np.array([p[0] for p in pushes]) - 0.5
        p_times = np.stack([p_start, np.array([p[1] for p in pushes]) + 0.5], axis=-1)
        p_true = run.truth.at(p_times)[..., :2]
        p_e = p_true[:, 1] - p_true[:, 0]
        for name, fn in methods.items():
            est = fn(run, p_start, p_times)
            d = est[:, 1] - est[:, 0]
            result.push_e[name] = np.linalg.norm(d - p_e, axis=-1) / np.linalg.norm(p_e, axis=-1)
    return result


def format_table(results: list[Result], file=None, drift: bool = False) -> str:
    """The metrics table: one row per scenario x method; median / 90th percentile in metres per horizon.
    drift=True tabulates the displacement error since the last fix instead (the fix's own error taken out)."""
    lines = []
    horizons = results[0].horizons
    head = f"{'scenario':13s} {'method':16s} {'outages':>7s} {'0 s':>6s}"
    for h in horizons:
        head += f" {f'{h:g} s med':>10s} {'p90':>7s}"
    if any(res.push_e for res in results):
        head += f"  {'push E med':>10s} {'E<0.1':>6s}"
    lines.append(head)
    lines.append("-" * len(head))
    for res in results:
        for name, err in (res.drift if drift else res.errors).items():
            n = int(np.sum(~np.isnan(err[:, -1])))
            row = f"{res.scenario:13s} {name:16s} {n:7d} {np.nanmedian(err[:, 0]):6.1f}"
            for j in range(1, len(horizons) + 1):
                row += f" {np.nanmedian(err[:, j]):10.1f} {np.nanpercentile(err[:, j], 90):7.1f}"
            e = res.push_e.get(name)
            if e is not None and len(e):
                row += f"  {np.median(e):10.2f} {np.mean(e < 0.1):6.0%}"
            lines.append(row)
    text = "\n".join(lines)
    if file is not None:
        print(text, file=file)
    return text


def bootstrap_interval(err: np.ndarray, rows: np.ndarray, q: float, resamples: int = 1000, level: float = 0.95,
                       seed: int = 0) -> tuple[float, float, float]:
    """(estimate, low, high): the q-th percentile of `err` (NaN ignored) and its bootstrap interval, resampling
    whole runs (the values of one seed are correlated: one road, one device, one fix error), not single outages."""
    keep = ~np.isnan(err)
    err, rows = err[keep], rows[keep]
    estimate = float(np.percentile(err, q))
    clusters = np.unique(rows)
    if len(clusters) < 2:
        return estimate, np.nan, np.nan
    groups = [err[rows == c] for c in clusters]
    rng = np.random.default_rng(seed)
    picks = rng.integers(len(groups), size=(resamples, len(groups)))
    stats = np.array([np.percentile(np.concatenate([groups[i] for i in pick]), q) for pick in picks])
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(stats, [tail, 100 - tail])
    return estimate, float(low), float(high)


def bootstrap_mean(err: np.ndarray, rows: np.ndarray, resamples: int = 1000, level: float = 0.95,
                   seed: int = 0) -> tuple[float, float, float]:
    """(mean, low, high): the mean of `err` (NaN ignored) and its bootstrap interval, whole runs resampled."""
    keep = ~np.isnan(err)
    err, rows = err[keep], rows[keep]
    clusters = np.unique(rows)
    if len(clusters) < 2:
        return float(np.mean(err)), np.nan, np.nan
    sums = np.array([err[rows == c].sum() for c in clusters])
    counts = np.array([np.sum(rows == c) for c in clusters])
    picks = np.random.default_rng(seed).integers(len(clusters), size=(resamples, len(clusters)))
    stats = sums[picks].sum(axis=1) / counts[picks].sum(axis=1)
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(stats, [tail, 100 - tail])
    return float(np.mean(err)), float(low), float(high)


def format_table_ci(results: list[Result], resamples: int = 1000, file=None) -> str:
    """The metrics table with 95 % bootstrap intervals (runs resampled): per method a median row, a 90th
    percentile row and a mean row, in metres, each value with its [low-high] interval, and the worst outage (its
    seed in brackets). In-sample scenarios (tuned on) are marked."""
    horizons = results[0].horizons
    cell = 24
    head = f"{'scenario':16s} {'method':16s} {'runs':>4s} {'outages':>7s} {'':>6s}"
    head += "".join(f" {f'{h:g} s [95%]':>{cell}s}" for h in horizons)
    lines = [head, "-" * len(head)]
    for res in results:
        rows = res.row_seeds()
        label = res.scenario + (" *" if in_sample(res.scenario) else "")
        for name, err in res.errors.items():
            n = int(np.sum(~np.isnan(err[:, -1])))
            for q, stat in ((50, "median"), (90, "p90"), (None, "mean"), (100, "worst")):
                row = (f"{label:16s} {name:16s} {len(np.unique(rows)):4d} {n:7d} {stat:>6s}" if q == 50
                       else f"{'':16s} {'':16s} {'':4s} {'':7s} {stat:>6s}")
                for j in range(1, len(horizons) + 1):
                    if q == 100:
                        worst = int(np.nanargmax(err[:, j]))
                        row += f" {f'{err[worst, j]:.1f} (seed {rows[worst]})':>{cell}s}"
                        continue
                    est, low, high = (bootstrap_mean(err[:, j], rows, resamples) if q is None
                                      else bootstrap_interval(err[:, j], rows, q, resamples))
                    row += f" {f'{est:.1f} [{low:.1f}-{high:.1f}]':>{cell}s}"
                lines.append(row)
    if any(in_sample(res.scenario) for res in results):
        lines.append("* in-sample: the recording was used to tune the algorithm")
    text = "\n".join(lines)
    if file is not None:
        print(text, file=file)
    return text


def progress(done: int, total: int, label: str, stream=sys.stderr) -> None:
    """A one-line progress bar on stderr (only on a terminal)."""
    if not getattr(stream, "isatty", lambda: False)():
        return
    width = 30
    filled = int(width * done / max(total, 1))
    stream.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} {label:30s}")
    if done >= total:
        stream.write("\n")
    stream.flush()
