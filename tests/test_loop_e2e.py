"""From the device back to the computer, on the app's own output: the generated T-Beam app on the emulated board
(codegen/sim/mpsim) records a drive with a GPS gap; `monitor` decodes the console lines it printed (also through
a port that drops mid-run), and `pull` copies the logs it wrote off a raw-REPL board for `post` to read."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from codegen.deploy.console import ConsoleStatus
from codegen.deploy.monitor import monitor
from codegen.sim.harness import generate_app, imu_counts, nmea_epoch, run_app, tbeam_scenario, write_counts, \
    write_stream
from conftest import require_tool

LAT, LON = 40.0350855, -75.52009367
RATE, ACCEL = 200.0, 1.0  # Hz, m/s^2
GAP = (18, 26)  # s without fixes: the app dead-reckons


def _speed(t):
    return ACCEL * (np.clip(t - 12.0, 0.0, 4.0) - np.clip(t - 22.0, 0.0, 4.0))


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """32 s: calibration, pushed East at 12-16 s and stopped at 22-26 s, fixes every second except in GAP."""
    micropython = require_tool("micropython")
    work = tmp_path_factory.mktemp("drive")
    app = generate_app("ttgo-tbeam-v1.1", work / "out")
    metres_per_deg_lon = 111320.0 * np.cos(np.radians(LAT))
    fine = np.arange(0.0, 32.0, 0.001)
    east = np.cumsum(_speed(fine)) * 0.001
    chunks = [(t, nmea_epoch(t, LAT, LON + np.interp(t, fine, east) / metres_per_deg_lon,
                             speed_kn=_speed(t) / 0.514444, course=90.0))
              for t in range(1, 32) if not GAP[0] <= t < GAP[1]]
    counts = write_counts(work / "imu.bin", imu_counts(32, RATE, seed=2,
                                                       pushes=[(12.0, 16.0, 0, ACCEL), (22.0, 26.0, 0, -ACCEL)]))
    gps = write_stream(work / "gps.txt", chunks)
    run = run_app(micropython, app, tbeam_scenario(work, counts, gps, 32), work)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "Traceback" not in run.stdout
    return run, work


def decoded(stdout: str) -> tuple[ConsoleStatus, list]:
    status = ConsoleStatus()
    events = [status.feed(line) for line in stdout.splitlines()]
    return status, [e for e in events if e is not None]


def test_the_console_of_a_drive_decoded(drive):
    run, _ = drive
    status, events = decoded(run.stdout)
    start = run.console("DEADRECKON")
    assert len(start) == 1 and status.starts == 1
    assert status.board == "ttgo-tbeam-v1.1" and f"kernel={status.kernel}" in start[0]
    assert status.kernel in ("native", "python") and status.imu == "ok"
    # every MODE line the app printed, in order: the fix lost in the gap, then found again
    assert [e.text for e in events if e.kind == "MODE"] == run.console("MODE")
    assert "MODE GPS -> IMU" in run.console("MODE") and run.console("MODE")[-1].endswith("-> GPS")
    assert status.mode == "GPS" and status.has_fix and not status.calibrating
    assert status.sats == 7  # nmea_epoch's GGA says 07 satellites
    assert abs(status.lat_e7 / 1e7 - LAT) < 1e-5 and abs(status.lon_e7 / 1e7 - LON) < 2e-3
    last_diag = dict(item.split("=") for item in run.console("DIAG")[-1].split()[1:])
    assert status.heap_free == int(last_diag["heap_free"]) and status.dropped == int(last_diag["dropped"]) == 0
    assert status.speed == pytest.approx(float(last_diag["gps_speed"])) and status.speed < 0.05  # stopped
    wins = run.console("WIN")
    assert status.windows == int(wins[-1].split()[1])
    line = status.status_line(80)
    assert len(line) <= 80 and line.startswith("GPS fix") and "sats 7" in line and status.kernel in line
    # in the gap the status says IMU and the dead-reckoned offset and speed
    gap = ConsoleStatus()
    for text in run.stdout.splitlines():
        gap.feed(text)
        if text.startswith("WIN") and "mode=IMU" in text:
            break
    assert gap.mode == "IMU" and not gap.has_fix and " m/s " in gap.status_line() and " m  drop" in gap.status_line()
    assert gap.speed == pytest.approx(float(np.hypot(gap.velocity[0], gap.velocity[1])))


class _Replay:
    """A TCP serial bridge that plays the console back: the first client gets the first part and is dropped (a
    board reset cutting the link), the next one the rest."""

    def __init__(self, data: bytes, cut: int):
        self.parts = [data[:cut], data[cut:]]
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        for index, part in enumerate(self.parts):
            conn, _ = self.server.accept()
            import time

            time.sleep(0.3)  # pyserial's socket:// open discards what has arrived: talk once it is listening
            for start in range(0, len(part), 1000):
                conn.sendall(part[start:start + 1000])
            if index == 0:
                conn.close()
                self.server.close()  # the port is gone for a while, then back
                time.sleep(1.0)
                self.server = socket.create_server(("127.0.0.1", int(self.url.rsplit(":", 1)[1])))
            else:
                self.last = conn  # kept open: the board keeps running

    def close(self):
        self.server.close()


def test_monitor_follows_the_board_through_a_dropped_port(drive, capsys):
    import io

    run, _ = drive
    data = run.stdout.encode()
    cut = data.index(b"\n", len(data) // 2) + 1
    expected, _ = decoded(run.stdout)
    replay = _Replay(data, cut)
    out = io.StringIO()
    try:
        status = monitor(replay.url, out=out, keys=None, timeout=60,
                         until=lambda s: s.windows == expected.windows and s.heap_free == expected.heap_free)
    finally:
        replay.close()
    text = out.getvalue()
    assert "went away" in text and "is back" in text
    assert (status.mode, status.sats, status.lat_e7, status.lon_e7, status.windows, status.kernel) == \
        (expected.mode, expected.sats, expected.lat_e7, expected.lon_e7, expected.windows, expected.kernel)
    assert run.console("MODE")[0] in text and "WIN " not in text  # events printed, windows only in the status


def test_the_drive_pulled_off_the_board_and_posted(drive, tmp_path, capsys):
    """The logs the app wrote, on a raw-REPL board (the peer holds the emulated board's filesystem), pulled with
    --post through the CLI: the copies are the app's bytes and post reads the drive (flat, pushed East)."""
    from codegen.cli import main
    from codegen.post import load_log
    from conftest import require
    from peers.repl_peer import ReplPeer, missing_reason

    reason = missing_reason()
    require(reason is None, reason or "")
    _, work = drive
    written = {p.name: p.read_bytes() for p in sorted((work / "fs").glob("dr*.bin"))}
    assert written
    root = tmp_path / "board"
    (root / "logs").mkdir(parents=True)
    for name, data in written.items():
        (root / "logs" / name).write_bytes(data)
    out = tmp_path / "pulled"
    with ReplPeer(root) as board:
        assert main(["pull", "--port", board.url, "-o", str(out), "--post"]) == 0
    printed = capsys.readouterr().out
    assert f"pulled {len(written)} log(s)" in printed
    assert {name: (out / name).read_bytes() for name in written} == written
    last = sorted(written)[-1]
    assert (out / (last[:-4] + "-post")).is_dir() and f"post {last} ->" in printed
    log = load_log(out / last)
    assert log.time_scale == "utc" and len(log.gps) >= 15
