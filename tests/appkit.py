"""Helpers for the app-level tests: a simulated run with GPS outages for the emulated board, a tap that records what
the unmodified app fed its kernel, and the replay of that record through the references (codegen/kernel).

The tap wraps, from outside the app, the kernel functions it calls and its GPS step, and writes one binary record
per event:

    C  calibration: count, moved, the samples, then 7 floats (q, gyro bias: seed kernel; q, 0, 0, 0: fused, eskf)
    P  one kernel call on m samples: m, the time the last of them was read (ticks_us), the samples (m x 6 int16),
       the intervals (m int32), the kernel's state going in (q, v, bias: 10 floats; seed), its flags after
       (fused) or the last fix's speed and the started flag going in (eskf), the 6 output floats; then the app's
       mode, anchor, shown position and ENU offset after the call
    G  eskf: a fix into the filter: its 7 arguments after the state (t_s, e, n, u, ve, vn as float32) and the
       answer
    F  a fix the app took: running (calibrated), test mode, samples read since calibration, lat, lon (1e-7 deg),
       the GPS velocity (3 floats)

The replay needs nothing from the app but this record: the reference runs on the same samples, with each fix at the
sample where the app had it.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codegen.sim import harness

TAP = r"""
import struct
import app

dump = open(DUMP, "wb")
dr = app.dr
FUSED = app.FUSED
ESKF = getattr(app, "ESKF", False)
A = None
fed = [0]


def _after(mode, m, samples, dt_us, out, before):
    a = A
    dump.write(b"P" + struct.pack("<Ii", m, a.t_prev))
    dump.write(bytes(samples))
    dump.write(bytes(dt_us))
    dump.write(struct.pack("<10f", *before))
    dump.write(struct.pack("<6f", *out))
    anchor = a.anchor or (0, 0)
    pos = a.position or (0, 0)
    dump.write(struct.pack("<Biiii3d", a.mode, anchor[0], anchor[1], pos[0], pos[1], a.enu[0], a.enu[1], a.enu[2]))


pending = []


def _wrap(orig, fused):
    def call(st, samples, dt_us, out):
        if ESKF:
            before = [st[dr.ESKF_GPS_SPEED], st[dr.ESKF_ALIGNED]] + [0.0] * 8
        elif fused:
            before = [0.0] * 10
        else:
            before = [st[i] for i in range(dr.Q, dr.Q + 4)] + [st[i] for i in range(dr.V, dr.V + 3)] + \
                     [st[i] for i in range(dr.GYRO_BIAS, dr.GYRO_BIAS + 3)]
        orig(st, samples, dt_us, out)
        if fused and not ESKF:
            before[0] = st[32]  # flags (API.md)
        fed[0] += len(dt_us)
        pending.append((len(dt_us), bytes(samples), bytes(dt_us), before, [out[i] for i in range(6)]))
    return call


def on_window(a, samples, dt_us, out):
    # the app's state after it used the output (anchor, offset, shown position)
    for m, s, d, before, o in pending:
        _after(a.mode, m, s, d, o, before)
    del pending[:]
    dump.flush()


