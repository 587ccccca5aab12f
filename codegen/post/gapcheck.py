"""How well `post` bridges a GPS gap it is given on purpose: cut epochs out of a log whose path is known, run the
method, and compare the path inside the gap, and its 1-sigma, with the truth and with the GPS-only cubic Hermite
bridge. Shared by the tests and benchmarks/post.py; the truth is a synthetic run's or the epochs that were cut out.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from codegen.post.bridge import hermite_bridge
from codegen.post.geodesy import enu_to_geodetic, geodetic_to_enu
from codegen.post.model import PostLog
from codegen.post.pipeline import PostResult

NOMINAL_COVERAGE = 0.6827  # a Gaussian error lies within its 1-sigma this often


def cut_gap(log: PostLog, start: float, length: float) -> PostLog:
    """The log without the GPS epochs of `length` seconds after `start` (start < t <= start + length): a gap of
    that many seconds of epochs, bridged from the epoch at or before `start` to the first after."""
    keep = (log.gps.t <= start) | (log.gps.t > start + length + 1e-9)
    return replace(log, gps=log.gps.select(keep), notes=list(log.notes))


@dataclass
class GapErrors:
    t: np.ndarray  # (K,) s, times inside the gap where the truth is known
    post: np.ndarray  # (K,2) post's east/north error, m
    sigma: np.ndarray  # (K,2) post's reported 1-sigma east/north, m
    hermite: np.ndarray  # (K,2) the GPS-only Hermite bridge's east/north error, m

    @property
    def post_rms(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.post**2, axis=1))))

    @property
    def hermite_rms(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.hermite**2, axis=1))))

    @property
    def covered(self) -> np.ndarray:
        """(K,2) bool: |error| <= 1-sigma, per axis."""
        return np.abs(self.post) <= self.sigma


def gap_errors(result: PostResult, start: float, length: float, truth_t: np.ndarray, truth_enu: np.ndarray
               ) -> GapErrors:
    """Errors at `truth_t` strictly inside the bridged gap; `truth_enu` (K,3) about result.origin. The Hermite bridge
    uses the GPS positions and Doppler velocities of the two epochs around the gap, as `post` saw them."""
    gps = result.log.gps
    a = int(np.searchsorted(gps.t, start, side="right")) - 1
    t0, t1 = gps.t[a], gps.t[a + 1]
    inside = (truth_t > t0) & (truth_t < t1)
    t = truth_t[inside]
    tr = result.track
    pos = np.stack([np.interp(t, tr.t, tr.pos[:, i]) for i in range(2)], axis=1)
    sigma = np.stack([np.interp(t, tr.t, tr.sigma_pos[:, i]) for i in range(2)], axis=1)
    p0, p1 = result.gps_enu[a, :2], result.gps_enu[a + 1, :2]
    h, _ = hermite_bridge(t, t0, p0, gps.vel[a, :2], t1, p1, gps.vel[a + 1, :2])
    truth = truth_enu[inside, :2]
    return GapErrors(t, pos - truth, sigma, h - truth)


def truth_about(result: PostResult, enu: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """ENU points about `origin` re-expressed about the result's origin (the first GPS fix)."""
    lat, lon, h = enu_to_geodetic(enu, origin)
    return geodetic_to_enu(lat, lon, h, result.origin)
