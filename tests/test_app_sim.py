"""The app against the simulator's sensor models (codegen/sim): a simulated car drive's MPU-6050 counts in
the emulated chip, the NEO-6M model's NMEA in the UART, a GPS outage; the app follows the fixes, then dead-reckons.
"""

from __future__ import annotations

import pytest

from codegen.board.loader import load_board
from codegen.sim.harness import (
    generate_app,
    run_app,
    tbeam_scenario,
    write_counts,
    write_stream,
)
from conftest import board_micropython

# In fused mode the app runs under this tap: it reports each fix's fused_position call (the Doppler, the metres from
# the previous anchor the app computed, the smoothed offset it got) and, per GPS-mode window, the app's ENU offset.
FUSED_TAP = r"""
import json
import app

dr = app.dr
orig_position = dr.fused_position


def fused_position(st, ve, vn, de, dn):
    orig_position(st, ve, vn, de, dn)
    anchor = a.anchor or (0, 0)
    print("FIXPOS " + json.dumps([ve, vn, de, dn, st[dr.FIX_AE], st[dr.FIX_AE + 1], anchor[0], anchor[1],
                                  a.nmea.lat_e7, a.nmea.lon_e7]))


def on_window(app_, samples, dt_us, out):
    print("ENU " + json.dumps([app_.mode, app_.enu[0], app_.enu[1], out[0], out[1]]))


dr.fused_position = fused_position
a = app.App()
a.on_window = on_window
a.run()
"""


@pytest.mark.parametrize("mode", ["seed", "fused"])
def test_simulated_drive_with_outage(tmp_path, mode):
    micropython = board_micropython()
    import codegen.sim.trajectory as sim_traj
    from codegen.sim.mpu6050 import simulate_imu
    from codegen.sim.neo6m import nmea_sentences, simulate_gps

    yaml = tmp_path / "board.yaml"
    yaml.write_text(f"extends: ttgo-tbeam-v1.1\nname: tbeam-{mode}\nalgorithm:\n  mode: {mode}\n")
    board = load_board(yaml).board
    out = generate_app(yaml, tmp_path / "out")
    trajectory = sim_traj.make_scenario("car", seed=3, duration=50.0)
    _, counts = simulate_imu(trajectory, board, seed=3)
    track = simulate_gps(trajectory, seed=3, outages=[(32.0, 60.0)])
    sentences = nmea_sentences(track)
    per_epoch = len(sentences) // len(track.t)
    chunks = [(float(track.t[i]) + 0.05, b"".join(sentences[per_epoch * i : per_epoch * (i + 1)]).decode())
              for i in range(len(track.t))]
    gps = write_stream(tmp_path / "gps.txt", chunks)
    imu = write_counts(tmp_path / "imu.bin", counts)
    scenario = tbeam_scenario(tmp_path, imu, gps, 48.0, rate_hz=board.imu.achieved_sample_rate_hz)
    script = None
    if mode == "fused":
        script = tmp_path / "tap.py"
        script.write_text(FUSED_TAP)
    run = run_app(micropython, out, scenario, tmp_path / "w", script=script and str(script))
    assert run.returncode == 0, run.stderr + run.stdout[-1500:]
    assert "Traceback" not in run.stdout
    # while fixes arrive the screen shows the receiver's position (to the 1e-7 degree of the NMEA's 5 decimals)
    i = 25
    screen = run.screen_at(track.t[i] + 0.9)
    assert screen[0].startswith("GPS fix")
    shown = float(screen[1].split()[0]) * (1 if screen[1].endswith("N") else -1)
    assert abs(shown - track.lat[i]) < 2e-7
    # the outage: IMU mode 3 s (fix_timeout_s) after the last fix, and the device keeps computing positions
    modes = [line for line in run.stdout.splitlines() if line.startswith("MODE")]
    assert modes == ["MODE GPS -> IMU"]
    switch = [e for e in run.screens() if e["lines"][0].startswith("IMU")][0]["t_us"] / 1e6
    assert 34.5 < switch < 36.5
    imu_windows = [line for line in run.stdout.splitlines() if line.startswith("WIN") and "mode=IMU" in line]
    assert len(imu_windows) >= 3
    for line in run.console("DIAG")[1:]:
        assert "dropped=0" in line, line
    # how far the dead-reckoned position is from the truth at the end (printed: accuracy is docs/accuracy.md's table)
    last = [line for line in run.stdout.splitlines() if line.startswith("WIN")][-1]
    fields = dict(item.split("=") for item in last.split()[2:])
    import numpy as np

    from codegen.sim.neo6m import geodetic_to_enu

    t_end = int(fields["ticks_ms"]) / 1000  # the run's ticks start at 0
    truth = trajectory.at(np.array([t_end]))[0]
    shown = geodetic_to_enu(np.array([int(fields["lat"]) * 1e-7]), np.array([int(fields["lon"]) * 1e-7]),
                            np.array([0.0]), track.origin)[0]
    anchor_t = 31.0
    travelled = np.linalg.norm(truth[:2] - trajectory.at(np.array([anchor_t]))[0][:2])
    print(f"{mode}: travelled {travelled:.1f} m since the last fix, error {np.linalg.norm(shown[:2] - truth[:2]):.1f} m")
    assert np.all(np.isfinite(shown))
    if mode == "fused":
        _check_fix_smoothing(run.stdout, track)


def _check_fix_smoothing(stdout, track):
    """The app's metres between fixes agree with the geodesy of the NMEA positions, and an outage starts from the
    smoothed fix: after each fix the app's ENU offset is the one fused_position left for it plus the kernel's
    displacements since (in GPS mode too: the outage's first window counts)."""
    import json

    import numpy as np

    from codegen.sim.neo6m import geodetic_to_enu

    def enu(lat_e7, lon_e7):
        return geodetic_to_enu(np.array([lat_e7 * 1e-7]), np.array([lon_e7 * 1e-7]), np.array([0.0]),
                               track.origin)[0][:2]

    fixes = []
    expect = None
    checked = 0
    for line in stdout.splitlines():
        if line.startswith("FIXPOS "):
            ve, vn, de, dn, ae, an, alat, alon, lat, lon = json.loads(line[7:])
            if alat or alon:  # not the first fix: the metres from the previous anchor
                want = enu(lat, lon) - enu(alat, alon)
                assert abs(de - want[0]) < 0.005 * abs(want[0]) + 0.02 and abs(dn - want[1]) < 0.005 * abs(
                    want[1]) + 0.02, (de, dn, want)
            fixes.append((ae, an))
            expect = [ae, an]
        elif line.startswith("ENU ") and expect is not None:
            mode, e, n, out_e, out_n = json.loads(line[4:])
            expect[0] += out_e
            expect[1] += out_n
            assert abs(e - expect[0]) < 1e-4 and abs(n - expect[1]) < 1e-4, (e, n, expect)
            checked += 1
    assert len(fixes) >= 20 and checked >= 10
    offsets = np.hypot(*np.array(fixes).T)
    assert offsets.max() < 10.0 and offsets[5:].max() > 0.05  # the filter moved the start point, by metres at most
