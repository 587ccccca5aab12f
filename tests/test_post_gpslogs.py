"""`deadreckon post IMU.csv --gps LOG` with a GPS logger's NMEA (RMC/GGA/VTG) or GPX, written here from a synthetic
run: sentences with their checksums computed by `nmea_sentence`, GPX with and without speed/course."""

from __future__ import annotations

import calendar
import time
from functools import reduce

import numpy as np
import pytest

from codegen.cli import main
from codegen.errors import UserError
from codegen.post import PostOptions, load_log, process
from codegen.post.orientation import wrap
from codegen.post.synthetic import Scenario, make_run, write_csv_pair

START_UTC = calendar.timegm((2026, 3, 14, 23, 58, 0))  # the run crosses midnight
KNOT = 0.514444


def nmea_sentence(body: str) -> str:
    """$body*CS with CS the XOR of the body's characters, two hex digits."""
    checksum = reduce(lambda a, c: a ^ ord(c), body, 0)
    return f"${body}*{checksum:02X}"


def _dm(value: float, positive: str, negative: str, degree_digits: int) -> tuple[str, str]:
    hemisphere = positive if value >= 0 else negative
    value = abs(value)
    degrees = int(value)
    minutes = (value - degrees) * 60.0
    return f"{degrees:0{degree_digits}d}{minutes:08.5f}", hemisphere


def _clock(t: float) -> tuple[str, str]:
    g = time.gmtime(int(t))
    return f"{g.tm_hour:02d}{g.tm_min:02d}{g.tm_sec:02d}.{int(round((t % 1) * 100)) % 100:02d}", \
        f"{g.tm_mday:02d}{g.tm_mon:02d}{g.tm_year % 100:02d}"


def write_nmea(path, log, sentences=("RMC", "GGA"), status="A", quality=1, speed_in="RMC"):
    lines = []
    v = log.gps.vel
    for i, t in enumerate(log.gps.t):
        utc = START_UTC + t
        clock, date = _clock(utc)
        lat, ns = _dm(log.gps.lat[i], "N", "S", 2)
        lon, ew = _dm(log.gps.lon[i], "E", "W", 3)
        sog = np.hypot(v[i, 0], v[i, 1])
        cog = np.degrees(np.arctan2(v[i, 0], v[i, 1])) % 360.0
        rmc_speed = f"{sog / KNOT:.3f},{cog:.2f}" if speed_in == "RMC" else ","
        if "RMC" in sentences:
            lines.append(nmea_sentence(f"GPRMC,{clock},{status},{lat},{ns},{lon},{ew},{rmc_speed},{date},,,"
                                       f"{'A' if status == 'A' else 'N'}"))
        if "VTG" in sentences:
            lines.append(nmea_sentence(f"GPVTG,{cog:.2f},T,,M,{sog / KNOT:.3f},N,{sog * 3.6:.3f},K,A"))
        if "GGA" in sentences:
            lines.append(nmea_sentence(f"GPGGA,{clock},{lat},{ns},{lon},{ew},{quality},08,1.0,408.0,M,47.0,M,,"))
        lines.append(nmea_sentence("GPGSA,A,3,01,02,03,04,05,06,07,08,,,,,1.8,1.0,1.5"))
    path.write_text("\r\n".join(lines) + "\r\n")
    return path


