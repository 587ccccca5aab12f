"""`deadreckon post` on device logs whose header or GPS records are damaged (or forged): a block size of 0 or of
letters, an axes remap with a trailing sign, a sensitivity of 0 or nan, fixes dated month 0, month 13 or year
65535, a latitude of 200 degrees. Each through the CLI: exit 2, an `error:` naming the file with a hint, no
traceback, within the bound, nothing written outside the output folder (nor the output folder made)."""

from __future__ import annotations

import pytest

from hostilekit import assert_refused, run_cli, snapshot, user_files
from inputkit import device_log

CASES = [
    ("block-bytes-0", {"header": {"block_bytes": "0"}}, ["the header's block_bytes=0 is not a block size"]),
    ("block-bytes-abc", {"header": {"block_bytes": "abc"}}, ["block_bytes=abc"]),
    ("block-bytes-negative", {"header": {"block_bytes": "-4096"}}, ["block_bytes=-4096"]),
    ("block-bytes-huge", {"header": {"block_bytes": "9" * 30}}, ["is not a block size (256..65536 bytes)"]),
    ("axes-trailing-sign", {"header": {"axes": "+0+1+2+"}}, ["axes=+0+1+2+", "a signed permutation"]),
    ("axes-repeated", {"header": {"axes": "+0+0+2"}}, ["axes=+0+0+2"]),
    ("axes-letters", {"header": {"axes": "+x+y+z"}}, ["axes=+x+y+z"]),
    ("accel-lsb-0", {"header": {"accel_lsb_per_g": "0"}}, ["accel_lsb_per_g=0"]),
    ("accel-lsb-nan", {"header": {"accel_lsb_per_g": "nan"}}, ["accel_lsb_per_g=nan"]),
    ("gyro-lsb-inf", {"header": {"gyro_lsb_per_dps": "inf"}}, ["gyro_lsb_per_dps=inf"]),
    ("gps-month-0", {"gps": {5: {"month": 0}}}, ["GPS record 6 of the log says", "which is no date"]),
    ("gps-month-13", {"gps": {5: {"month": 13}}}, ["-13-", "which is no date"]),
    ("gps-year-65535", {"gps": {0: {"year": 65535}}}, ["GPS record 1 of the log says 65535-"]),
    ("gps-day-31-november", {"gps": {3: {"day": 31}}}, ["2026-11-31"]),
    ("gps-latitude-200", {"gps": {7: {"lat": 2_000_000_000}}}, ["latitude 200.0000000", "not on Earth"]),
    ("gps-longitude-minus-200", {"gps": {7: {"lon": -2_000_000_000}}}, ["longitude -200.0000000"]),
]


@pytest.mark.parametrize("damage,phrases", [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_damaged_device_log_is_refused(tmp_path, damage, phrases):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    (home / "dr00001.bin").write_bytes(device_log(**damage))
    before = snapshot(home)
    outcome = run_cli("post", "dr00001.bin", "-o", "post-out", "--no-plots", cwd=home, timeout=60)
    assert_refused(outcome, "dr00001.bin: ", *phrases, "hint: ", bound=60)
    assert snapshot(home) == before


def test_the_undamaged_log_posts(tmp_path):
    """The same log without the damage is posted (so each case above fails for its damage alone)."""
    (tmp_path / "dr00001.bin").write_bytes(device_log())
    outcome = run_cli("post", "dr00001.bin", "-o", "post-out", "--no-plots", cwd=tmp_path, timeout=120)
    assert outcome.returncode == 0, outcome.stderr


def _csv_pair(home):
    from codegen.post.synthetic import write_csv_pair
    from inputkit import synthetic_run

    imu, gps = write_csv_pair(synthetic_run(), home)
    return imu.read_text().splitlines(keepends=True), gps.read_text().splitlines(keepends=True)


def _late(lines):
    return [lines[0]] + [f"{float(line.split(',', 1)[0]) + 1000:.4f},{line.split(',', 1)[1]}" for line in lines[1:]]


@pytest.mark.parametrize("imu_lines,gps_lines,phrase", [
    (lambda lines: lines, lambda lines: lines[:2], "error: imu.csv and gps.csv: only 1 GPS epoch(s) with a fix"),
    (lambda lines: lines[:3], lambda lines: lines, "error: imu.csv and gps.csv: only 2 IMU sample(s)"),
    (_late, lambda lines: lines, "error: imu.csv and gps.csv: IMU (1000.000..1039.980 s) and GPS"),
], ids=["one-gps-epoch", "two-imu-samples", "no-shared-interval"])
def test_a_log_too_short_is_named_by_its_files(tmp_path, imu_lines, gps_lines, phrase):
    home = tmp_path / "home"
    home.mkdir()
    imu, gps = _csv_pair(home)
    (home / "imu.csv").write_text("".join(imu_lines(imu)))
    (home / "gps.csv").write_text("".join(gps_lines(gps)))
    before = snapshot(home)
    outcome = run_cli("post", "imu.csv", "--gps", "gps.csv", "--no-plots", cwd=home, timeout=60)
    assert_refused(outcome, phrase, "hint: ", bound=60)
    assert snapshot(home) == before
