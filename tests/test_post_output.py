"""What `deadreckon post` hands a person and a program: no numpy/scipy warning on the terminal, a report.json that a
strict JSON parser reads and that matches docs/post-report.schema.json (null where a value is unknown, with the
reason), and one time zero (the first GPS epoch, said in UTC) for the report and the plots.

The hard case is the app's own device log from the emulated board on a short walk (yaw held nearly everywhere, the
delay search at its edge): it used to print RuntimeWarnings and write NaN and Infinity into report.json."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from codegen.board.loader import load_board
from codegen.cli import main
from codegen.post import PostOptions, load_log, process
from codegen.post.gapcheck import cut_gap
from codegen.post.outputs import report_text, summary, time_zero
from conftest import require_shared_data, require_tool

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = json.loads((ROOT / "docs" / "post-report.schema.json").read_text())


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"report.json holds {name}, which JSON does not allow")

    return json.loads(text, parse_constant=refuse)


def _nulls(value, path=()):
    """Paths of every null in a JSON value."""
    if value is None:
        yield path
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _nulls(v, path + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _nulls(v, path + (i,))


def check_report(report: dict) -> None:
    jsonschema.validate(report, SCHEMA)
    for path in _nulls(report):
        if path[0] in ("options", "unknown"):
            continue
        assert path[0] in report["unknown"], f"{'.'.join(map(str, path))} is null without a reason"


@pytest.fixture(scope="module")
def emulated_walk_log(tmp_path_factory):
    """The device log the generated app writes on the emulated T-Beam during `simulate --scenario walk --outage 10
    --on-micropython` (seed 0): 29 s, 50 Hz IMU rows, 1 Hz fixes."""
    require_tool("micropython")
    from codegen.sim.onmicropython import run_on_micropython

    work = tmp_path_factory.mktemp("emulated-walk")
    loaded = load_board(ROOT / "board_configs" / "ttgo-tbeam-v1.1.yaml")
    with open(work / "table.txt", "w") as stream:
        run_on_micropython(loaded, "walk", 10.0, [1.0, 5.0, 10.0], seed=0, work=work, stream=stream)
    logs = sorted((work / "fs").glob("dr*.bin"))
    assert logs, "the app wrote no log"
    return logs[0]


@pytest.mark.filterwarnings("error")
def test_device_log_of_the_emulated_walk_gives_clean_output(emulated_walk_log, tmp_path, capsys):
    """A delay search that ends at its edge is reported as unknown (null, with the reason). This log's own search
    once ended there (+488 ms, correlation 0.004); since the gyro frame orients a hand-held device it finds -211 ms
    +- 438 ms within +-1 s, so the edge is reached here by a range (+-50 ms) narrower than the true delay (~-95 ms)."""
    out = tmp_path / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any numpy/scipy warning fails the run here instead of reaching the terminal
        assert main(["post", str(emulated_walk_log), "-o", str(out), "--max-lag", "0.05"]) == 0
    printed = capsys.readouterr()
    assert "Warning" not in printed.err + printed.out
    assert not re.search(r"\b(nan|inf)\b", printed.out, re.I)
    report = _strict((out / "report.json").read_text())
    check_report(report)
    assert report["delay_search_at_edge"] is True and report["delay_sigma_s"] is None
    assert "edge" in report["unknown"]["delay_sigma_s"]
    assert report["angle_sigma_median_deg"][2] is None and "held" in report["unknown"]["angle_sigma_median_deg"]
    assert "delay      " in printed.out and "+- unbounded" in printed.out
    # one zero for the report and the plots: the first GPS epoch, in UTC (the device log's fixes carry UTC)
    log = load_log(emulated_walk_log)
    assert report["first_gps_epoch_s"] == pytest.approx(log.gps.t[0])
    stamp = np.datetime64(report["time_zero_utc"].rstrip("Z"), "ms").astype(float) / 1e3
    assert stamp == pytest.approx(log.gps.t[0], abs=1e-3)
    text = (out / "report.txt").read_text()
    assert f"s after the first GPS epoch, {report['time_zero_utc'][:10]} {report['time_zero_utc'][11:21]} UTC" in text
    for name in ("angles.png", "velocity.png", "trajectory.png"):
        assert (out / name).stat().st_size > 20_000


@pytest.fixture(scope="module")
def walk_with_gap():
    walk = load_log(require_shared_data("gnss-imu-walk"))
    return process(cut_gap(walk, walk.gps.t[0] + 40.0, 10.0), PostOptions(plots=False))


def test_walk_report_is_strict_json_with_its_zero_in_utc(walk_with_gap):
    """The real walk (GPST): the zero is the first epoch less the 18 leap seconds, every value is known, the gap's
    row is there, and report.txt and the plots count from the same zero."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report = _strict(json.dumps(summary(walk_with_gap), allow_nan=False))
        text = report_text(walk_with_gap)
    check_report(report)
    assert report["time_scale"] == "gpst" and report["time_zero_utc"].startswith("2025-08-28T17:30:")
    zero = time_zero(walk_with_gap)
    assert zero.t == walk_with_gap.log.gps.t[0]
    assert zero.utc.timestamp() == pytest.approx(zero.t - 18.0)
    assert f"(s after {zero.label})" in text
    (gap,) = report["gps_gaps"]
    assert gap["start_s"] == pytest.approx(40.0, abs=0.26) and gap["worst_sigma_m"] > 0


def test_a_report_with_unknowns_names_each_reason():
    """strict_json on its own: NaN and infinities anywhere become null, and each top-level key that held one is
    named with its reason."""
    from codegen.post.outputs import strict_json

    unknown: dict[str, str] = {}
    value = strict_json({"a": float("nan"), "b": [1.0, float("inf")], "c": {"d": -np.inf}, "e": np.float32(2.5),
                         "f": np.int64(3)}, {"a": "why a"}, unknown)
    assert value == {"a": None, "b": [1.0, None], "c": {"d": None}, "e": 2.5, "f": 3}
    assert unknown["a"] == "why a" and set(unknown) == {"a", "b", "c"}
    json.dumps(value, allow_nan=False)


def test_the_yaw_band_breaks_where_the_yaw_wraps():
    """A yaw near +-180 whose band edges wrap at other intervals than the yaw itself: the band is broken at the yaw's
    own wraps, so its edges keep the yaw's length (they did not, and the angles plot raised ValueError)."""
    from codegen.post.outputs import _break_wraps

    t = np.arange(6.0)
    yaw = np.array([170.0, 176.0, 179.0, -179.0, -176.0, -170.0])
    x, y, lo, hi = _break_wraps(t, yaw, yaw - 5.0, yaw + 5.0)
    assert len(x) == len(y) == len(lo) == len(hi) == 7
    assert np.isnan(y[3]) and np.isnan(lo[3]) and np.isnan(hi[3])
    assert y[4] == -179.0 and lo[4] == -184.0
