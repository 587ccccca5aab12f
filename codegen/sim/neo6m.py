"""NEO-6M model: a trajectory's truth -> GPS fixes with realistic errors and outages -> NMEA sentences.

    track = simulate_gps(trajectory, seed=0, quality="open-sky", rate_hz=1.0, outages=[(60.0, 90.0)])
    lines = nmea_sentences(track)     # list[bytes], each "$GP...*HH\\r\\n": per epoch RMC, VTG, GGA, GSA

The error model (our reading of the u-blox NEO-6 data sheet, GPS.G6-HW-09005, and common field experience):
- fixes at `rate_hz` (1 Hz default, up to 5 Hz), on whole UTC seconds (plus fractions at higher rates);
- horizontal position error: first-order Gauss-Markov per axis with correlation time 60 s; sigma from the quality
  profile, 2D CEP = 1.1774 sigma: "open-sky" 2.5 m CEP, "poor" 17 m CEP (bad antenna, under trees),
  "rtk" 0 (truth, to isolate the IMU's own drift); vertical sigma 1.5x horizontal;
- Doppler velocity error: white, sigma 0.1 m/s per horizontal axis (0.2 m/s vertical) in "open-sky", x3 "poor";
- speed over ground and course over ground from the noisy velocity; the course is undefined (NaN, an empty NMEA
  field) below 0.5 m/s, as the receiver's course is noise at walking-pace stops;
- outages: (start s, end s) intervals in which the receiver reports no fix (RMC status V, GGA quality 0, empty
  fields), as when the antenna is covered or the GPS is switched off.

Positions are kept both as local ENU metres from the trajectory's start (what the benchmark compares) and as
geodetic latitude/longitude around `origin` (what NMEA carries), converted with the WGS-84 radii of curvature from
codegen.kernel.reference.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import numpy as np

from codegen.kernel.reference import radii_of_curvature
from codegen.sim.mpu6050 import gauss_markov

KNOTS_PER_MS = 3600.0 / 1852.0
CEP_PER_SIGMA = 1.1774  # 2D circular error probable of an isotropic Gaussian, in sigmas per axis
COURSE_MIN_SPEED = 0.5  # m/s
DEFAULT_ORIGIN = (40.0966916, -105.1471665, 1601.4)  # deg, deg, m (the shared walk's start, Colorado)
DEFAULT_EPOCH = _dt.datetime(2026, 3, 14, 12, 0, 0, tzinfo=_dt.timezone.utc)

QUALITY = {  # profile: (horizontal CEP m, velocity sigma m/s, satellites, HDOP)
    "rtk": (0.0, 0.0, 12, 0.6),
    "open-sky": (2.5, 0.1, 9, 0.9),
    "poor": (17.0, 0.3, 5, 3.5),
}
POSITION_TAU_S = 60.0


@dataclass
class GpsTrack:
    """One fix per epoch. NaN where a value is undefined; `valid` False during outages."""

    t: np.ndarray  # (K,) s since the start of the run (epoch time of the fix)
    valid: np.ndarray  # (K,) bool
    enu: np.ndarray  # (K, 3) m, fix position in the run's ENU frame
    vel: np.ndarray  # (K, 3) m/s, Doppler velocity ENU (as the receiver measures it)
    lat: np.ndarray  # (K,) deg
    lon: np.ndarray  # (K,) deg
    alt: np.ndarray  # (K,) m; GGA reports it as altitude with a geoid separation of 0 (so MSL = ellipsoid)
    speed: np.ndarray  # (K,) m/s over ground
    course: np.ndarray  # (K,) deg from true North, clockwise; NaN when undefined
    sats: np.ndarray  # (K,) int
    hdop: np.ndarray  # (K,) float
    origin: tuple[float, float, float]
    epoch: _dt.datetime  # UTC at t = 0

    def device_velocity(self) -> np.ndarray:
        """Horizontal ENU velocity as the device can form it from NMEA (speed + course; 0 where course is empty)."""
        c = np.radians(np.nan_to_num(self.course))
        s = np.where(np.isnan(self.course), 0.0, self.speed)
        return np.stack([s * np.sin(c), s * np.cos(c)], axis=-1)

    def last_valid_before(self, times: np.ndarray) -> np.ndarray:
        """Index of the last valid fix with t < time, per time (-1 where none)."""
        good = np.flatnonzero(self.valid)
        pos = np.searchsorted(self.t[good], np.asarray(times, dtype=float), side="left") - 1
        return np.where(pos >= 0, good[np.maximum(pos, 0)], -1)


def enu_to_geodetic(enu: np.ndarray, origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local ENU metres around origin (lat, lon deg, h m) -> lat, lon (deg), h (m). Radii at the origin."""
    lat0, lon0, h0 = origin
    m, n = radii_of_curvature(lat0)
    lat = lat0 + np.degrees(enu[..., 1] / (m + h0))
    lon = lon0 + np.degrees(enu[..., 0] / ((n + h0) * np.cos(np.radians(lat0))))
    return lat, lon, h0 + enu[..., 2]


