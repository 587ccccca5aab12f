"""`deadreckon post` on the real walk recording (../shared/data/gnss-imu-walk): RTKLIB .pos + raw IMU CSV + .tag."""

from __future__ import annotations

import json

import numpy as np
import pytest

from codegen.cli import main
from codegen.post import load_log
from codegen.post.rtklib import read_sf_imu, read_tag
from conftest import require_shared_data


@pytest.fixture(scope="module")
def walk():
    return require_shared_data("gnss-imu-walk")


def test_tag_file_header_and_records(walk):
    tag = read_tag(walk / "imu_1730.csv.tag")
    assert tag.version.startswith("TIMETAG RTKLIB")
    assert tag.start == pytest.approx(1756402240.961, abs=1e-3)
    assert len(tag.tick) == (((walk / "imu_1730.csv.tag").stat().st_size - 76) // 8)
    assert tag.tick[-1] / 1000 == pytest.approx(134.3, abs=0.5)  # the 134 s walk


def test_imu_on_gps_time_matches_the_authors_stamping(walk):
    """Our tag-based stamps against the recording's own GPS-stamped copy (imu_1730_sf.csv): same samples, within
    a receive-latency's worth of each other."""
    log = load_log(walk)
    sf = read_sf_imu(walk / "imu_1730_sf.csv")
    assert len(log.imu) == len(sf)
    for axis in range(3):  # the same samples (sf is low-pass filtered, so compare shapes)
        assert np.corrcoef(log.imu.acc[:, axis], sf.acc[:, axis])[0, 1] > 0.9
    assert np.abs(log.imu.t - sf.t).max() < 0.03
    assert log.time_scale == "gpst"
    assert np.all(np.isin(log.gps.quality, [1, 2]))


def test_walk_end_to_end(walk, tmp_path, capsys):
    out = tmp_path / "walk"
    assert main(["post", str(walk), "-o", str(out)]) == 0
    printed = capsys.readouterr()
    assert "post: " in printed.err  # progress
    summary = json.loads((out / "report.json").read_text())
    for name in ("trajectory.csv", "trajectory.gpx", "angles.csv", "report.txt", "angles.png", "velocity.png",
                 "trajectory.png"):
        assert (out / name).stat().st_size > 0
    assert abs(summary["delay_s"]) < 0.5 and summary["delay_correlation"] > 0.5
    assert summary["velocity_residual_rms_mps"] < 0.15
    assert summary["intervals_solved"] >= 0.95 * summary["intervals"]
    # the IMU reads about +1 g on z at rest: a device held roughly level
    roll, pitch, _ = summary["angles_median_deg"]
    assert abs(roll) < 15 and abs(pitch) < 15
    gpx = (out / "trajectory.gpx").read_text()
    assert "<time>2025-08-28T17:30:" in gpx  # GPST - 18 s leap seconds = UTC


def test_gps_option_takes_an_rtklib_solution(walk, tmp_path):
    """`post IMU.csv --gps run.pos` reads what the folder form reads: the raw IMU CSV through its .tag, the .pos
    epochs on GPST (it was refused before, with a complaint about the IMU CSV's missing header)."""
    folder = load_log(walk)
    pair = load_log(walk / "imu_1730.csv", gps=walk / "gnss_1730_sf.pos")
    assert pair.time_scale == "gpst"
    assert np.array_equal(pair.imu.t, folder.imu.t) and np.array_equal(pair.imu.acc, folder.imu.acc)
    assert np.array_equal(pair.gps.t, folder.gps.t) and np.array_equal(pair.gps.vel, folder.gps.vel)
    # an IMU CSV of our own format (t,ax,ay,az in g on GPST) goes with a .pos too
    imu = tmp_path / "imu.csv"
    rows = ["t,ax,ay,az"] + [f"{t:.4f},{a[0] / 9.80665:.5f},{a[1] / 9.80665:.5f},{a[2] / 9.80665:.5f}"
                             for t, a in zip(folder.imu.t[:2000], folder.imu.acc[:2000])]
    imu.write_text("\n".join(rows) + "\n")
    mine = load_log(imu, gps=walk / "gnss_1730_sf.pos")
    assert mine.time_scale == "gpst" and len(mine.imu) == 2000
    assert np.allclose(mine.imu.t, folder.imu.t[:2000], atol=1e-4)