def on_cal(a, calib, moved):
    dump.write(b"C" + struct.pack("<IB", len(calib) // 6, moved))
    dump.write(bytes(calib))
    st = a.estate if ESKF else a.fstate if FUSED else a.state
    extra = [0.0, 0.0, 0.0] if FUSED or ESKF else [st[i] for i in range(dr.GYRO_BIAS, dr.GYRO_BIAS + 3)]
    q = dr.ESKF_Q if ESKF else dr.Q
    dump.write(struct.pack("<7f", *([st[i] for i in range(q, q + 4)] + extra)))


def _fix(self, p, idx, running):
    v = self.gps_vel
    dump.write(b"F" + struct.pack("<BBIii3f", running, self.test_mode, idx, p.lat_e7, p.lon_e7, v[0], v[1], v[2]))


if hasattr(app.App, "_on_fix"):  # each fix as the app takes it, at the sample it says
    orig_on_fix = app.App._on_fix

    def on_fix(self, fix):
        running = self.imu is not None and self.state_id == 1
        orig_on_fix(self, fix)
        _fix(self, fix, self.fix_sample if running else 0, running)

    app.App._on_fix = on_fix
else:  # an app that takes its fixes in _gps, at the samples read by then
    orig_gps = app.App._gps

    def gps(self):
        before = self.fixes_seen
        idx = fed[0] + self.k
        running = self.imu is not None and self.state_id == 1
        got = orig_gps(self)
        if self.fixes_seen != before:
            _fix(self, self.nmea, idx, running)
        return got

    app.App._gps = gps
if ESKF:
    dr.eskf_process = _wrap(dr.eskf_process, True)
    orig_eskf_gps = dr.eskf_gps

    def eskf_gps(st, t, e, n, u, ve, vn):
        started = orig_eskf_gps(st, t, e, n, u, ve, vn)
        dump.write(b"G" + struct.pack("<6fB", t, e, n, u, ve, vn, started))
        return started

    dr.eskf_gps = eskf_gps
    orig_eskf_interval = dr.eskf_calibration_interval

    def eskf_calibration_interval(st, ve, vn, seconds):
        orig_eskf_interval(st, ve, vn, seconds)
        dump.write(b"I" + struct.pack("<3f", ve, vn, seconds))

    dr.eskf_calibration_interval = eskf_calibration_interval
elif FUSED:
    dr.fused_process = _wrap(dr.fused_process, True)
else:
    dr.process = _wrap(dr.process, False)
A = app.App()
A.on_window = on_window
A.on_calibrated = on_cal
print("KERNEL", app.KERNEL)
A.run()
"""


@dataclass
class Call:
    m: int
    t_last: int  # ticks_us of the last sample read before the call
    samples: np.ndarray  # (m, 6) int16
    dt: np.ndarray  # (m,) int32 microseconds
    before: np.ndarray  # seed: q, v, bias going in; fused: flags after (element 0)
    out: np.ndarray  # (6,)
    mode: int = 0
    anchor: tuple[int, int] = (0, 0)
    pos: tuple[int, int] = (0, 0)
    enu: np.ndarray = field(default_factory=lambda: np.zeros(3))
    start: int = 0  # index of its first sample in the stream after calibration
    fix: int | None = None  # index in Record.fixes of the fix the app was anchored at (the last one before)


@dataclass
class Fix:
    running: bool
    test_mode: bool
    index: int  # samples read since calibration when the app took the fix
    lat_e7: int
    lon_e7: int
    vel: np.ndarray  # (3,) m/s East, North, Up


@dataclass
class Record:
    calib: np.ndarray | None = None
    moved: int = 0
    cal_state: np.ndarray | None = None  # q (4), gyro bias (3)
    calls: list[Call] = field(default_factory=list)
    fixes: list[Fix] = field(default_factory=list)
    # eskf: each fix into the filter, after how many calls: (calls before it, (t_s, e, n, u, ve, vn), started)
    eskf_fixes: list[tuple[int, tuple, bool]] = field(default_factory=list)
    # eskf: the fix interval that spans the last calibration (ve, vn, seconds before its end), if the app had one
    eskf_interval: tuple | None = None

    def stream(self) -> tuple[np.ndarray, np.ndarray]:
        """(samples (N, 6), dt (N,)): everything the app's kernel got after calibration, in order."""
        return (np.concatenate([c.samples for c in self.calls]), np.concatenate([c.dt for c in self.calls]))


def read_record(path: Path) -> Record:
    data = path.read_bytes()
    rec = Record()
    i = 0
    start = 0
    last_fix = None
    after = struct.calcsize("<Biiii3d")
    while i < len(data):
        kind = data[i : i + 1]
        i += 1
        if kind == b"C":
            count, moved = struct.unpack_from("<IB", data, i)
            i += 5
            rec.calib = np.frombuffer(data, "<i2", count * 6, i).reshape(-1, 6)
            i += count * 12
            rec.cal_state = np.array(struct.unpack_from("<7f", data, i))
            i += 28
            rec.moved = moved
        elif kind == b"P":
            m, t_last = struct.unpack_from("<Ii", data, i)
            i += 8
            samples = np.frombuffer(data, "<i2", m * 6, i).reshape(-1, 6)
            i += m * 12
            dt = np.frombuffer(data, "<i4", m, i)
            i += m * 4
            before = np.array(struct.unpack_from("<10f", data, i))
            i += 40
            out = np.array(struct.unpack_from("<6f", data, i))
            i += 24
            mode, alat, alon, plat, plon, e, n, u = struct.unpack_from("<Biiii3d", data, i)
            i += after
            rec.calls.append(Call(m, t_last, samples, dt, before, out, mode, (alat, alon), (plat, plon),
                                  np.array([e, n, u]), start, last_fix))
            start += m
        elif kind == b"F":
            running, test, idx, lat, lon, ve, vn, vu = struct.unpack_from("<BBIii3f", data, i)
            i += struct.calcsize("<BBIii3f")
            rec.fixes.append(Fix(bool(running), bool(test), idx, lat, lon, np.array([ve, vn, vu])))
            if not test:
                last_fix = len(rec.fixes) - 1
        elif kind == b"G":
            *args, started = struct.unpack_from("<6fB", data, i)
            i += struct.calcsize("<6fB")
            rec.eskf_fixes.append((len(rec.calls), tuple(args), bool(started)))
        elif kind == b"I":
            rec.eskf_interval = struct.unpack_from("<3f", data, i)
            i += 12
        else:
            raise AssertionError(f"bad record {kind!r} at byte {i - 1}")
    return rec


def outage_world(board, scenario: str, seed: int, duration: float, outages, work: Path):
    """A simulated run of `scenario` for the emulated board: the MPU-6050 model's counts, the NEO-6M model's NMEA
    with `outages` [(start s, end s)] cut in (each epoch's sentences arrive 0.1 s after it). Returns
    (mpsim scenario dict, trajectory, GPS track)."""
    traj, track, counts_path, gps_path = harness.modelled_streams(board, scenario, seed, duration, outages, work)
    spec = harness.tbeam_scenario(
        work, counts_path, gps_path, duration, rate_hz=board.imu.achieved_sample_rate_hz,
        imu={"address": board.imu.address, "accel_range_g": board.imu.accel_range_g,
             "gyro_range_dps": board.imu.gyro_range_dps},
        display=board.display.model if board.display else None,
        pmu=None if board.power.chip == "none" else board.power.chip,
        rail=None if board.gps.power == "always_on" else board.gps.power,
        uart_id=board.uart[board.gps.uart].id)
    return spec, traj, track


def driving_world(board, work: Path, skip_s: float, duration: float):
    """The simulated car from `skip_s` s on, when it drives: the board is switched on in a moving car."""
    from codegen.sim import mpu6050, neo6m, trajectory

    traj = trajectory.make_scenario("car", seed=42, duration=skip_s + duration)
    t_us, counts = mpu6050.simulate_imu(traj, board, seed=42)
    counts = counts[int(np.searchsorted(t_us * 1e-6, skip_s)):]
    track = neo6m.simulate_gps(traj, seed=1042, rate_hz=board.gps.rate_hz)
    sentences = neo6m.nmea_sentences(track)
    per_epoch = len(sentences) // len(track.t)
    chunks = [(float(track.t[i]) - skip_s + 0.1, b"".join(sentences[i * per_epoch:(i + 1) * per_epoch]).decode())
              for i in range(len(track.t)) if skip_s <= track.t[i] and track.t[i] - skip_s + 0.1 < duration]
    spec = harness.tbeam_scenario(
        work, harness.write_counts(work / "imu.bin", counts), harness.write_stream(work / "gps.txt", chunks),
        duration, rate_hz=board.imu.achieved_sample_rate_hz,
        imu={"address": board.imu.address, "accel_range_g": board.imu.accel_range_g,
             "gyro_range_dps": board.imu.gyro_range_dps},
        display=board.display.model if board.display else None, pmu=board.power.chip,
        rail=None if board.gps.power == "always_on" else board.gps.power, uart_id=board.uart[board.gps.uart].id)
    speed = float(np.hypot(*traj.velocity_at(np.array([skip_s]))[0][:2]))
    return spec, speed


def x86_natmod(out: Path, target: Path) -> Path:
    """Build OUT/native's dr_native.mpy for x86, the 32-bit board-precision unix MicroPython the app runs on, and put
    it alone in `target` (a folder for run_app's extra_path)."""
    from codegen.tools import tool_env
    from conftest import mpy_dir, require_tool

    mpy_cross = require_tool("mpy-cross")
    require_tool("make")
    done = subprocess.run(["make", f"MPY_DIR={mpy_dir()}", "ARCH=x86", f"MPY_CROSS={mpy_cross}",
                           f"PYTHON={sys.executable}"], cwd=out / "native", capture_output=True, text=True,
                          env=tool_env())
    assert done.returncode == 0, done.stdout + done.stderr
    target.mkdir(parents=True, exist_ok=True)
    (target / "dr_native.mpy").write_bytes((out / "native" / "dr_native.mpy").read_bytes())
    return target