def geodetic_to_enu(lat, lon, h, origin) -> np.ndarray:
    """Inverse of enu_to_geodetic."""
    lat0, lon0, h0 = origin
    m, n = radii_of_curvature(lat0)
    north = np.radians(np.asarray(lat) - lat0) * (m + h0)
    east = np.radians(np.asarray(lon) - lon0) * (n + h0) * np.cos(np.radians(lat0))
    return np.stack([east, north, np.asarray(h, dtype=float) - h0], axis=-1)


def simulate_gps(trajectory, seed: int = 0, quality: str = "open-sky", rate_hz: float = 1.0,
                 outages=(), origin=DEFAULT_ORIGIN, epoch=DEFAULT_EPOCH, times=None) -> GpsTrack:
    """NEO-6M fixes for `trajectory` (a codegen.sim.trajectory.Trajectory or anything with .at/.velocity_at/
    .duration). outages: iterable of (start s, end s) with no fix. times: the fix epochs (s), evenly spaced at
    1/rate_hz, instead of whole seconds from 0 (the replay uses the recording's own epochs)."""
    if quality not in QUALITY:
        raise ValueError(f"unknown GPS quality {quality!r}; choose from {', '.join(QUALITY)}")
    if not 0 < rate_hz <= 5:
        raise ValueError(f"NEO-6M rate {rate_hz} Hz is outside 0..5 Hz")
    cep, vel_sigma, sats, hdop = QUALITY[quality]
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, trajectory.duration + 1e-9, 1.0 / rate_hz) if times is None else np.asarray(times, float)
    k = len(t)
    sigma = cep / CEP_PER_SIGMA
    pos_err = gauss_markov(rng, k, 1.0 / rate_hz, 1.0, POSITION_TAU_S) * [sigma, sigma, 1.5 * sigma]
    vel_err = rng.standard_normal((k, 3)) * [vel_sigma, vel_sigma, 2 * vel_sigma]
    enu = trajectory.at(t) + pos_err
    vel = trajectory.velocity_at(t) + vel_err
    speed = np.hypot(vel[:, 0], vel[:, 1])
    course = np.where(speed >= COURSE_MIN_SPEED, np.degrees(np.arctan2(vel[:, 0], vel[:, 1])) % 360.0, np.nan)
    valid = np.ones(k, dtype=bool)
    for start, end in outages:
        valid &= ~((t >= start) & (t < end))
    lat, lon, alt = enu_to_geodetic(enu, origin)
    return GpsTrack(t, valid, enu, vel, lat, lon, alt, speed, course,
                    np.full(k, sats), np.full(k, hdop), tuple(origin), epoch)


# ------------------------------------------------------------------------------------------------------- NMEA
def nmea_checksum(body: str) -> str:
    """XOR of the bytes between '$' and '*', two upper-case hex digits."""
    c = 0
    for ch in body.encode("ascii"):
        c ^= ch
    return f"{c:02X}"


def _sentence(body: str) -> bytes:
    return f"${body}*{nmea_checksum(body)}\r\n".encode("ascii")


def _degrees_minutes(value: float, width: int) -> str:
    """|value| as dddmm.mmmmm, rounded to 1e-5 minute with the carry into degrees (59.999996' -> next degree)."""
    units = int(round(abs(value) * 60 * 100000))  # 1e-5 minute
    degrees, minutes = divmod(units, 60 * 100000)
    return f"{degrees:0{width}d}{minutes // 100000:02d}.{minutes % 100000:05d}"


