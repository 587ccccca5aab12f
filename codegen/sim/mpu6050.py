"""MPU-6050 model: a trajectory's exact truth -> the raw int16 counts the app reads, with timestamps.

    t_us, counts = simulate_imu(trajectory, board, seed=0)
    # t_us:   (N,) int64, microseconds since the start of the run, when the app read each sample
    # counts: (N, 6) int16, [ax, ay, az, gx, gy, gz] in the SENSOR frame, exactly as registers 0x3B..0x48
    #         (ACCEL_XOUT..GYRO_ZOUT, big-endian on the wire) would give them at the board's configured ranges

This is the stream the app's emulated MPU-6050 serves from its registers, and what the reference
pipeline consumes. The board's `imu.axes` remap is undone here (the truth is in the board frame; the chip reports
its own axes), so `codegen.kernel.reference.remap_axes` brings the counts back to the board frame.

The error model (`MpuErrors`, defaults from the MPU-6050 product specification rev 3.4 unless marked):
- white noise: accel 400 ug/sqrt(Hz), gyro 0.005 deg/s/sqrt(Hz), one-sided densities; added at the 1 kHz internal
  rate with sigma = density * sqrt(rate / 2), then low-pass filtered by the DLPF, so the output's Allan deviation
  in the white region is density / sqrt(2 tau);
- per-device constants drawn from the seed: zero-g offset uniform in +-50 mg (x, y) and +-80 mg (z), gyro
  zero-rate offset uniform in +-20 deg/s, sensitivity error uniform +-3 %, cross-axis sensitivity uniform +-2 %;
- in-run bias drift (what calibration cannot remove; our choice, not a datasheet figure): first-order
  Gauss-Markov, gyro sigma 0.01 deg/s with tau 100 s, accel sigma 1 mg with tau 200 s;
- DLPF: second-order Butterworth at the DLPF_CFG bandwidth (260/184/94/44/21/10/5 Hz), run at the 1 kHz rate;
- sampling: the app reads the registers every 1/sample_rate_hz s with timing jitter (Gaussian, sigma 100 us,
  our choice) and gets the latest 1 kHz output sample; timestamps are the read times, as ticks_us gives them;
- quantisation to int16 at the configured range (LSB per g / per deg/s from codegen.board.model), saturation at
  -32768 / +32767.

`MpuErrors.ideal()` switches every error off (exact quantised truth, no jitter), for invariant tests.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import butter, group_delay, lfilter, lfilter_zi

from codegen.board.model import (
    ACCEL_LSB_PER_G,
    DLPF_BANDWIDTH_HZ,
    GYRO_LSB_PER_DPS,
    STANDARD_GRAVITY,
)

INT16_MIN, INT16_MAX = -32768, 32767


@dataclass(frozen=True)
class MpuErrors:
    accel_noise_ug_rthz: float = 400.0  # ug/sqrt(Hz)
    gyro_noise_dps_rthz: float = 0.005  # deg/s/sqrt(Hz)
    accel_offset_mg: tuple[float, float, float] = (50.0, 50.0, 80.0)  # +- bound per axis, mg
    gyro_offset_dps: float = 20.0  # +- bound, deg/s
    sensitivity_pct: float = 3.0  # +- bound, %
    cross_axis_pct: float = 2.0  # +- bound, %
    gyro_drift_dps: float = 0.01  # Gauss-Markov sigma, deg/s
    gyro_drift_tau_s: float = 100.0
    accel_drift_mg: float = 1.0  # Gauss-Markov sigma, mg
    accel_drift_tau_s: float = 200.0
    jitter_us: float = 100.0  # sigma of the read time, us
    dlpf: bool = True

    @classmethod
    def ideal(cls) -> "MpuErrors":
        return cls(0.0, 0.0, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0, 0.0, 100.0, 0.0, 200.0, 0.0, False)

    def noise_only(self) -> "MpuErrors":
        """White noise (and the DLPF) only: for Allan-deviation checks."""
        return replace(MpuErrors.ideal(), accel_noise_ug_rthz=self.accel_noise_ug_rthz,
                       gyro_noise_dps_rthz=self.gyro_noise_dps_rthz, dlpf=self.dlpf)


@dataclass(frozen=True)
class DeviceErrors:
    """The constants one simulated chip was drawn with (SI units, sensor frame)."""

    accel_offset: np.ndarray  # (3,) m/s^2
    gyro_offset: np.ndarray  # (3,) rad/s
    accel_matrix: np.ndarray  # (3, 3) scale and cross-axis: measured = M @ true
    gyro_matrix: np.ndarray  # (3, 3)


def draw_device(errors: MpuErrors, rng: np.random.Generator) -> DeviceErrors:
    def matrix() -> np.ndarray:
        m = np.eye(3) + np.diag(rng.uniform(-1, 1, 3) * errors.sensitivity_pct / 100.0)
        off = rng.uniform(-1, 1, (3, 3)) * errors.cross_axis_pct / 100.0
        np.fill_diagonal(off, 0.0)
        return m + off

    accel_offset = rng.uniform(-1, 1, 3) * np.asarray(errors.accel_offset_mg) * 1e-3 * STANDARD_GRAVITY
    gyro_offset = np.radians(rng.uniform(-1, 1, 3) * errors.gyro_offset_dps)
    return DeviceErrors(accel_offset, gyro_offset, matrix(), matrix())


def dlpf_delay_s(bandwidth_hz: float, rate_hz: float, at_hz: float = 1.0) -> float:
    """How late dlpf_filter's output runs behind its input at `at_hz` (s): its group delay there, ~1/(sqrt(2) pi f_c)
    well below the cut-off (5.1 ms at the 44 Hz DLPF_CFG 3; the datasheet gives 4.9 ms)."""
    cutoff = min(bandwidth_hz, 0.45 * rate_hz)
    b, a = butter(2, cutoff, fs=rate_hz)
    _, samples = group_delay((b, a), w=[at_hz], fs=rate_hz)
    return float(samples[0]) / rate_hz


def gauss_markov(rng: np.random.Generator, n: int, dt: float, sigma: float, tau: float, dims: int = 3) -> np.ndarray:
    """First-order Gauss-Markov process (stationary, std sigma, correlation time tau), (n, dims)."""
    if sigma == 0.0:
        return np.zeros((n, dims))
    phi = np.exp(-dt / tau)
    drive = rng.standard_normal((n, dims)) * sigma * np.sqrt(1.0 - phi * phi)
    drive[0] = rng.standard_normal(dims) * sigma
    return lfilter([1.0], [1.0, -phi], drive, axis=0)


def dlpf_filter(x: np.ndarray, bandwidth_hz: float, rate_hz: float) -> np.ndarray:
    """Second-order Butterworth low-pass along axis 0, started in steady state (no start-up transient)."""
    cutoff = min(bandwidth_hz, 0.45 * rate_hz)
    b, a = butter(2, cutoff, fs=rate_hz)
    zi = lfilter_zi(b, a)[:, None] * x[:1]
    y, _ = lfilter(b, a, x, axis=0, zi=zi)
    return y


def board_to_sensor(v_board: np.ndarray, axis_map) -> np.ndarray:
    """Invert the board's axis remap: board[i] = sign_i * sensor[src_i]  =>  sensor[src_i] = sign_i * board[i]."""
    out = np.empty_like(v_board)
    for i, (src, sign) in enumerate(axis_map):
        out[..., src] = sign * v_board[..., i]
    return out


