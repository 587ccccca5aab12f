"""What benchmarks/hostile_fuzz.py found, kept as cases: an IMU CSV acceleration of 1e308 g (scipy's "initial guess
outside bounds" after the run) and a GPX track point at latitude nan ("residuals are not finite"). Through the CLI:
exit 2, the file and line named, a hint, no traceback, nothing changed around the work."""

from __future__ import annotations

from fuzzkit import _absolute_imu, _gpx
from hostilekit import assert_refused, run_cli, snapshot, user_files


def _post(home, imu: str, gps: str, name: str, *phrases: str) -> None:
    (home / "imu.csv").write_text(imu)
    (home / name).write_text(gps)
    before = snapshot(home)
    outcome = run_cli("post", "imu.csv", "--gps", name, "--no-plots", cwd=home, timeout=60)
    assert_refused(outcome, *phrases, "hint: ", bound=60)
    assert snapshot(home) == before


def test_an_acceleration_of_1e308_g(tmp_path):
    user_files(tmp_path)
    lines = _absolute_imu().split("\n")
    t, ax, ay, rest = lines[40].split(",", 3)
    lines[40] = ",".join((t, ax, "1e308", rest))
    _post(tmp_path, "\n".join(lines), _gpx(), "gps.gpx",
          "imu.csv:41:1: error: IMU log: ay is 1e+308 g, outside -64..64")


def test_a_track_point_at_latitude_nan(tmp_path):
    user_files(tmp_path)
    gpx = _gpx().replace('lat="', 'lat="nan" x="', 1)
    _post(tmp_path, _absolute_imu(), gpx, "gps.gpx", "gps.gpx: track point 1 at nan")
