"""GPS fixes as a logger wrote them (NMEA, GPX) -> a `GpsSeries`, with the velocity derived where it is missing.

A speed logger's NMEA RMC/VTG and many GPX files carry the receiver's own speed and course (from Doppler); a GPX from
a route planner or a plain GGA log carries positions only. Where SOG/COG or the climb rate are missing, they are
derived from the positions: each fix is put into a local East-North-Up frame about the first fix, and the velocity
at epoch i is the central difference (p[i+1] - p[i-1]) / (t[i+1] - t[i-1]) (one-sided at the ends of a stretch
without gaps; never across a gap). Its 1-sigma is sqrt(2) * s / (t[i+1] - t[i-1]), with s the epoch-to-epoch position
noise estimated from the log's own second differences (median |p[i+1] - 2 p[i] + p[i-1]| / 0.6745 / sqrt(6)), so a
noisy log gets a wide sigma rather than a wrong orientation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from codegen.post.csvlog import average_duplicate_epochs, velocity_from_sog_cog
from codegen.post.geodesy import geodetic_to_enu
from codegen.post.model import GpsSeries

DOPPLER_SIGMA = 0.1  # m/s, a receiver's own speed/course (u-blox 6 datasheet)
UERE = 2.5  # m, horizontal 1-sigma per unit HDOP
DEFAULT_HDOP = 2.0  # when the log has none
CLIMB_UNKNOWN_SIGMA = 1.0  # m/s, vertical velocity when neither a climb rate nor heights are in the log
DERIVED_GAP_FACTOR = 3.0  # an epoch interval this many typical intervals long: no difference across it
MIN_POSITION_NOISE = 0.05  # m, floor of the epoch-to-epoch position noise estimate


@dataclass
class Fixes:
    """Valid fixes in time order; NaN where the log has no value."""

    t: np.ndarray  # s
    lat: np.ndarray  # deg
    lon: np.ndarray  # deg
    alt: np.ndarray  # m
    sog: np.ndarray  # m/s
    cog: np.ndarray  # deg from North
    climb: np.ndarray  # m/s
    hdop: np.ndarray
    notes: list[str] = field(default_factory=list)


def to_gps_series(fixes: Fixes, source: str) -> tuple[GpsSeries, list[str]]:
    notes = list(fixes.notes)
    n_rows = len(fixes.t)
    t, (lat, lon, alt, sog, cog, climb, hdop) = average_duplicate_epochs(
        fixes.t, fixes.lat, fixes.lon, fixes.alt, fixes.sog, fixes.cog, fixes.climb, fixes.hdop)
    if len(t) < n_rows:
        notes.append(f"{source}: averaged {n_rows - len(t)} duplicate GPS epoch(s)")
    m = len(t)
    has_alt = np.isfinite(alt)
    enu = geodetic_to_enu(lat, lon, np.where(has_alt, alt, 0.0), (lat[0], lon[0], float(alt[0]) if has_alt[0] else 0.0))
    vel = np.full((m, 3), np.nan)
    sigma_vel = np.full((m, 3), DOPPLER_SIGMA)
    reported = np.isfinite(sog) & (np.isfinite(cog) | (sog == 0))
    vel[reported] = velocity_from_sog_cog(sog[reported], np.nan_to_num(cog[reported]), np.zeros(reported.sum()))
    derived, derived_sigma = derive_velocity(t, enu)
    missing = ~reported
    if missing.any():
        vel[missing, :2] = derived[missing, :2]
        sigma_vel[missing, :2] = derived_sigma[missing, None]
        notes.append(f"{source}: speed and course derived from positions at {missing.sum()} of {m} epochs "
                     f"(central differences in local ENU, 1-sigma {np.median(derived_sigma[missing]):.2f} m/s)")
    has_climb = np.isfinite(climb)
    vel[has_climb, 2] = climb[has_climb]
    from_heights = ~has_climb & has_alt
    vel[from_heights, 2] = derived[from_heights, 2]
    sigma_vel[from_heights, 2] = 2.0 * derived_sigma[from_heights]  # heights are about twice as noisy
    unknown = ~has_climb & ~has_alt
    vel[unknown, 2] = 0.0
    sigma_vel[unknown, 2] = CLIMB_UNKNOWN_SIGMA
    if from_heights.any():
        notes.append(f"{source}: climb rate derived from heights at {from_heights.sum()} epochs (central differences)")
    if unknown.any():
        notes.append(f"{source}: no climb rate or height at {unknown.sum()} epochs: vertical velocity taken as 0 "
                     f"+- {CLIMB_UNKNOWN_SIGMA:g} m/s")
    bad = ~np.isfinite(vel).all(axis=1)
    vel[bad] = 0.0
    sigma_vel[bad] = 1e3  # a lone fix between gaps: no velocity at all
    sigma_h = UERE * np.where(np.isfinite(hdop), np.maximum(hdop, 1.0), DEFAULT_HDOP)
    sigma_pos = np.stack([sigma_h, sigma_h, np.where(has_alt, 2 * sigma_h, np.nan)], axis=1)
    gps = GpsSeries(t, lat, lon, np.where(has_alt, alt, np.nan), vel, sigma_vel, sigma_pos, np.zeros(m, dtype=int))
    return gps, notes


def derive_velocity(t: np.ndarray, enu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,3) central-difference velocities (NaN where an epoch stands alone) and their (M,) 1-sigma, m/s."""
    m = len(t)
    vel = np.full((m, 3), np.nan)
    sigma = np.full(m, np.nan)
    if m < 2:
        return vel, sigma
    step = np.diff(t)
    typical = float(np.median(step))
    breaks = np.flatnonzero(step > DERIVED_GAP_FACTOR * typical) + 1
    noise = _position_noise(t, enu, breaks)
    for a, b in zip(np.concatenate([[0], breaks]), np.concatenate([breaks, [m]])):
        if b - a < 2:
            continue
        lo = np.clip(np.arange(a, b) - 1, a, b - 1)
        hi = np.clip(np.arange(a, b) + 1, a, b - 1)
        span = t[hi] - t[lo]
        vel[a:b] = (enu[hi] - enu[lo]) / span[:, None]
        sigma[a:b] = np.sqrt(2.0) * noise / span
    return vel, sigma


def _position_noise(t: np.ndarray, enu: np.ndarray, breaks: np.ndarray) -> float:
    """m: epoch-to-epoch horizontal position noise from second differences within stretches (robust)."""
    if len(t) < 3:
        return UERE
    second = enu[2:, :2] - 2.0 * enu[1:-1, :2] + enu[:-2, :2]
    same = np.ones(len(second), dtype=bool)
    for b in breaks:  # a second difference that straddles a break mixes stretches
        same[max(b - 2, 0):b] = False
    values = np.abs(second[same]).ravel()
    if not len(values):
        return UERE
    return max(float(np.median(values)) / 0.6745 / np.sqrt(6.0), MIN_POSITION_NOISE)
