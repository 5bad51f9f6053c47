"""Swellendam: real OSM layers and a geographic SRTM DEM -> features and a prior on a UTM 34S grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
import shapely
from pyproj import Transformer

from pipeline.build.region import build_features, build_prior
from pipeline.config.region import load_config
from pipeline.gis.layers import LayerError, read_vector
from tests.pipeline.gis_helpers import REPO, tree_hashes, write_config

pytestmark = pytest.mark.realdata

SWELLENDAM_TOML = REPO / "terrain_data" / "swellendam.toml"


def config_for(swellendam: Path, tmp_path: Path, restore: bool) -> Path:
    """The committed Swellendam config with its data paths pointed at the fixture folder."""
    import tomllib

    doc = tomllib.loads(SWELLENDAM_TOML.read_text())
    for layer in doc["layers"].values():
        layer["path"] = str(swellendam / Path(layer["path"]).name)
    doc["layers"]["water"]["restore_index"] = restore
    return write_config(tmp_path / "swellendam.toml", doc)


@pytest.fixture(scope="module")
def built(swellendam: Path, tmp_path_factory):
    before = tree_hashes(swellendam)
    cfg = load_config(config_for(swellendam, tmp_path_factory.mktemp("sw"), restore=True))
    stack = build_features(cfg, progress=False)
    return cfg, stack, build_prior(stack, cfg.model), before


def test_committed_config_points_at_the_fixture(swellendam: Path) -> None:
    cfg = load_config(SWELLENDAM_TOML)
    for layer in cfg.layers.values():
        assert layer.path.resolve().parent == swellendam.resolve()
    assert cfg.grid.crs.to_epsg() == 32734


def test_stale_water_index_is_reported_not_dropped(swellendam: Path, tmp_path: Path) -> None:
    before = tree_hashes(swellendam, "water.*")
    cfg = load_config(config_for(swellendam, tmp_path, restore=False))
    with pytest.raises(LayerError) as info:
        build_features(cfg, progress=False)
    msg = str(info.value)
    assert str(swellendam / "water.shp") in msg
    assert "SHAPE_RESTORE_SHX" in msg and "restore_index = true" in msg and "[layers.water]" in msg
    assert tree_hashes(swellendam, "water.*") == before


def test_restored_water_layer_is_complete(swellendam: Path, tmp_path: Path) -> None:
    cfg = load_config(config_for(swellendam, tmp_path, restore=True))
    before = tree_hashes(swellendam, "water.*")
    layer = read_vector(cfg.layers["water"], cfg.grid)
    assert tree_hashes(swellendam, "water.*") == before
    # every record the .shp holds is read: count record headers by walking the .shp itself
    shp = (swellendam / "water.shp").read_bytes()
    offset, records = 100, 0
    while offset + 8 <= len(shp):
        records += 1
        offset += 8 + 2 * int.from_bytes(shp[offset + 4:offset + 8], "big")
    assert layer.geometries.size == records
    assert shapely.is_valid(layer.geometries).all()


def test_features_and_prior(built, swellendam: Path) -> None:
    cfg, stack, prior, before = built
    assert tree_hashes(swellendam) == before  # inputs untouched by a whole build
    assert prior.density.sum() * cfg.grid.cell_area == pytest.approx(1.0, rel=1e-12)
    assert (prior.density[stack["water"].values == 1] == 0).all()
    assert 0 < stack["water"].values.mean() < 0.05
    assert 0 < stack["protected"].values.mean() < 0.5
    d = stack["road_distance"].values
    assert d.min() == 0 and np.isfinite(d).all()
    slope = stack["slope"].values
    assert np.isfinite(slope).all() and slope.max() > 30  # the Langeberg mountains north of town


def test_dem_reprojection_matches_the_source(built, swellendam: Path) -> None:
    """Elevations on the UTM grid vs exact bilinear interpolation of the source SRTM pixels at the same
    places (pyproj), allowing GDAL's warper a location error of 1/8 source pixel (~10 m here)."""
    from pipeline.gis.layers import read_dem

    cfg, _, _, _ = built
    dem = read_dem(cfg.layers["dem"], cfg.grid)
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, cfg.grid.height, 2000), rng.integers(0, cfg.grid.width, 2000)
    xc, yc = cfg.grid.cell_centres()
    lon, lat = Transformer.from_crs("EPSG:32734", "EPSG:4326", always_xy=True).transform(xc[rows, cols], yc[rows, cols])
    with rasterio.open(swellendam / "srtm_41_19_4326.tif") as src:
        band = src.read(1).astype(np.float64)
        c, r = ~src.transform @ (lon, lat)

    def bilinear(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        u, v = u - 0.5, v - 0.5  # pixel centres sit at half-integers
        u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
        fu, fv = u - u0, v - v0
        return ((band[v0, u0] * (1 - fu) + band[v0, u0 + 1] * fu) * (1 - fv)
                + (band[v0 + 1, u0] * (1 - fu) + band[v0 + 1, u0 + 1] * fu) * fv)

    shifts = np.linspace(-0.125, 0.125, 5)
    stencil = np.stack([bilinear(c + du, r + dv) for du in shifts for dv in shifts])
    got = dem[rows, cols]
    assert np.median(np.abs(got - bilinear(c, r))) < 1.0
    assert np.all(got >= stencil.min(axis=0) - 0.5) and np.all(got <= stencil.max(axis=0) + 0.5)
