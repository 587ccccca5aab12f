"""trajectory.html: one self-contained page with the reconstructed path, the GPS fixes, the GPS gaps and flagged
stretches in their own colours, and each gap's 1-sigma as a band.

The track is an inline SVG in local East-North metres, so it draws with no network and no script. When the page can
reach the Leaflet CDN, a second panel puts the same layers over OpenStreetMap tiles (an optional layer: without the
network that panel says so and the SVG stays the map).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from html import escape

import numpy as np

LEAFLET_CSS = "https://unpkg.com/leaflet@1.9.4/dist/leaflet.css"
LEAFLET_JS = "https://unpkg.com/leaflet@1.9.4/dist/leaflet.js"
SVG_WIDTH, SVG_HEIGHT, SVG_MARGIN = 900, 640, 24  # px
MAX_PATH_POINTS = 4000  # rows of the path drawn (every k-th row beyond this)
MAX_BAND_CIRCLES = 300  # per gap: 1-sigma circles drawn along it
COLOURS = {"path": "#1f77b4", "fix": "#404040", "gap": "#ff7f0e", "band": "#fbd9b5", "flagged": "#9467bd",
           "start": "#2ca02c", "end": "#d62728"}


@dataclass
class MapLayers:
    """What the page shows, all in one local frame: ENU metres about the first fix, and lat/lon (deg) for tiles."""

    title: str
    path_en: np.ndarray  # (T,2) m
    path_ll: np.ndarray  # (T,2) deg lat, lon
    sigma: np.ndarray  # (T,) m, horizontal 1-sigma of each path row (largest of east, north)
    fixes_en: np.ndarray  # (M,2) m
    fixes_ll: np.ndarray  # (M,2) deg
    gaps: list[np.ndarray]  # index arrays into the path rows, one per GPS gap
    flagged: list[tuple[np.ndarray, str]]  # index arrays and the flags, one per flagged stretch
    dead_reckoned: bool  # the whole path is dead-reckoned (--velocity-only)


def _thin(index: np.ndarray, most: int) -> np.ndarray:
    """Every k-th of `index` so that at most about `most` remain, always with the last."""
    kept = index[:: max(1, int(np.ceil(len(index) / most)))]
    return kept if len(index) == 0 or kept[-1] == index[-1] else np.append(kept, index[-1])


class _Frame:
    """ENU metres -> SVG pixels, one scale for both axes (north up)."""

    def __init__(self, points: np.ndarray):
        finite = points[np.isfinite(points).all(axis=1)]
        low, high = finite.min(axis=0), finite.max(axis=0)
        span = np.maximum(high - low, 1.0)
        self.scale = min((SVG_WIDTH - 2 * SVG_MARGIN) / span[0], (SVG_HEIGHT - 2 * SVG_MARGIN) / span[1])
        self.centre = 0.5 * (low + high)

    def xy(self, en: np.ndarray) -> np.ndarray:
        x = SVG_WIDTH / 2 + (en[:, 0] - self.centre[0]) * self.scale
        y = SVG_HEIGHT / 2 - (en[:, 1] - self.centre[1]) * self.scale
        return np.stack([x, y], axis=1)

    def points(self, en: np.ndarray) -> str:
        return " ".join(f"{x:.1f},{y:.1f}" for x, y in self.xy(en) if np.isfinite(x) and np.isfinite(y))


def _svg(layers: MapLayers) -> str:
    everything = np.concatenate([layers.path_en, layers.fixes_en])
    with_band = [layers.path_en[g] + d * layers.sigma[g, None] for g in layers.gaps for d in (-1.0, 1.0)]
    frame = _Frame(np.concatenate([everything] + with_band) if with_band else everything)
    out = [f'<svg id="track" xmlns="http://www.w3.org/2000/svg" width="{SVG_WIDTH}" height="{SVG_HEIGHT}" '
           f'viewBox="0 0 {SVG_WIDTH} {SVG_HEIGHT}" role="img" aria-label="track">',
           f'<rect width="{SVG_WIDTH}" height="{SVG_HEIGHT}" fill="#ffffff"/>']
    band = list(layers.gaps) + ([np.arange(len(layers.path_en))] if layers.dead_reckoned else [])
    for index in band:
        for (x, y), r in zip(frame.xy(layers.path_en[_thin(index, MAX_BAND_CIRCLES)]),
                             layers.sigma[_thin(index, MAX_BAND_CIRCLES)] * frame.scale):
            if np.isfinite(r):
                out.append(f'<circle class="band" cx="{x:.1f}" cy="{y:.1f}" r="{max(r, 0.5):.1f}" '
                           f'fill="{COLOURS["band"]}"/>')
    for x, y in frame.xy(layers.fixes_en):
        out.append(f'<circle class="fix" cx="{x:.1f}" cy="{y:.1f}" r="2" fill="{COLOURS["fix"]}"/>')
    path = _thin(np.arange(len(layers.path_en)), MAX_PATH_POINTS)
    out.append(f'<polyline class="path" points="{frame.points(layers.path_en[path])}" fill="none" '
               f'stroke="{COLOURS["path"]}" stroke-width="2"/>')
    for index, flags in layers.flagged:
        out.append(f'<polyline class="flagged" points="{frame.points(layers.path_en[index])}" fill="none" '
                   f'stroke="{COLOURS["flagged"]}" stroke-width="5" stroke-opacity="0.6"><title>{escape(flags)}'
                   '</title></polyline>')
    for index in layers.gaps:
        out.append(f'<polyline class="gap" points="{frame.points(layers.path_en[index])}" fill="none" '
                   f'stroke="{COLOURS["gap"]}" stroke-width="4"/>')
    (sx, sy), (ex, ey) = frame.xy(layers.path_en[[0, -1]])
    out.append(f'<rect class="end" x="{ex - 7:.1f}" y="{ey - 7:.1f}" width="14" height="14" fill="{COLOURS["end"]}" '
               'stroke="#000"/>')  # under the start: a round trip ends where it began
    out.append(f'<polygon class="start" points="{sx:.1f},{sy - 9:.1f} {sx - 8:.1f},{sy + 6:.1f} {sx + 8:.1f},'
               f'{sy + 6:.1f}" fill="{COLOURS["start"]}" stroke="#000"/>')
    bar = _scale_bar(frame.scale)
    out.append(f'<line x1="{SVG_MARGIN}" y1="{SVG_HEIGHT - 10}" x2="{SVG_MARGIN + bar * frame.scale:.1f}" '
               f'y2="{SVG_HEIGHT - 10}" stroke="#000" stroke-width="2"/>'
               f'<text x="{SVG_MARGIN}" y="{SVG_HEIGHT - 14}" font-size="12">{bar:g} m</text>')
    out.append("</svg>")
    return "\n".join(out)


def _scale_bar(scale: float) -> float:
    """A round length (m) about a fifth of the SVG's width."""
    target = SVG_WIDTH / 5 / scale
    power = 10.0 ** np.floor(np.log10(target))
    return float(max(m * power for m in (1, 2, 5) if m * power <= target) if target >= power else power)