def _lat_field(lat: float) -> str:
    return f"{_degrees_minutes(lat, 2)},{'N' if lat >= 0 else 'S'}"


def _lon_field(lon: float) -> str:
    return f"{_degrees_minutes(lon, 3)},{'E' if lon >= 0 else 'W'}"


def nmea_sentences(track: GpsTrack) -> list[bytes]:
    """NMEA 2.3 sentences as a NEO-6M sends them, per epoch: RMC, VTG, GGA, GSA (talker GP), CR LF terminated.

    Positions with 5 decimals of minutes (~2 cm), speed in knots (RMC, VTG) and km/h (VTG), course in degrees
    true (empty when undefined), altitude in GGA. Epochs without a fix give the receiver's no-fix forms:
    RMC status V, VTG mode N, GGA quality 0, GSA fix type 1, with empty data fields.
    """
    out: list[bytes] = []
    for i in range(len(track.t)):
        when = track.epoch + _dt.timedelta(seconds=float(track.t[i]))
        hms = when.strftime("%H%M%S") + f".{when.microsecond // 10000:02d}"
        dmy = when.strftime("%d%m%y")
        if track.valid[i]:
            knots = track.speed[i] * KNOTS_PER_MS
            kmh = track.speed[i] * 3.6
            crs = "" if np.isnan(track.course[i]) else f"{track.course[i]:.2f}"
            latf, lonf = _lat_field(track.lat[i]), _lon_field(track.lon[i])
            out.append(_sentence(f"GPRMC,{hms},A,{latf},{lonf},{knots:.3f},{crs},{dmy},,,A"))
            out.append(_sentence(f"GPVTG,{crs},T,,M,{knots:.3f},N,{kmh:.3f},K,A"))
            out.append(_sentence(f"GPGGA,{hms},{latf},{lonf},1,{track.sats[i]:02d},{track.hdop[i]:.2f},"
                                 f"{track.alt[i]:.1f},M,0.0,M,,"))
            svs = ",".join(f"{sv:02d}" for sv in range(1, track.sats[i] + 1)) + "," * (12 - track.sats[i])
            pdop, vdop = track.hdop[i] * 1.6, track.hdop[i] * 1.3
            out.append(_sentence(f"GPGSA,A,3,{svs},{pdop:.2f},{track.hdop[i]:.2f},{vdop:.2f}"))
        else:
            out.append(_sentence(f"GPRMC,{hms},V,,,,,,,{dmy},,,N"))
            out.append(_sentence("GPVTG,,,,,,,,,N"))
            out.append(_sentence(f"GPGGA,{hms},,,,,0,00,99.99,,,,,,"))
            out.append(_sentence("GPGSA,A,1,,,,,,,,,,,,,99.99,99.99,99.99"))
    return out


@dataclass
class ParsedFix:
    time: str
    valid: bool
    lat: float | None
    lon: float | None
    speed: float | None  # m/s
    course: float | None  # deg
    alt: float | None


def parse_nmea(lines: list[bytes]) -> list[ParsedFix]:
    """A small strict reader of our own RMC + GGA output (for the simulator's round-trip tests): checks every
    checksum and returns one fix per RMC, with the altitude of the GGA that follows it."""
    fixes: list[ParsedFix] = []
    for raw in lines:
        text = raw.decode("ascii").strip()
        if not text.startswith("$") or "*" not in text:
            raise ValueError(f"not an NMEA sentence: {text!r}")
        body, check = text[1:].split("*")
        if nmea_checksum(body) != check:
            raise ValueError(f"bad checksum in {text!r}")
        f = body.split(",")
        if f[0] == "GPRMC":
            ok = f[2] == "A"
            lat = lon = None
            if ok:
                lat = (int(f[3][:2]) + float(f[3][2:]) / 60) * (1 if f[4] == "N" else -1)
                lon = (int(f[5][:3]) + float(f[5][3:]) / 60) * (1 if f[6] == "E" else -1)
            fixes.append(ParsedFix(f[1], ok, lat, lon, float(f[7]) / KNOTS_PER_MS if f[7] else None,
                                   float(f[8]) if f[8] else None, None))
        elif f[0] == "GPGGA" and fixes and f[9]:
            fixes[-1].alt = float(f[9])
    return fixes
