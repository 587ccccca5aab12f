"""trajectory.html, the map page: drawn by headless Chromium with every host name unresolvable (no network, so no
Leaflet and no tiles), the track, the GPS fixes, the gap and its 1-sigma band must still be on the screenshot, in
their own colours."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from PIL import Image

from codegen.cli import main
from codegen.post.gapcheck import cut_gap
from codegen.post.mappage import COLOURS
from codegen.post.synthetic import Scenario, make_run, write_csv_pair
from conftest import require_tool

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run",
                  "--host-resolver-rules=MAP * ~NOTFOUND", "--window-size=960,900"]


def _rgb(hex_colour: str) -> np.ndarray:
    return np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])


def _pixels_near(image: np.ndarray, hex_colour: str, tolerance: int = 12) -> int:
    return int(np.sum(np.all(np.abs(image[:, :, :3].astype(int) - _rgb(hex_colour)) <= tolerance, axis=2)))


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    work = tmp_path_factory.mktemp("map")
    log, _ = make_run(Scenario(duration=120.0, seed=4))
    log.imu.gyro = None  # orientation only interpolated across the gap: a 1-sigma band of metres, wide on the map
    log = cut_gap(log, 50.0, 30.0)
    imu, gps = write_csv_pair(log, work)
    out = work / "out"
    assert main(["post", str(imu), "--gps", str(gps), "-o", str(out), "--no-plots"]) == 0
    return out / "trajectory.html"


def test_page_is_self_contained_apart_from_the_optional_basemap(page):
    html = page.read_text()
    assert "<svg" in html and 'class="path"' in html and 'class="gap"' in html and 'class="band"' in html
    external = [line for line in html.splitlines() if "https://" in line]
    # only the Leaflet tags and the tile URL inside the script that runs when Leaflet loaded
    assert all("unpkg.com/leaflet" in line or "tile.openstreetmap.org" in line for line in external), external


def test_chromium_without_network_draws_the_track(page, tmp_path):
    chromium = require_tool("chromium")
    shot = tmp_path / "shot.png"
    done = subprocess.run([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}",
                           f"--screenshot={shot}", page.as_uri()], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and shot.exists(), done.stderr[-2000:]
    image = np.asarray(Image.open(shot).convert("RGB"))
    legend_swatch = 14 * 10  # each colour's legend swatch alone is about this many pixels
    counts = {name: _pixels_near(image, COLOURS[name]) for name in ("path", "gap", "band", "fix")}
    assert counts["path"] > 5 * legend_swatch, counts  # a drawn line, not the legend's swatch
    assert counts["gap"] > 3 * legend_swatch, counts
    assert counts["band"] > 10 * legend_swatch, counts
    assert counts["fix"] > 2 * legend_swatch, counts
