"""WGS-84 geodetic <-> local East-North-Up about a reference point (exact, through ECEF)."""

from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0  # m, semi-major axis
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat_deg, lon_deg, h) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack(
        [(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon), (n * (1.0 - WGS84_E2) + h) * np.sin(lat)],
        axis=-1,
    )


def _enu_matrix(lat0_deg: float, lon0_deg: float) -> np.ndarray:
    lat, lon = np.radians(lat0_deg), np.radians(lon0_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def geodetic_to_enu(lat_deg, lon_deg, h, origin: tuple[float, float, float]) -> np.ndarray:
    """(N,3) ENU metres of the points relative to origin (lat0, lon0, h0)."""
    ecef = geodetic_to_ecef(np.asarray(lat_deg), np.asarray(lon_deg), np.asarray(h))
    ecef0 = geodetic_to_ecef(*origin)
    return (ecef - ecef0) @ _enu_matrix(origin[0], origin[1]).T


def enu_to_geodetic(enu: np.ndarray, origin: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of `geodetic_to_enu` (Bowring's iteration on ECEF): lat, lon in degrees and h in metres."""
    return ecef_to_geodetic(np.asarray(enu) @ _enu_matrix(origin[0], origin[1]) + geodetic_to_ecef(*origin))


def ecef_to_geodetic(ecef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS-84 ECEF (..., 3) m -> latitude, longitude (deg), ellipsoidal height (m): Bowring's iteration on the
    latitude; five rounds reach well under a millimetre near the surface."""
    x, y, z = ecef[..., 0], ecef[..., 1], ecef[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(5):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    h = p / np.cos(lat) - n
    return np.degrees(lat), np.degrees(lon), h