def write_gpx(path, log, with_speed=True, version="1.1"):
    v = log.gps.vel
    points = []
    for i, t in enumerate(log.gps.t):
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(int(START_UTC + t))) + f".{int(round((t % 1) * 1000)):03d}Z"
        sog = np.hypot(v[i, 0], v[i, 1])
        cog = np.degrees(np.arctan2(v[i, 0], v[i, 1])) % 360.0
        extra = ""
        if with_speed and version == "1.0":
            extra = f"<course>{cog:.2f}</course><speed>{sog:.3f}</speed>"
        elif with_speed:
            extra = (f"<extensions><gpxtpx:TrackPointExtension><gpxtpx:speed>{sog:.3f}</gpxtpx:speed>"
                     f"<gpxtpx:course>{cog:.2f}</gpxtpx:course></gpxtpx:TrackPointExtension></extensions>")
        points.append(f'<trkpt lat="{log.gps.lat[i]:.8f}" lon="{log.gps.lon[i]:.8f}"><ele>408.0</ele>'
                      f"<time>{stamp}</time>{extra}</trkpt>")
    ns = ('xmlns="http://www.topografix.com/GPX/1/0"' if version == "1.0" else
          'xmlns="http://www.topografix.com/GPX/1/1" '
          'xmlns:gpxtpx="http://www.garmin.com/xmlschemas/TrackPointExtension/v2"')
    path.write_text(f'<?xml version="1.0" encoding="UTF-8"?>\n<gpx version="{version}" creator="test" {ns}>\n'
                    f"<trk><name>run</name><trkseg>\n" + "\n".join(points) + "\n</trkseg></trk></gpx>\n")
    return path


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    log, truth = make_run(Scenario(duration=240.0, seed=12))
    folder = tmp_path_factory.mktemp("gpslogs")
    utc = type(log)(log.name, type(log.imu)(log.imu.t + START_UTC, log.imu.acc, log.imu.gyro), log.gps)
    imu, _ = write_csv_pair(utc, folder)
    return log, truth, imu, folder


def _orientation_error(result, truth):
    o = result.orientation
    return np.degrees(wrap(o.euler[o.valid] - truth.euler(o.t[o.valid] - START_UTC)))


def test_nmea_checksum_helper_matches_a_published_sentence():
    # the RMC example of the NMEA 0183 descriptions (checksum 6A)
    assert nmea_sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W") == \
        "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"


def test_nmea_rmc_gga_end_to_end(run, tmp_path, capsys):
    log, truth, imu, _ = run
    nmea = write_nmea(tmp_path / "track.nmea", log)
    out = tmp_path / "out"
    assert main(["post", str(imu), "--gps", str(nmea), "-o", str(out), "--no-plots"]) == 0
    loaded = load_log(imu, nmea)
    assert loaded.time_scale == "utc" and len(loaded.gps) == len(log.gps)
    assert np.allclose(loaded.gps.t - START_UTC, log.gps.t, atol=0.006)  # centiseconds in the sentence
    assert np.allclose(loaded.gps.vel[:, :2], log.gps.vel[:, :2], atol=0.01)
    result = process(loaded, PostOptions(plots=False))
    err = _orientation_error(result, truth)
    assert np.abs(err[:, :2]).max() < 0.5
    assert result.velocity_residual_rms < 0.15
    assert "<time>2026-03-15T00:0" in (out / "trajectory.gpx").read_text()  # after midnight, dated


def test_nmea_vtg_gives_the_speed_when_rmc_has_none(run, tmp_path):
    log, _, imu, _ = run
    nmea = write_nmea(tmp_path / "vtg.nmea", log, sentences=("RMC", "VTG", "GGA"), speed_in="VTG")
    loaded = load_log(imu, nmea)
    assert np.allclose(loaded.gps.vel[:, :2], log.gps.vel[:, :2], atol=0.01)
    assert not any("speed and course derived" in n for n in loaded.notes)


def test_nmea_gga_only_derives_speed_course_and_climb(run, tmp_path):
    """GGA has no speed, course or date: velocity by central differences of the positions (and heights), time in
    seconds after midnight of the first day (the IMU CSV must then be on that axis too)."""
    log, truth, _, folder = run
    nmea = write_nmea(tmp_path / "gga.nmea", log, sentences=("GGA",))
    day = START_UTC - START_UTC % 86400
    shifted = type(log)(log.name, type(log.imu)(log.imu.t + START_UTC - day, log.imu.acc, log.imu.gyro), log.gps)
    imu, _ = write_csv_pair(shifted, tmp_path / "imu")
    loaded = load_log(imu, nmea)
    assert any("derived from positions" in n for n in loaded.notes)
    assert any("seconds after midnight" in n for n in loaded.notes)
    assert np.all(np.diff(loaded.gps.t) > 0)  # across midnight: a day added
    # the central difference of positions whose noise is 2 m: a velocity 1-sigma of about 2 m/s, and said so
    true_v = truth.velocity(loaded.gps.t - (START_UTC - day))[:, :2]
    err = loaded.gps.vel[:, :2] - true_v
    assert np.sqrt(np.mean(err**2)) < 2.0 * np.median(loaded.gps.sigma_vel[:, 0])
    # the heights are constant: the climb derived in the first fix's ENU frame is the curvature of the Earth only
    assert np.abs(loaded.gps.vel[:, 2]).max() < 0.01
    result = process(loaded, PostOptions(plots=False))
    o = result.orientation
    e = np.abs(np.degrees(wrap(o.euler[o.valid] - truth.euler(o.t[o.valid] - (START_UTC - day)))))[:, :2]
    sigma = np.degrees(o.sigma[o.valid])[:, :2]
    # white 2 m position noise makes the derived accelerations noisy: the tilt is worse than with Doppler (0.5 deg),
    # and its reported 1-sigma says so (it covers the error)
    assert np.median(e) < 2.0
    assert np.all(e <= 3.0 * sigma) and np.mean(e <= sigma) > 0.6