def _legend(layers: MapLayers) -> str:
    path = "dead-reckoned path (IMU + Doppler, no GPS positions)" if layers.dead_reckoned else "reconstructed path"
    rows = [("path", path), ("fix", "GPS fixes"), ("gap", "GPS gap, dead-reckoned"),
            ("band", "1-sigma where dead-reckoned"), ("flagged", "flagged intervals (hover for the flags)"),
            ("start", "start"), ("end", "end")]
    return "".join(f'<span><i style="background:{COLOURS[k]}"></i>{escape(text)}</span>' for k, text in rows)


def _leaflet_data(layers: MapLayers) -> str:
    def ll(index):
        return np.round(layers.path_ll[index], 7).tolist()

    path = _thin(np.arange(len(layers.path_ll)), MAX_PATH_POINTS)
    data = {
        "path": ll(path),
        "fixes": np.round(layers.fixes_ll, 7).tolist(),
        "gaps": [ll(g) for g in layers.gaps],
        "bands": [[ll(_thin(g, MAX_BAND_CIRCLES)), np.round(layers.sigma[_thin(g, MAX_BAND_CIRCLES)], 2).tolist()]
                  for g in layers.gaps],
        "flagged": [[ll(i), f] for i, f in layers.flagged],
        "colours": COLOURS,
    }
    return json.dumps(data, allow_nan=False).replace("</", "<\\/")


_SCRIPT = """
(function () {
  var note = document.getElementById("basemap-note");
  if (typeof L === "undefined") {
    note.textContent = "basemap: not loaded (no network); the track above is the map";
    return;
  }
  var d = JSON.parse(document.getElementById("layers").textContent), c = d.colours;
  var box = document.getElementById("basemap");
  box.style.height = "520px";
  var map = L.map(box);
  L.tileLayer("https://tile.openstreetmap.org/{z}/{x}/{y}.png",
              {maxZoom: 21, maxNativeZoom: 19, attribution: "&copy; OpenStreetMap contributors"}).addTo(map);
  d.bands.forEach(function (b) { b[0].forEach(function (p, i) {
    L.circle(p, {radius: b[1][i], stroke: false, fillColor: c.band, fillOpacity: 0.5}).addTo(map); }); });
  d.fixes.forEach(function (p) {
    L.circleMarker(p, {radius: 2, stroke: false, fillColor: c.fix, fillOpacity: 1}).addTo(map); });
  var line = L.polyline(d.path, {color: c.path, weight: 2}).addTo(map);
  d.flagged.forEach(function (f) {
    L.polyline(f[0], {color: c.flagged, weight: 5, opacity: 0.6}).bindTooltip(f[1]).addTo(map); });
  d.gaps.forEach(function (g) { L.polyline(g, {color: c.gap, weight: 4}).addTo(map); });
  map.fitBounds(line.getBounds());
  note.textContent = "basemap: OpenStreetMap tiles";
})();
"""


def map_page(layers: MapLayers) -> str:
    title = escape(layers.title)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="stylesheet" href="{LEAFLET_CSS}">
<style>
body {{ font: 14px sans-serif; margin: 12px; color: #222; }}
h1 {{ font-size: 17px; margin: 0 0 6px; }}
#legend span {{ margin-right: 14px; white-space: nowrap; }}
#legend i {{ display: inline-block; width: 14px; height: 10px; margin-right: 4px; border: 1px solid #888; }}
#track {{ border: 1px solid #ccc; display: block; margin: 8px 0; }}
#basemap-note {{ color: #666; }}
</style></head>
<body>
<h1>{title}</h1>
<div id="legend">{_legend(layers)}</div>
{_svg(layers)}
<div id="basemap-note">basemap: loading</div>
<div id="basemap"></div>
<script type="application/json" id="layers">{_leaflet_data(layers)}</script>
<script src="{LEAFLET_JS}"></script>
<script>{_SCRIPT}</script>
</body></html>
"""
