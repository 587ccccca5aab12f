"""The reference pipeline: NumPy, float64, the executable specification of the dead-reckoning kernel.

The C kernel (native_ext/) and the generated MicroPython fallback compute the same thing in float32; the tests hold
them to this module. Read it next to the seed's equations:

1. gyro bias subtraction and scaling to rad/s; accel scaling to m/s^2;
2. orientation from the gyro, as a unit quaternion q = [w, x, y, z] that turns body vectors into ENU vectors,
   starting at the tilt found at calibration:  q_{k+1} = q_k (x) exp(omega_k * dt_k / 2);
3. a_enu,k = R(q_k) f_k - [0, 0, g];
4. block median per axis over blocks of b samples (numpy.median: an even b gives the mean of the middle two);
5. deadband: a component with |a| < l becomes exactly 0;
6. zero-order hold integration:  v_{k+1} = v_k + a_k dt_k,  p_{k+1} = p_k + v_k dt_k + a_k dt_k^2 / 2;
7. the window's ENU displacement, and ENU metres -> latitude/longitude offset from an anchor (WGS-84 radii).

Conventions (DESIGN.md): sensor/body frame xyz after the board's axis remap, earth frame ENU, specific force
(+1 g up at rest), gravity 9.80665 m/s^2. Raw samples are int16 counts [ax, ay, az, gx, gy, gz].
The other engineers import `integrate_zoh` and the rotation helpers from here: keep their names stable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STANDARD_GRAVITY = 9.80665  # m/s^2
WGS84_A = 6378137.0  # m, semi-major axis
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
DEG_E7 = 1e7  # integer units per degree of the anchor representation (1e-7 degree)


# --------------------------------------------------------------------------------------------- integration (step 6)
def integrate_zoh(acc, dt, v0=(0.0, 0.0, 0.0)):
    """Zero-order-hold double integration.

    acc: (N, 3) m/s^2, held constant from sample k for dt[k] seconds; dt: (N,) s; v0: (3,) m/s.
    Returns (vel, pos), each (N+1, 3): vel[k] = v(t_k) in m/s, pos[k] = p(t_k) in m with pos[0] = 0.
        v_{k+1} = v_k + a_k dt_k
        p_{k+1} = p_k + v_k dt_k + a_k dt_k^2 / 2
    """
    acc = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    dt = np.asarray(dt, dtype=np.float64).reshape(-1)
    if len(dt) != len(acc):
        raise ValueError(f"acc has {len(acc)} samples but dt has {len(dt)}")
    v0 = np.asarray(v0, dtype=np.float64).reshape(3)
    dv = acc * dt[:, None]
    vel = np.empty((len(acc) + 1, 3))
    vel[0] = v0
    vel[1:] = v0 + np.cumsum(dv, axis=0)
    dp = vel[:-1] * dt[:, None] + 0.5 * acc * (dt * dt)[:, None]
    pos = np.zeros((len(acc) + 1, 3))
    pos[1:] = np.cumsum(dp, axis=0)
    return vel, pos


# --------------------------------------------------------------------------------------------- rotations
def quat_multiply(p, q):
    """Hamilton product p (x) q of quaternions [w, x, y, z]; broadcasts over leading axes."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_normalise(q):
    """q / |q| (the unit quaternion of the same rotation)."""
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_conjugate(q):
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q):
    """Rotation matrix R (3x3, or (..., 3, 3)) of the unit quaternion q: v_enu = R @ v_body."""
    w, x, y, z = np.moveaxis(quat_normalise(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_quat(r):
    """Unit quaternion [w, x, y, z] (w >= 0) of a 3x3 rotation matrix (Shepperd's method, stable for all angles)."""
    r = np.asarray(r, dtype=np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    candidates = [trace, r[0, 0], r[1, 1], r[2, 2]]
    i = int(np.argmax(candidates))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return quat_normalise(q if q[0] >= 0 else -q)


def quat_rotate(q, v):
    """Rotate vector(s) v (..., 3) from body to ENU by unit quaternion q."""
    return np.einsum("...ij,...j->...i", quat_to_matrix(q), np.asarray(v, dtype=np.float64))


def quat_from_rotvec(rotvec):
    """exp(rotvec / 2): the unit quaternion turning by |rotvec| rad about rotvec's direction."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle, continuous at 0
    k = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), k * rotvec], axis=-1)


def gyro_update(q, omega, dt):
    """One orientation step: q (x) exp(omega * dt / 2); omega body rate (3,) rad/s, dt s. Returns unit q."""
    return quat_normalise(quat_multiply(q, quat_from_rotvec(np.asarray(omega, dtype=np.float64) * dt)))


def gyro_integrate(q0, omega, dt):
    """Orientations q_0..q_N (N+1, 4) from q0 by the body rates omega (N, 3) rad/s held for dt (N,) s."""
    omega = np.asarray(omega, dtype=np.float64).reshape(-1, 3)
    dt = np.asarray(dt, dtype=np.float64).reshape(-1)
    out = np.empty((len(omega) + 1, 4))
    out[0] = quat_normalise(q0)
    for k in range(len(omega)):
        out[k + 1] = gyro_update(out[k], omega[k], dt[k])
    return out


def tilt_from_gravity(f):
    """Shortest-arc unit quaternion turning the measured specific force f (body, any scale) onto ENU up [0, 0, 1].

    Yaw is left at zero (the rotation has no component about up). A device upside down (f along -z) turns 180
    degrees about x.
        q = normalise([|f| + f_z, f_y, -f_x, 0])
    """
    f = np.asarray(f, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(f)
    if norm == 0:
        raise ValueError("no gravity in the calibration samples (zero specific force)")
    w = norm + f[2]
    if w <= 1e-6 * norm:
        return np.array([0.0, 1.0, 0.0, 0.0])
    return quat_normalise(np.array([w, f[1], -f[0], 0.0]))


def quat_yaw(yaw):
    """Unit quaternion of a rotation by yaw rad about ENU up (counter-clockwise seen from above)."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


# --------------------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class KernelConfig:
    """The kernel's run-time parameters (the C `dr_config`), in the board's units."""

    block: int = 16  # b, samples per block median
    window: int = 512  # n, samples per processing window
    accel_lsb_per_g: float = 16384.0  # counts per g
    gyro_lsb_per_dps: float = 131.0  # counts per degree/s
    deadband_g: float = 0.03125  # l, g
    motion_threshold_g: float = 0.02  # calibration accel standard deviation limit, g
    axis_map: tuple = ((0, 1), (1, 1), (2, 1))  # per body axis: (sensor axis, sign)

    @classmethod
    def from_board(cls, board) -> "KernelConfig":
        alg = board.algorithm
        return cls(
            block=alg.block,
            window=alg.window,
            accel_lsb_per_g=board.imu.accel_lsb_per_g,
            gyro_lsb_per_dps=board.imu.gyro_lsb_per_dps,
            deadband_g=alg.deadband_g,
            motion_threshold_g=alg.motion_threshold_g,
            axis_map=tuple(tuple(a) for a in board.imu.axis_map),
        )

    @property
    def accel_ms2_per_lsb(self) -> float:
        return STANDARD_GRAVITY / self.accel_lsb_per_g

    @property
    def gyro_rads_per_lsb(self) -> float:
        return np.pi / 180.0 / self.gyro_lsb_per_dps

    @property
    def deadband_ms2(self) -> float:
        return self.deadband_g * STANDARD_GRAVITY


def remap_axes(counts, axis_map):
    """Sensor-frame samples (N, 6) -> body frame, applying (source axis, sign) to accel and gyro alike."""
    counts = np.asarray(counts, dtype=np.float64).reshape(-1, 6)
    out = np.empty_like(counts)
    for i, (src, sign) in enumerate(axis_map):
        out[:, i] = sign * counts[:, src]
        out[:, 3 + i] = sign * counts[:, 3 + src]
    return out


# --------------------------------------------------------------------------------------------- calibration
@dataclass
class Calibration:
    q: np.ndarray  # (4,) initial orientation (tilt, yaw 0)
    gyro_bias_lsb: np.ndarray  # (3,) body-frame gyro bias, counts
    accel_std_g: np.ndarray  # (3,) population standard deviation of the accel, g
    moved: bool  # any accel standard deviation above the motion threshold


def calibrate(samples, cfg: KernelConfig = KernelConfig()) -> Calibration:
    """From raw samples (M, 6) at rest: tilt from the mean specific force, gyro bias, and the 'moved' verdict."""
    body = remap_axes(samples, cfg.axis_map)
    if len(body) == 0:
        raise ValueError("calibration needs at least one sample")
    mean = body.mean(axis=0)
    std_g = body[:, :3].std(axis=0) / cfg.accel_lsb_per_g
    return Calibration(
        q=tilt_from_gravity(mean[:3]),
        gyro_bias_lsb=mean[3:].copy(),
        accel_std_g=std_g,
        moved=bool(np.any(std_g > cfg.motion_threshold_g)),
    )


# --------------------------------------------------------------------------------------------- window (steps 1-6)
def block_median(x, b):
    """Per-axis median of consecutive blocks of b samples: (N, k) -> (N // b, k), numpy.median semantics."""
    x = np.asarray(x)
    if b < 1 or len(x) % b:
        raise ValueError(f"{len(x)} samples are not a whole number of blocks of {b}")
    return np.median(x.reshape(len(x) // b, b, *x.shape[1:]), axis=1)


def deadband(a, limit):
    """Components with |a| < limit become exactly 0."""
    a = np.array(a, dtype=np.float64, copy=True)
    a[np.abs(a) < limit] = 0.0
    return a


def enu_acceleration(samples, dt, q0, gyro_bias_lsb, cfg: KernelConfig = KernelConfig()):
    """Steps 1-3: per-sample ENU acceleration (N, 3) m/s^2 (gravity removed) and orientations q_0..q_N (N+1, 4)."""
    body = remap_axes(samples, cfg.axis_map)
    f = body[:, :3] * cfg.accel_ms2_per_lsb
    omega = (body[:, 3:] - np.asarray(gyro_bias_lsb, dtype=np.float64)) * cfg.gyro_rads_per_lsb
    qs = gyro_integrate(q0, omega, dt)
    a = np.einsum("kij,kj->ki", quat_to_matrix(qs[:-1]), f)
    a[:, 2] -= STANDARD_GRAVITY
    return a, qs


@dataclass
class WindowResult:
    displacement: np.ndarray  # (3,) ENU m over the window
    velocity: np.ndarray  # (3,) ENU m/s at the window's end
    q: np.ndarray  # (4,) orientation at the window's end
    medians: np.ndarray  # (N // b, 3) block medians after the deadband, m/s^2
    raw_medians: np.ndarray  # (N // b, 3) block medians before the deadband, m/s^2


def process_window(samples, dt_us, q0, v0, gyro_bias_lsb, cfg: KernelConfig = KernelConfig()) -> WindowResult:
    """One window: raw samples (N, 6) int16 counts, dt_us (N,) hold time of each sample in us (sample k to k+1),
    q0 orientation at the first sample, v0 (3,) ENU m/s. N must be a multiple of cfg.block."""
    samples = np.asarray(samples).reshape(-1, 6)
    dt = np.asarray(dt_us, dtype=np.float64).reshape(-1) * 1e-6
    if len(dt) != len(samples):
        raise ValueError(f"{len(samples)} samples but {len(dt)} time steps")
    if len(samples) % cfg.block:
        raise ValueError(f"window of {len(samples)} samples is not a multiple of the block size {cfg.block}")
    a, qs = enu_acceleration(samples, dt, q0, gyro_bias_lsb, cfg)
    raw = block_median(a, cfg.block)
    med = deadband(raw, cfg.deadband_ms2)
    held = np.repeat(med, cfg.block, axis=0)
    vel, pos = integrate_zoh(held, dt, v0)
    return WindowResult(displacement=pos[-1], velocity=vel[-1], q=qs[-1], medians=med, raw_medians=raw)


# --------------------------------------------------------------------------------------------- geodesy (step 7)
def radii_of_curvature(lat_deg):
    """WGS-84 meridian radius M and prime-vertical radius N (m) at geodetic latitude lat_deg."""
    s = np.sin(np.radians(lat_deg))
    w2 = 1.0 - WGS84_E2 * s * s
    n = WGS84_A / np.sqrt(w2)
    m = WGS84_A * (1.0 - WGS84_E2) / (w2 * np.sqrt(w2))
    return m, n


def offset_latlon_e7(lat_e7: int, lon_e7: int, east_m: float, north_m: float) -> tuple[int, int]:
    """Anchor (integers of 1e-7 degree) + a local ENU offset (m) -> new (lat_e7, lon_e7), rounded to nearest.

    dlat = north / M(lat),  dlon = east / (N(lat) cos lat), radians; the radii are taken at the anchor (metres to
    kilometres from it, the flat-earth error is far below the 1e-7 degree = 1.1 cm unit)."""
    lat = lat_e7 / DEG_E7
    m, n = radii_of_curvature(lat)
    dlat = np.degrees(north_m / m) * DEG_E7
    dlon = np.degrees(east_m / (n * np.cos(np.radians(lat)))) * DEG_E7
    new_lon = lon_e7 + int(np.round(dlon))
    if new_lon > 1_800_000_000:
        new_lon -= 3_600_000_000
    elif new_lon < -1_800_000_000:
        new_lon += 3_600_000_000
    return lat_e7 + int(np.round(dlat)), new_lon
