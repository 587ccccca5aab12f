"""`deadreckon post` on the device's own log format (docs/log-format.md v1), written here from a synthetic run."""

from __future__ import annotations

import calendar
import struct

import numpy as np
import pytest

from codegen.board.model import STANDARD_GRAVITY
from codegen.cli import main
from codegen.post import PostOptions, load_log, process
from codegen.post.orientation import wrap
from codegen.post.synthetic import Scenario, make_run

BLOCK = 4096
START_UTC = calendar.timegm((2026, 11, 21, 23, 59, 30))  # crosses midnight during the run


class Blocks:
    def __init__(self):
        self.out, self.block = bytearray(), bytearray()

    def add(self, record: bytes):
        if len(self.block) + len(record) > BLOCK:
            self.flush()
        self.block += record

    def flush(self):
        if self.block:
            self.out += self.block + bytes(BLOCK - len(self.block))
            self.block = bytearray()


def write_device_log(path, log, latency=0.25, seed=0, axes="+0+1+2", clock_rate=1.0):
    """IMU counts at their device time; each fix logged when its NMEA would have arrived (time + latency).
    The device clock runs at clock_rate device seconds per true second."""
    rng = np.random.default_rng(seed)
    header = f"deadreckon=1;board=synthetic;imu_rate_hz=200;log_every=4;accel_lsb_per_g=16384;gyro_lsb_per_dps=131;axes={axes};kernel=python"
    b = Blocks()
    b.add(struct.pack("<BBH", 0x48, 1, len(header)) + header.encode())
    t0 = log.imu.t[0]
    counts = np.round(log.imu.acc / STANDARD_GRAVITY * 16384).astype(int)
    events = [(t, "I", i) for i, t in enumerate(log.imu.t)]
    arrival = log.gps.t + latency + rng.uniform(0.0, 0.15, len(log.gps))
    events += [(t, "G", i) for i, t in enumerate(arrival)]
    events.sort()
    v = log.gps.vel
    for t, kind, i in events:
        t_us = int(round((t - t0 + 5.0) * clock_rate * 1e6)) & 0xFFFFFFFF
        if kind == "I":
            ax, ay, az = counts[i]
            b.add(struct.pack("<BI6h", 0x49, t_us, ax, ay, az, 0, 0, 0))
        else:
            utc = START_UTC + log.gps.t[i]
            day = utc - utc % 86400
            y, mo, d = __import__("time").gmtime(day)[:3]
            sog = np.hypot(v[i, 0], v[i, 1])
            cog = np.degrees(np.arctan2(v[i, 0], v[i, 1])) % 360.0
            b.add(struct.pack("<BIIHBBiiiiHiBBBH", 0x47, t_us, int(round((utc % 86400) * 1000)), y, mo, d,
                              int(round(log.gps.lat[i] * 1e7)), int(round(log.gps.lon[i] * 1e7)), 400000,
                              int(sog * 1000 + 0.5), int(cog * 100 + 0.5) % 36000, int(round(v[i, 2] * 1000)),
                              3, 1, 8, 120))
    b.flush()
    path.write_bytes(bytes(b.out))
    return path


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    log, truth = make_run(Scenario(duration=300.0, seed=5))
    path = write_device_log(tmp_path_factory.mktemp("dev") / "dr00001.bin", log)
    return path, log, truth


def test_device_log_reads_onto_utc(run):
    path, log, _ = run
    dev = load_log(path)
    assert dev.time_scale == "utc"
    assert len(dev.imu) == len(log.imu) and len(dev.gps) == len(log.gps)
    assert np.allclose(dev.imu.acc, log.imu.acc, atol=2 * STANDARD_GRAVITY / 16384)
    # UTC fix times exact; the IMU on the device clock's own rate, offset to the early edge of arrivals that jitter
    # by 0..150 ms: no drift over the 300 s
    assert np.allclose(np.diff(dev.gps.t), 1.0)
    offset = (dev.imu.t - dev.imu.t[0]) - (log.imu.t - log.imu.t[0])
    assert np.ptp(offset) < 1e-5


def test_short_log_keeps_the_device_clock_rate(tmp_path):
    """30 s with fix receipts jittering by 0..150 ms: a line fitted to them would put the rate ~1e-3 off (the IMU
    times drifting a millisecond per second against the truth); the device's own clock rate keeps them exact."""
    log, _ = make_run(Scenario(duration=30.0, seed=3))
    dev = load_log(write_device_log(tmp_path / "dr00001.bin", log, seed=4))
    lateness = dev.imu.t - (START_UTC + log.imu.t)
    assert np.ptp(lateness) < 1e-5
    assert np.allclose(np.diff(dev.imu.t), np.diff(log.imu.t), atol=1e-6)
    # the offset sits on the early edge: the IMU early by the 250 ms latency plus the least jitter of ~30 fixes
    assert -0.25 - 0.03 <= lateness[0] <= -0.25 + 0.001
    assert any("the device's rate" in note for note in dev.notes)


