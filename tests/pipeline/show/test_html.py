"""terrain-prior show --html: the prior's interactive map, checked against pyproj and in headless Chromium offline."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pyogrio.raw
import pytest
import shapely
from pyproj import Transformer

from pipeline.cli import main
from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tests.browser import geojson_layers, image_overlay, probe, screenshot

CRS = "EPSG:32734"
ROADS = [[(300100.0, 6186100.0), (301900.0, 6187900.0)], [(300100.0, 6187500.0), (301900.0, 6187500.0)]]
LAKE = [(301200.0, 6186200.0), (301700.0, 6186200.0), (301700.0, 6186700.0), (301200.0, 6186700.0)]


@pytest.fixture(scope="module")
def region(tmp_path_factory) -> tuple[Path, Path]:
    """A 2 km region (20 m cells) with two roads and a lake, and a prior that is zero on its western
    half and rises eastwards: (region.toml, prior.tif)."""
    d = tmp_path_factory.mktemp("region")
    gpkg = d / "region.gpkg"
    roads = shapely.to_wkb(shapely.linestrings(ROADS))
    pyogrio.raw.write(gpkg, roads, [np.arange(2)], ["id"], layer="roads", driver="GPKG", geometry_type="LineString", crs=CRS)
    pyogrio.raw.write(gpkg, shapely.to_wkb(np.array([shapely.Polygon(LAKE)])), [np.arange(1)], ["id"], layer="lakes",
                      driver="GPKG", geometry_type="Polygon", crs=CRS, append=True)
    toml = d / "region.toml"
    toml.write_text(f"""
[region]
name = "tiny"
crs = "{CRS}"
bounds = [300000, 6186000, 302000, 6188000]
cell_size = 20.0

[layers.roads]
path = "{gpkg}"
layer = "roads"

[layers.lakes]
path = "{gpkg}"
layer = "lakes"

[features.water]
type = "mask"
layers = ["lakes"]