@pytest.mark.parametrize("version", ["1.0", "1.1"])
def test_gpx_with_speed_and_course(run, tmp_path, version):
    log, truth, imu, _ = run
    gpx = write_gpx(tmp_path / "track.gpx", log, with_speed=True, version=version)
    loaded = load_log(imu, gpx)
    assert not any("derived from positions" in n for n in loaded.notes)
    assert np.allclose(loaded.gps.vel[:, :2], log.gps.vel[:, :2], atol=0.01)
    result = process(loaded, PostOptions(plots=False))
    assert np.abs(_orientation_error(result, truth)[:, :2]).max() < 0.5


def test_gpx_without_speed_derives_it(run, tmp_path, capsys):
    log, _, imu, _ = run
    gpx = write_gpx(tmp_path / "plain.gpx", log, with_speed=False)
    out = tmp_path / "out"
    assert main(["post", str(imu), "--gps", str(gpx), "-o", str(out), "--no-plots"]) == 0
    assert "speed and course derived from positions" in (out / "report.txt").read_text()


@pytest.mark.parametrize("name, writer, message", [
    ("track.nmea", lambda p, log: write_nmea(p, log), "GPS log (NMEA) without IMU data"),
    ("track.gpx", lambda p, log: write_gpx(p, log), "GPS log (GPX) without IMU data"),
])
def test_gps_only_input_says_what_needs_imu_data(run, tmp_path, capsys, name, writer, message):
    log, _, _, _ = run
    path = writer(tmp_path / name, log)
    code = main(["post", str(path), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "--gps" in err and "Traceback" not in err


def test_nmea_with_no_valid_fix_is_refused(run, tmp_path):
    log, _, imu, _ = run
    nmea = write_nmea(tmp_path / "nofix.nmea", log, status="V", quality=0)
    with pytest.raises(UserError, match="none of the .* epochs has a valid fix"):
        load_log(imu, nmea)


def test_nmea_damaged_lines_are_skipped_and_counted(run, tmp_path):
    log, _, imu, _ = run
    nmea = write_nmea(tmp_path / "noisy.nmea", log)
    lines = nmea.read_text().splitlines()
    lines[10] = lines[10][:-1] + ("0" if lines[10][-1] != "0" else "1")  # checksum broken
    lines[20] = lines[20][:15]  # cut short
    nmea.write_text("\r\n".join(lines))
    loaded = load_log(imu, nmea)
    assert any("skipped 2 damaged line(s)" in n and "line 11" in n for n in loaded.notes)


def test_gpx_that_is_not_xml_is_located(run, tmp_path):
    _, _, imu, _ = run
    gpx = tmp_path / "bad.gpx"
    gpx.write_text('<?xml version="1.0"?>\n<gpx version="1.1">\n<trk><trkseg><trkpt lat="1" lon="2">\n</gpx>\n')
    with pytest.raises(UserError) as info:
        load_log(imu, gpx)
    assert "bad.gpx:4:" in info.value.render()


def test_gpx_route_without_times_is_refused(run, tmp_path):
    _, _, imu, _ = run
    gpx = tmp_path / "route.gpx"
    gpx.write_text('<?xml version="1.0"?>\n<gpx version="1.1" xmlns="http://www.topografix.com/GPX/1/1">'
                   '<rte><rtept lat="47.0" lon="8.0"/><rtept lat="47.1" lon="8.1"/></rte></gpx>\n')
    with pytest.raises(UserError, match="no track point with a time"):
        load_log(imu, gpx)