def test_a_clock_proven_off_by_the_fixes_is_followed(tmp_path):
    """A device clock 1 % fast (an MPU-6050 oscillator at its tolerance), 120 s of fixes: the fixes show the rate far
    beyond their jitter, and the IMU times follow them instead of drifting 1.2 s."""
    log, _ = make_run(Scenario(duration=120.0, seed=3))
    dev = load_log(write_device_log(tmp_path / "dr00001.bin", log, seed=4, clock_rate=1.01))
    lateness = dev.imu.t - (START_UTC + log.imu.t)
    assert np.ptp(lateness) < 0.05
    assert any("runs off its nominal rate" in note for note in dev.notes)


def test_device_log_end_to_end(run, tmp_path, capsys):
    path, log, truth = run
    assert main(["post", str(path), "-o", str(tmp_path / "out"), "--no-plots"]) == 0
    dev = load_log(path)
    result = process(dev, PostOptions())
    o = result.orientation
    # the IMU was mapped to the fixes' early edge, which is 250 ms after the fix: the delay search finds that
    # fixed NMEA latency (IMU stamps early by it), within one IMU sample
    assert abs(result.delay - (-0.25)) <= 0.02
    err = np.degrees(wrap(o.euler[o.valid] - truth.euler(o.t[o.valid] - START_UTC)))
    assert np.abs(err[:, :2]).max() < 0.5
    assert result.velocity_residual_rms < 0.15
    assert "<time>2026-11-2" in (tmp_path / "out" / "trajectory.gpx").read_text()


def test_axis_remap_from_the_header(tmp_path):
    log, _ = make_run(Scenario(duration=30.0, seed=2))
    swapped = log.imu.acc[:, [1, 0, 2]] * np.array([1.0, -1.0, 1.0])  # sensor axes as mounted
    log.imu.acc = swapped
    path = write_device_log(tmp_path / "dr00002.bin", log, axes="-1+0+2")
    dev = load_log(path)  # body x = -sensor y, body y = sensor x
    assert np.allclose(dev.imu.acc[:, 0], -swapped[:, 1], atol=1e-2)
    assert np.allclose(dev.imu.acc[:, 1], swapped[:, 0], atol=1e-2)


