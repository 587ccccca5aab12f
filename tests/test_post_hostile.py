"""`deadreckon post` against hostile and degenerate input, as a user runs it.

Every case runs the real CLI (`python -m codegen post ...`) in a subprocess and must end within a time bound with a
clear message on stderr, exit status 2 and no traceback, and must leave everything outside the output folder as it
was (the whole working folder is hashed before and after, the output folder aside).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from codegen.post.synthetic import Scenario, make_run, write_csv_pair

ROOT = Path(__file__).resolve().parent.parent
TIME_BOUND = 120.0  # s for one refused run (a refusal comes before the work; the degenerate logs are 40 s long)


def _tree_hashes(folder: Path, skip: Path | None = None) -> dict[str, str]:
    out = {}
    for path in sorted(folder.rglob("*")):
        if skip is not None and (path == skip or skip in path.parents):
            continue
        key = str(path.relative_to(folder))
        if path.is_symlink():
            out[key] = "link:" + os.readlink(path)
        elif path.is_file():
            out[key] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[key] = "dir"
    return out


def refused(work: Path, *args, out: Path | None = None, expect: str) -> str:
    """Run `deadreckon post ARGS` in `work`; assert exit 2, `expect` in stderr, no traceback, nothing outside `out`
    changed; return stderr."""
    before = _tree_hashes(work, skip=out)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-m", "codegen", "post", *map(str, args)], cwd=work, env=env,
                          capture_output=True, text=True, timeout=TIME_BOUND, stdin=subprocess.DEVNULL)
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
    assert expect in proc.stderr, proc.stderr[-2000:]
    assert "error:" in proc.stderr
    assert _tree_hashes(work, skip=out) == before
    return proc.stderr


@pytest.fixture(scope="module")
def pair_text(tmp_path_factory):
    log, _ = make_run(Scenario(duration=40.0, seed=3))
    folder = tmp_path_factory.mktemp("pair")
    imu, gps = write_csv_pair(log, folder)
    return imu.read_text(), gps.read_text()


@pytest.fixture
def work(tmp_path, pair_text):
    (tmp_path / "imu.csv").write_text(pair_text[0])
    (tmp_path / "gps.csv").write_text(pair_text[1])
    return tmp_path


def _gps_with(work: Path, edit) -> Path:
    lines = (work / "gps.csv").read_text().splitlines()
    header, rows = lines[0], [line.split(",") for line in lines[1:]]
    edit(rows)
    path = work / "gps_edited.csv"
    path.write_text("\n".join([header] + [",".join(r) for r in rows]) + "\n")
    return path


# --------------------------------------------------------------------------------------- the output folder


def test_output_at_an_existing_file(work):
    (work / "results").write_text("my notes\n")
    refused(work, "imu.csv", "--gps", "gps.csv", "-o", "results", expect="is an existing file, not a folder")


def test_output_at_the_inputs_folder_holding_the_users_report(work):
    (work / "report.txt").write_text("my own report, not post's\n")
    err = refused(work, "imu.csv", "--gps", "gps.csv", "-o", ".", expect="report.txt")
    assert "did not write" in err


def test_output_folder_where_an_input_is_named_like_an_output(work):
    (work / "imu.csv").rename(work / "trajectory.csv")
    refused(work, "trajectory.csv", "--gps", "gps.csv", "-o", ".", expect="is an input of this run")


def test_output_file_that_is_a_link_out_of_the_folder(work, tmp_path_factory):
    outside = tmp_path_factory.mktemp("outside") / "precious.txt"
    outside.write_text("not yours\n")
    (work / "out").mkdir()
    (work / "out" / "trajectory.csv").symlink_to(outside)
    refused(work, "imu.csv", "--gps", "gps.csv", "-o", "out", expect="trajectory.csv")
    assert outside.read_text() == "not yours\n"


def test_a_foreign_manifest_does_not_make_files_ours(work):
    out = work / "out"
    out.mkdir()
    (out / "post-manifest.json").write_text('{"files": {"report.txt": "0"}}\n')
    (out / "report.txt").write_text("mine\n")
    refused(work, "imu.csv", "--gps", "gps.csv", "-o", "out", expect="did not write")


def test_a_report_edited_after_the_run_is_not_replaced(work):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    first = subprocess.run([sys.executable, "-m", "codegen", "post", "imu.csv", "--gps", "gps.csv", "-o", "out",
                            "--no-plots"], cwd=work, env=env, capture_output=True, text=True, timeout=TIME_BOUND)
    assert first.returncode == 0, first.stderr[-2000:]
    again = subprocess.run([sys.executable, "-m", "codegen", "post", "imu.csv", "--gps", "gps.csv", "-o", "out",
                            "--no-plots"], cwd=work, env=env, capture_output=True, text=True, timeout=TIME_BOUND)
    assert again.returncode == 0, again.stderr[-2000:]  # its own files it replaces
    with open(work / "out" / "report.txt", "a") as f:
        f.write("my remarks\n")
    refused(work, "imu.csv", "--gps", "gps.csv", "-o", "out", expect="report.txt")
    assert (work / "out" / "report.txt").read_text().endswith("my remarks\n")


# ------------------------------------------------------------------------------------------- degenerate logs


def test_gps_velocity_that_never_changes(work):
    def constant(rows):
        for r in rows:
            r[3], r[4], r[5] = "12.5000", "45.0000", "0.0000"

    refused(work, "imu.csv", "--gps", _gps_with(work, constant), "-o", "out", out=work / "out",
            expect="it never changes")


def test_standing_still(work):
    def still(rows):
        for r in rows:
            r[3], r[4], r[5] = "0.0000", "0.0000", "0.0000"

    refused(work, "imu.csv", "--gps", _gps_with(work, still), "-o", "out", out=work / "out",
            expect="the device stood still")


def test_nmea_log_whose_fixes_are_all_invalid(work):
    from test_post_gpslogs import nmea_sentence

    lines = []
    for s in range(30):
        clock = f"1200{s:02d}.00"
        lines.append(nmea_sentence(f"GPRMC,{clock},V,,,,,,,140326,,,N"))
        lines.append(nmea_sentence(f"GPGGA,{clock},,,,,0,00,99.9,,M,,M,,"))
    (work / "nofix.nmea").write_text("\n".join(lines) + "\n")
    refused(work, "imu.csv", "--gps", "nofix.nmea", "-o", "out", out=work / "out",
            expect="none of the 30 epochs has a valid fix")


def test_gps_log_with_no_epochs(work):
    (work / "empty_gps.csv").write_text("t,lat,lon,sog,cog,climb\n")
    refused(work, "imu.csv", "--gps", "empty_gps.csv", "-o", "out", out=work / "out", expect="GPS epoch")


# ---------------------------------------------------------------------------------------------------- ranges


def test_latitude_999(work):
    def far_north(rows):
        rows[7][1] = "999.0"

    err = refused(work, "imu.csv", "--gps", _gps_with(work, far_north), "-o", "out", out=work / "out",
                  expect="lat is 999 deg, outside -90..90")
    assert "gps_edited.csv:9:1" in err


def test_longitude_and_negative_speed(work):
    def bad(rows):
        rows[3][3] = "-4.0"

    refused(work, "imu.csv", "--gps", _gps_with(work, bad), "-o", "out", out=work / "out",
            expect="sog is -4 m/s, outside 0..600")


@pytest.mark.parametrize("option, value, expect", [
    ("--max-lag", "-1", "--max-lag is -1"),
    ("--max-lag", "0", "--max-lag is 0"),
    ("--max-lag", "1e9", "--max-lag is 1e+09"),
    ("--window", "100000", "--window is 100000"),
    ("--window", "0", "--window is 0"),
    ("--rate", "-10", "--rate is -10"),
    ("--rate", "nan", "--rate is nan"),
    ("--delay", "inf", "--delay is inf"),
    ("--min-horizontal-accel", "-1", "--min-horizontal-accel is -1"),
    ("--accel-scale", "0,1,1", "each factor must be within"),
    ("--accel-offset", "5,0,0", "each offset must be within"),
])
def test_option_out_of_range(work, option, value, expect):
    refused(work, "imu.csv", "--gps", "gps.csv", "-o", "out", option, value, out=work / "out", expect=expect)


# ------------------------------------------------------------------------------------- inputs that never end


def test_input_that_is_a_device_not_a_file(work):
    refused(work, "/dev/zero", "--gps", "gps.csv", "-o", "out", out=work / "out", expect="not a regular file")


def test_input_that_is_a_pipe(work):
    os.mkfifo(work / "stream.csv")  # nothing ever writes to it: reading it would wait forever
    refused(work, "stream.csv", "-o", "out", out=work / "out", expect="not a regular file")


def test_gpx_entity_bomb(work):
    # e11 would expand to 10^11 copies of "boom": expat refuses the amplification, and post says where
    entities = '<!ENTITY e0 "boom">' + "".join(f'<!ENTITY e{i} "{f"&e{i - 1};" * 10}">' for i in range(1, 12))
    text = (f'<?xml version="1.0"?>\n<!DOCTYPE gpx [{entities}]>\n<gpx version="1.1" '
            'xmlns="http://www.topografix.com/GPX/1/1"><trk><name>&e11;</name></trk></gpx>\n')
    (work / "bomb.gpx").write_text(text)
    refused(work, "imu.csv", "--gps", "bomb.gpx", "-o", "out", out=work / "out", expect="bomb.gpx")


def test_nan_in_the_imu_log(work):
    lines = (work / "imu.csv").read_text().splitlines()
    fields = lines[30].split(",")
    fields[1] = "nan"
    lines[30] = ",".join(fields)
    (work / "imu.csv").write_text("\n".join(lines) + "\n")
    refused(work, "imu.csv", "--gps", "gps.csv", "-o", "out", out=work / "out", expect="imu.csv:31:1")


def test_binary_garbage_as_the_gps_log(work):
    (work / "noise.csv").write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    refused(work, "imu.csv", "--gps", "noise.csv", "-o", "out", out=work / "out", expect="noise.csv:")


def test_outputs_post_wrote_and_did_not_write_again_are_removed_only_if_unchanged(tmp_path):
    """Not hostile, the other side of the rule: post's own earlier outputs that a run does not write again (the
    plots after --no-plots) go, unless the user changed them; each file lands whole through a rename."""
    from codegen.errors import UserError
    from codegen.post.outdir import check_output_folder, write_files

    out = tmp_path / "out"
    write_files(out, {"report.txt": b"one\n", "angles.png": b"png", "delay.png": b"png2"})
    check_output_folder(out, [])  # all three are post's, unchanged: a new run may replace them
    (out / "delay.png").write_bytes(b"edited by the user")
    with pytest.raises(UserError, match="delay.png"):  # now a run that might write delay.png is refused
        check_output_folder(out, [])
    write_files(out, {"report.txt": b"two\n"})  # (a run that writes no plot would not touch it)
    assert (out / "report.txt").read_text() == "two\n"
    assert not (out / "angles.png").exists()
    assert (out / "delay.png").read_bytes() == b"edited by the user"
    assert sorted(p.name for p in out.iterdir()) == ["delay.png", "post-manifest.json", "report.txt"]