[features.road_distance]
type = "distance"
layers = ["roads"]
""")
    grid = Grid.from_bounds((300000, 6186000, 302000, 6188000), 20.0, CRS)
    r = np.tile(np.arange(grid.width, dtype=np.float64), (grid.height, 1))
    r[:, : grid.width // 2] = 0.0
    prior = d / "prior.tif"
    TerrainPrior.from_array(r, grid).write(prior)
    return toml, prior


@pytest.fixture(scope="module")
def prior_html(region, tmp_path_factory) -> Path:
    toml, prior = region
    out = tmp_path_factory.mktemp("map") / "map.html"
    assert main(["-q", "show", str(prior), "--html", str(out), "--region", str(toml)]) == 0
    return out


def test_the_file_references_nothing_outside_itself(prior_html):
    text = prior_html.read_text(encoding="utf-8")
    assert re.findall(r"<script[^>]+src=|<link[^>]+href=|url\((?!data:|#default#VML)", text) == []
    assert "L.map(" in text and "L.control.layers(" in text


def test_overlay_pixels_are_the_density_reprojected(prior_html, region):
    """Each overlay pixel centre (EPSG:3857, from the overlay bounds) mapped back to the grid by pyproj:
    transparent exactly where the prior is zero or off the grid, and the colour rises with the density."""
    _, prior_path = region
    prior = TerrainPrior.read(prior_path)
    pixels, [[south, west], [north, east]] = image_overlay(prior_html)
    h, w = pixels.shape[:2]
    to_merc = Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True)
    (x0, x1), (y1, y0) = to_merc.transform([west, east], [north, south])
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    mx, my = x0 + cols * (x1 - x0) / w, y1 - rows * (y1 - y0) / h
    gx, gy = Transformer.from_crs("EPSG:3857", CRS, always_xy=True).transform(mx, my)
    left, bottom, right, top = prior.grid.bounds
    c, r = np.floor((gx - left) / 20.0).astype(int), np.floor((top - gy) / 20.0).astype(int)
    inside = (c >= 0) & (c < prior.grid.width) & (r >= 0) & (r < prior.grid.height)
    density = np.zeros((h, w))
    density[inside] = prior.density[r[inside], c[inside]]
    # pixels whose centre lies within 1 % of a cell of a cell edge may fall either way under rounding
    frac_c, frac_r = (gx - left) / 20.0 % 1, (top - gy) / 20.0 % 1
    clear = (np.minimum(frac_c, 1 - frac_c) > 0.01) & (np.minimum(frac_r, 1 - frac_r) > 0.01)
    alpha = pixels[..., 3]
    assert np.array_equal(alpha[clear] > 0, density[clear] > 0)
    assert (alpha[clear & (density == 0)] == 0).all() and (alpha > 0).mean() > 0.3
    # viridis: the red-plus-green sum grows monotonically from dark purple to yellow
    lit = clear & (density > 0)
    order = np.argsort(density[lit])
    brightness = (pixels[..., 0] + pixels[..., 1])[lit][order]
    assert np.all(np.diff(brightness) >= -2.5 / 255)


def test_roads_and_water_are_the_config_layers_in_lon_lat(prior_html):
    layers = geojson_layers(prior_html)
    assert [len(fc["features"]) for fc in layers] == [1, 2]  # the water mask comes first in the config
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    roads = [f["geometry"]["coordinates"] for f in layers[1]["features"]]
    for got, line in zip(roads, ROADS, strict=True):
        np.testing.assert_allclose(got, np.column_stack(to_ll.transform(*np.array(line).T)), atol=1e-9)


def test_show_needs_an_output(region, capsys):
    _, prior = region
    assert main(["-q", "show", str(prior)]) == 1
    assert "error: show: give --png, --html or both" in capsys.readouterr().err


def test_map_in_headless_chromium_offline(prior_html, tmp_path):
    got = probe(prior_html, tmp_path)
    assert got["maps"] == 1
    assert [(o["name"], o.get("kind"), o.get("count")) for o in got["overlays"]] == [
        ("prior density", "image", None), ("lakes", "features", 1), ("roads", "features", 2)]
    for o in got["overlays"]:
        assert o["checked"] and o["on_map"] and o["off_after_click"] and o["on_after_second_click"], o
    assert got["overlays"][0]["loaded"]
    assert got["paths"] == 3 and got["legend"] == 1
    assert got["errors"] == [] and got["console"] == [] and got["resources"] == []
    shot = screenshot(prior_html, tmp_path / "map.png")
    import matplotlib.image

    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (900, 1200) and pixels[..., :3].std() > 0.05  # drawn, not a blank page


def test_the_probe_sees_errors_and_network_requests(prior_html, tmp_path):
    """The browser check can fail: a throwing script and a CDN script tag are both reported."""
    broken = tmp_path / "broken.html"
    broken.write_text(prior_html.read_text(encoding="utf-8").replace(
        "</body>", '<script src="https://cdn.example.invalid/x.js"></script><script>undefinedName()</script></body>'),
        encoding="utf-8")
    got = probe(broken, tmp_path)
    assert any("undefinedName" in e for e in got["errors"])
    assert any("cdn.example.invalid" in e for e in got["errors"] + got["resources"])


def test_a_layers_where_filter_picks_the_features_drawn(region, tmp_path):
    toml, prior = region
    filtered = tmp_path / "region.toml"
    filtered.write_text(toml.read_text().replace('layer = "roads"\n', 'layer = "roads"\nwhere = "id = 1"\n'))
    out = tmp_path / "map.html"
    assert main(["-q", "show", str(prior), "--html", str(out), "--region", str(filtered)]) == 0
    _, roads = geojson_layers(out)
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    assert len(roads["features"]) == 1
    np.testing.assert_allclose(roads["features"][0]["geometry"]["coordinates"],
                               np.column_stack(to_ll.transform(*np.array(ROADS[1]).T)), atol=1e-9)