def read_times(duration_s: float, rate_hz: float, jitter_us: float, rng: np.random.Generator) -> np.ndarray:
    """The app's register-read times in us (int64, strictly increasing) for a run of duration_s."""
    n = int(np.floor(duration_s * rate_hz)) + 1
    nominal = np.arange(n) * (1e6 / rate_hz)
    if jitter_us > 0:
        nominal = nominal + np.abs(rng.normal(0.0, jitter_us, n))  # a read is late, never early
    t_us = np.round(nominal).astype(np.int64)
    t_us = np.maximum.accumulate(t_us)
    t_us[1:] = np.maximum(t_us[1:], t_us[:-1] + 1)
    return t_us[t_us <= int(duration_s * 1e6)]


def simulate_imu(trajectory, board, seed: int = 0, errors: MpuErrors | None = None, device: DeviceErrors | None = None):
    """Raw MPU-6050 samples for `trajectory` as the board's app would read them.

    board: a codegen.board.model.Board (ranges, DLPF, sample rate and axis remap come from board.imu).
    Returns (t_us (N,) int64, counts (N, 6) int16 [ax, ay, az, gx, gy, gz], sensor frame).
    """
    errors = MpuErrors() if errors is None else errors
    imu = board.imu
    rng = np.random.default_rng(seed)
    device = draw_device(errors, rng) if device is None else device
    rate = trajectory.rate_hz
    n = len(trajectory.t)
    dt = 1.0 / rate

    f = board_to_sensor(trajectory.specific_force(), imu.axis_map)
    w = board_to_sensor(trajectory.gyro, imu.axis_map)
    f = f @ device.accel_matrix.T + device.accel_offset
    w = w @ device.gyro_matrix.T + device.gyro_offset
    f += gauss_markov(rng, n, dt, errors.accel_drift_mg * 1e-3 * STANDARD_GRAVITY, errors.accel_drift_tau_s)
    w += gauss_markov(rng, n, dt, np.radians(errors.gyro_drift_dps), errors.gyro_drift_tau_s)
    f += rng.standard_normal((n, 3)) * errors.accel_noise_ug_rthz * 1e-6 * STANDARD_GRAVITY * np.sqrt(rate / 2)
    w += rng.standard_normal((n, 3)) * np.radians(errors.gyro_noise_dps_rthz) * np.sqrt(rate / 2)
    if errors.dlpf and imu.dlpf in DLPF_BANDWIDTH_HZ:
        bandwidth = DLPF_BANDWIDTH_HZ[imu.dlpf]
        f = dlpf_filter(f, bandwidth, rate)
        w = dlpf_filter(w, bandwidth, rate)

    t_us = read_times(trajectory.duration, imu.sample_rate_hz, errors.jitter_us, rng)
    # the register holds the newest internal sample: index floor(t * rate)
    idx = np.minimum((t_us * rate // 1_000_000).astype(np.int64), n - 1)
    accel_counts = f[idx] / STANDARD_GRAVITY * ACCEL_LSB_PER_G[imu.accel_range_g]
    gyro_counts = np.degrees(w[idx]) * GYRO_LSB_PER_DPS[imu.gyro_range_dps]
    counts = np.clip(np.round(np.hstack([accel_counts, gyro_counts])), INT16_MIN, INT16_MAX).astype(np.int16)
    return t_us, counts


def degrade_recording(t_s, accel_g, gyro_rad_s, board, seed: int = 0, errors: MpuErrors | None = None,
                      already_ug_rthz: float = 70.0):
    """Make a real IMU recording look like an MPU-6050 on `board`: add the noise the recording lacks (densities
    subtract in quadrature), the device offsets/scale/cross-axis and the drift, then quantise to int16 counts.

    t_s (N,) s; accel_g (N, 3) g; gyro_rad_s (N, 3) rad/s, already in the board frame.
    Returns (t_us int64 from 0, counts (N, 6) int16, sensor frame).
    """
    errors = MpuErrors() if errors is None else errors
    imu = board.imu
    rng = np.random.default_rng(seed)
    device = draw_device(errors, rng)
    t_s = np.asarray(t_s, dtype=float)
    n = len(t_s)
    rate = (n - 1) / (t_s[-1] - t_s[0])
    dt = 1.0 / rate
    f = board_to_sensor(np.asarray(accel_g, dtype=float) * STANDARD_GRAVITY, imu.axis_map)
    w = board_to_sensor(np.asarray(gyro_rad_s, dtype=float), imu.axis_map)
    f = f @ device.accel_matrix.T + device.accel_offset
    w = w @ device.gyro_matrix.T + device.gyro_offset
    f += gauss_markov(rng, n, dt, errors.accel_drift_mg * 1e-3 * STANDARD_GRAVITY, errors.accel_drift_tau_s)
    w += gauss_markov(rng, n, dt, np.radians(errors.gyro_drift_dps), errors.gyro_drift_tau_s)
    extra_ug = np.sqrt(max(errors.accel_noise_ug_rthz**2 - already_ug_rthz**2, 0.0))
    f += rng.standard_normal((n, 3)) * extra_ug * 1e-6 * STANDARD_GRAVITY * np.sqrt(rate / 2)
    w += rng.standard_normal((n, 3)) * np.radians(errors.gyro_noise_dps_rthz) * np.sqrt(rate / 2)
    accel_counts = f / STANDARD_GRAVITY * ACCEL_LSB_PER_G[imu.accel_range_g]
    gyro_counts = np.degrees(w) * GYRO_LSB_PER_DPS[imu.gyro_range_dps]
    counts = np.clip(np.round(np.hstack([accel_counts, gyro_counts])), INT16_MIN, INT16_MAX).astype(np.int16)
    t_us = np.round((t_s - t_s[0]) * 1e6).astype(np.int64)
    return t_us, counts


def counts_to_si(counts, board):
    """int16 counts (N, 6) sensor frame -> (specific force m/s^2, angular rate rad/s), both (N, 3) sensor frame."""
    counts = np.asarray(counts, dtype=float)
    f = counts[:, :3] / ACCEL_LSB_PER_G[board.imu.accel_range_g] * STANDARD_GRAVITY
    w = np.radians(counts[:, 3:] / GYRO_LSB_PER_DPS[board.imu.gyro_range_dps])
    return f, w