def test_cut_off_device_log_keeps_whole_records(run, tmp_path):
    path, _, _ = run
    data = path.read_bytes()
    cut = tmp_path / "dr00003.bin"
    cut.write_bytes(data[: len(data) - BLOCK // 2 - 5])
    dev = load_log(cut)
    assert any("incomplete" in n for n in dev.notes)
    assert len(dev.imu) > 1000


@pytest.mark.parametrize("content, message", [
    (b"", "is empty"),
    (b"\x00" * 100, "not a deadreckon device log"),
    (struct.pack("<BBH", 0x48, 7, 0), "version 7"),
])
def test_bad_device_logs(tmp_path, capsys, content, message):
    path = tmp_path / "dr00009.bin"
    path.write_bytes(content)
    code = main(["post", str(path), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err


def test_device_log_without_fix(tmp_path, capsys):
    log, _ = make_run(Scenario(duration=20.0))
    log.gps = log.gps.select(np.zeros(len(log.gps), dtype=bool))
    path = write_device_log(tmp_path / "dr00004.bin", log)
    code = main(["post", str(path), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "no GPS fix" in err


def test_log_written_by_the_generated_app_on_micropython(tmp_path):
    """The real writer: the generated T-Beam app on the unix-port MicroPython (codegen/sim/mpsim) logs a flat device that
    is pushed East and stopped while the GPS reports the same motion; `post` reads that log and finds it flat."""
    from codegen.sim.harness import (
        generate_app,
        imu_counts,
        nmea_epoch,
        run_app,
        tbeam_scenario,
        write_counts,
        write_stream,
    )
    from conftest import board_micropython

    micropython = board_micropython()
    app = generate_app("ttgo-tbeam-v1.1", tmp_path / "out")
    rate, accel = 200.0, 1.0  # Hz, m/s^2
    pushes = [(12.0, 16.0, 0, accel), (22.0, 26.0, 0, -accel)]

    def speed(t):
        return accel * (np.clip(t - 12.0, 0.0, 4.0) - np.clip(t - 22.0, 0.0, 4.0))

    lat0, lon0 = 40.0350855, -75.52009367
    metres_per_deg_lon = 111320.0 * np.cos(np.radians(lat0))
    fine = np.arange(0.0, 32.0, 0.001)
    east = np.cumsum(speed(fine)) * 0.001
    chunks = []
    for t in range(1, 32):
        lon = lon0 + np.interp(t, fine, east) / metres_per_deg_lon
        chunks.append((t, nmea_epoch(t, lat0, lon, speed_kn=speed(t) / 0.514444, course=90.0)))
    counts = write_counts(tmp_path / "imu.bin", imu_counts(32, rate, seed=2, pushes=pushes))
    gps = write_stream(tmp_path / "gps.txt", chunks)
    run = run_app(micropython, app, tbeam_scenario(tmp_path, counts, gps, 32), tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    logs = sorted((tmp_path / "fs").glob("dr*.bin"))
    assert logs
    dev = load_log(logs[-1])
    assert dev.time_scale == "utc" and len(dev.gps) >= 15 and dev.imu.rate_hz == pytest.approx(50.0, rel=0.05)
    result = process(dev, PostOptions())
    o = result.orientation
    e = np.degrees(o.euler[o.valid])
    assert np.abs(e[:, 0]).max() < 1.0 and np.abs(e[:, 1]).max() < 1.0  # flat
    assert result.velocity_residual_rms < 0.15
    assert abs(result.delay) < 0.5
    # the push was along the sensor's x axis, eastwards: the body x axis (after the header's axes remap) points
    # East or West, so the yaw of the pushed intervals is 0 or 180 deg
    pushed = o.valid & (o.horizontal_accel > 0.5 * accel)
    yaw = np.degrees(o.euler[pushed, 2])
    assert pushed.sum() >= 4
    assert np.all(np.minimum(np.abs(yaw), 180.0 - np.abs(yaw)) < 5.0)


def _v2_part(path, run, part, t0_us, n_rows=40, every=4, rate=200.0):
    """A version 2 part file: its header, then IMU rows one log period apart from t0_us (the run's clock)."""
    header = (f"deadreckon=2;board=synthetic;imu_rate_hz={rate:g};log_every={every};accel_lsb_per_g=16384;"
              f"gyro_lsb_per_dps=131;axes=+0+1+2;kernel=python;block_bytes={BLOCK};run={run};part={part}")
    b = Blocks()
    b.add(struct.pack("<BBH", 0x48, 2, len(header)) + header.encode())
    for k in range(n_rows):
        b.add(struct.pack("<BI6h", 0x49, (t0_us + int(k * every / rate * 1e6)) & 0xFFFFFFFF, 0, 0, 16384, 0, 0, 0))
    b.flush()
    path.write_bytes(bytes(b.out))
    return path


def test_a_run_is_read_whole_from_its_parts_in_order(tmp_path):
    from codegen.post.devicelog import parse_device_parts, run_parts

    # the run's clock wraps inside part 2: read in order, the parts are one increasing time line
    start = (1 << 32) - 30 * 20000
    _v2_part(tmp_path / "dr00003.bin", 3, 1, start)
    _v2_part(tmp_path / "dr00004.bin", 3, 2, start + 40 * 20000)
    _v2_part(tmp_path / "dr00005.bin", 3, 3, start + 80 * 20000)
    parts = run_parts(tmp_path / "dr00004.bin")
    assert [p.name for p in parts] == ["dr00003.bin", "dr00004.bin", "dr00005.bin"]
    t = np.array([r[0] for r in parse_device_parts(parts).imu])
    assert len(t) == 120 and np.all(np.diff(t) == 20000)
    assert run_parts(tmp_path) == parts  # a folder of one run


def test_a_missing_middle_part_or_two_runs_in_a_folder_is_a_clear_error(tmp_path, capsys):
    _v2_part(tmp_path / "dr00001.bin", 1, 1, 0)
    _v2_part(tmp_path / "dr00003.bin", 1, 3, 2_000_000)
    assert main(["post", str(tmp_path / "dr00001.bin"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "lacks part(s) 2" in err and "Traceback" not in err
    (tmp_path / "dr00003.bin").unlink()
    _v2_part(tmp_path / "dr00002.bin", 2, 1, 0)
    assert main(["post", str(tmp_path), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "of 2 runs in the folder" in err and "pass one file" in err


def test_version_2_rows_stand_for_the_middle_of_their_box(tmp_path):
    from codegen.post.devicelog import parse_device_log, to_post_log

    _v2_part(tmp_path / "dr00001.bin", 1, 1, 1_000_000)
    raw = parse_device_log(tmp_path / "dr00001.bin")
    raw.gps = [(1_000_000 + k * 200_000, 0xFFFFFFFF, 0, 0, 0, 470000000, 80000000, 0, 1000 * k, 9000, 0, 3, 1, 8, 100)
               for k in range(4)]
    log = to_post_log(raw)
    assert log.imu.t[0] == pytest.approx(1.0 - 1.5 / 200.0)  # (log_every - 1) / 2 samples before the row's time
