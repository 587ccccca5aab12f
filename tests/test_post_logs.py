"""Readers of `deadreckon post`: bad logs give located errors (exit 2, no traceback); RTKLIB .tag/.pos formats."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from codegen.cli import main
from codegen.errors import UserError
from codegen.post import load_log
from codegen.post.rtklib import read_pos, read_tag
from codegen.post.synthetic import Scenario, make_run, write_csv_pair


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    log, _ = make_run(Scenario(duration=40.0, seed=3))
    folder = tmp_path_factory.mktemp("pair")
    imu, gps = write_csv_pair(log, folder)
    return imu.read_text(), gps.read_text()


def _post(capsys, *argv):
    code = main(["post", *map(str, argv), "--no-plots"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def _write(tmp_path, imu_text, gps_text):
    imu, gps = tmp_path / "imu.csv", tmp_path / "gps.csv"
    imu.write_text(imu_text)
    gps.write_text(gps_text)
    return imu, gps


def test_good_pair_runs(tmp_path, capsys, pair):
    imu, gps = _write(tmp_path, *pair)
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 0, err
    assert (tmp_path / "out" / "trajectory.gpx").exists()


def test_empty_imu_log(tmp_path, capsys, pair):
    imu, gps = _write(tmp_path, "", pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "imu.csv:1:1: error: IMU log" in err and "is empty" in err


def test_empty_gps_log(tmp_path, capsys, pair):
    imu, gps = _write(tmp_path, pair[0], "t,lat,lon,sog,cog,climb\n")
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "GPS epoch" in err


def test_truncated_in_the_header(tmp_path, capsys, pair):
    imu, gps = _write(tmp_path, "t,ax,a", pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "imu.csv:1:1" in err and "lacks column" in err


def test_truncated_last_line_is_dropped_with_a_note(tmp_path, capsys, pair):
    text = pair[0]
    cut = text[: text.rstrip("\n").rfind("\n") + 8]  # the last line cut after a few characters
    imu, gps = _write(tmp_path, cut, pair[1])
    code = main(["post", str(imu), "--gps", str(gps), "-o", str(tmp_path / "out"), "--no-plots"])
    out = capsys.readouterr().out
    assert code == 0
    assert "dropped a truncated last line" in out


def test_truncated_after_a_few_samples(tmp_path, capsys, pair):
    imu, gps = _write(tmp_path, "\n".join(pair[0].split("\n")[:6]), pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "IMU sample" in err or "share" in err


def test_damaged_line_in_the_middle(tmp_path, capsys, pair):
    lines = pair[0].split("\n")
    lines[100] = lines[100][:5]
    imu, gps = _write(tmp_path, "\n".join(lines), pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "imu.csv:101:" in err and "fields" in err


def test_not_a_number(tmp_path, capsys, pair):
    lines = pair[0].split("\n")
    fields = lines[50].split(",")
    fields[2] = "0.0x1"
    lines[50] = ",".join(fields)
    imu, gps = _write(tmp_path, "\n".join(lines), pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    column = len(fields[0]) + len(fields[1]) + 3
    assert f"imu.csv:51:{column}: error: IMU log: ay is '0.0x1', not a number" in err


def test_time_going_back(tmp_path, capsys, pair):
    lines = pair[0].split("\n")
    lines[200], lines[201] = lines[201], lines[200]
    imu, gps = _write(tmp_path, "\n".join(lines), pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "imu.csv:202:1" in err and "goes back in time" in err


def test_repeated_imu_time(tmp_path, capsys, pair):
    lines = pair[0].split("\n")
    lines[300] = lines[299]
    imu, gps = _write(tmp_path, "\n".join(lines), pair[1])
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "imu.csv:301:1" in err and "repeats" in err


def test_gps_time_going_back(tmp_path, capsys, pair):
    lines = pair[1].split("\n")
    lines[10], lines[11] = lines[11], lines[10]
    imu, gps = _write(tmp_path, pair[0], "\n".join(lines))
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "gps.csv:12:1" in err


def test_duplicate_gps_epochs_are_averaged(tmp_path, pair):
    lines = pair[1].rstrip("\n").split("\n")
    lines.insert(5, lines[5])
    imu, gps = _write(tmp_path, pair[0], "\n".join(lines) + "\n")
    log = load_log(imu, gps)
    assert any("duplicate" in note for note in log.notes)
    assert np.all(np.diff(log.gps.t) > 0)


def test_gps_without_imu(tmp_path, capsys, pair):
    _, gps = _write(tmp_path, pair[0], pair[1])
    code, err = _post(capsys, gps, "-o", tmp_path / "out")
    assert code == 2
    assert "GPS log without IMU data" in err


def test_imu_without_gps(tmp_path, capsys, pair):
    imu, _ = _write(tmp_path, pair[0], pair[1])
    code, err = _post(capsys, imu, "-o", tmp_path / "out")
    assert code == 2
    assert "--gps" in err


def test_logs_on_different_time_axes(tmp_path, capsys, pair):
    lines = pair[1].split("\n")
    shifted = [lines[0]] + [",".join([f"{float(l.split(',')[0]) + 1000:.3f}"] + l.split(",")[1:]) for l in lines[1:] if l]
    imu, gps = _write(tmp_path, pair[0], "\n".join(shifted) + "\n")
    code, err = _post(capsys, imu, "--gps", gps, "-o", tmp_path / "out")
    assert code == 2
    assert "same time axis" in err


def test_missing_file(tmp_path, capsys):
    code, err = _post(capsys, tmp_path / "nope.csv", "-o", tmp_path / "out")
    assert code == 2 and "does not exist" in err


def test_folder_with_gps_solution_but_no_imu(tmp_path, capsys):
    (tmp_path / "run.pos").write_text(
        "%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  sdne(m)"
        "  sdeu(m)  sdun(m) age(s)  ratio  vn(m/s)  ve(m/s)  vu(m/s)  sdvn  sdve  sdvu  sdvne  sdveu  sdvun\n"
        "2025/08/28 17:30:39.749 40.0966916 -105.1471665 1601.435 1 25 0.01 0.01 0.01 0 0 0 0 0 0.001 -0.002 0.027"
        " 0.05 0.05 0.05 0 0 0\n")
    code, err = _post(capsys, tmp_path, "-o", tmp_path / "out")
    assert code == 2 and "no IMU log" in err


def test_pos_without_velocities_is_refused(tmp_path):
    path = tmp_path / "novel.pos"
    path.write_text("%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns\n"
                    "2025/08/28 17:30:39.749 40.0966916 -105.1471665 1601.435 1 25\n")
    with pytest.raises(UserError, match="vn, ve, vu"):
        read_pos(path)


def _tag_bytes(start_time: int, frac: float, records, size_fpos=4) -> bytes:
    header = b"TIMETAG RTKLIB demo5".ljust(60, b"\0") + struct.pack("<I", 123456)
    body = b"".join(struct.pack("<I" + ("I" if size_fpos == 4 else "Q"), t, f) for t, f in records)
    return header + struct.pack("<Id", start_time, frac) + body


@pytest.mark.parametrize("size_fpos", [4, 8])
def test_tag_layout(tmp_path, size_fpos):
    path = tmp_path / "x.tag"
    path.write_bytes(_tag_bytes(1756402240, 0.5, [(10, 100), (25, 180), (40, 260)], size_fpos))
    tag = read_tag(path)
    assert tag.tick_f == 123456 and tag.start == pytest.approx(1756402240.5)
    assert tag.tick.tolist() == [10, 25, 40] and tag.fpos.tolist() == [100, 180, 260]
    # a line ending at byte 150 arrived with the second record
    assert tag.receive_time(np.array([150]))[0] == pytest.approx(1756402240.5 + 0.025)


def test_not_a_tag_file(tmp_path):
    path = tmp_path / "x.tag"
    path.write_bytes(b"hello")
    with pytest.raises(UserError, match="not an RTKLIB time-tag"):
        read_tag(path)


def test_gps_gap_is_flagged_and_bridged():
    from codegen.post import PostOptions, process

    log, truth = make_run(Scenario(duration=150.0, seed=4))
    keep = (log.gps.t < 60.0) | (log.gps.t > 80.0)
    log.gps = log.gps.select(keep)
    result = process(log, PostOptions())
    gap_flags = [k for k, f in enumerate(result.orientation.flags) if "gps-gap" in f]
    assert len(gap_flags) == 1
    # the stretches GPS covers are smoothed on their own: the gap does not spoil them
    assert result.velocity_residual_rms < 0.15
    # the gap itself is bridged (dead reckoning on the interpolated orientation: no gyro, so only a rough path)
    inside = (result.track.t > 60.5) & (result.track.t < 79.5)
    assert inside.sum() >= 180 and np.all(np.isfinite(result.track.pos[inside]))
    assert np.all(np.diff(result.track.t) > 0)
