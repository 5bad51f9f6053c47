"""The prior and feature GeoTIFFs are valid Cloud-Optimized GeoTIFFs with overviews (rio-cogeo's port of
GDAL's validator, and Debian's gdalinfo when installed), read back unchanged, and come with their
QGIS style in the same atomic commit."""

from __future__ import annotations

import json
import shutil
import subprocess
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import rasterio
from rio_cogeo.cogeo import cog_validate

from pipeline.build.region import write_features
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE, Grid
from pipeline.prior import write
from pipeline.prior.style import RAMP_QUANTILE
from pipeline.prior.terrain import TerrainPrior

GDALINFO = shutil.which("gdalinfo")


def _prior(h: int = 700, w: int = 530) -> TerrainPrior:
    """A prior big enough for two overview levels, with a structural-zero block."""
    grid = Grid.from_bounds((0.0, 0.0, w * 10.0, h * 10.0), 10.0, "EPSG:32734")
    r = np.random.default_rng(3).random((h, w))
    r[:100, :80] = 0.0
    return TerrainPrior.from_array(r, grid, {"test": 1})


def _assert_cog(path) -> None:
    valid, errors, warnings = cog_validate(path, strict=True, quiet=True)
    assert valid and not errors and not warnings, (errors, warnings)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    prior = _prior()
    return prior, prior.write(tmp_path_factory.mktemp("cog") / "prior.tif")


def test_prior_is_a_valid_cog_with_overviews(written):
    prior, path = written
    _assert_cog(path)
    with rasterio.open(path) as src:
        assert src.overviews(1) == [2, 4]
        assert src.profile["compress"] == "deflate" and (src.profile["blockxsize"], src.profile["blockysize"]) == (256, 256)
        assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        # the overviews average the density (AVERAGE resampling), 2x2 cells per cell at level 1
        half = src.read(1, out_shape=(350, 265))
    full = prior.density.astype(np.float32)
    np.testing.assert_allclose(half, full.reshape(350, 2, 265, 2).mean(axis=(1, 3)), rtol=1e-5)
    back = TerrainPrior.read(path)
    np.testing.assert_array_equal(back.density, full)
    np.testing.assert_array_equal(back.sat, prior.sat)
    np.testing.assert_array_equal(back.sat2, prior.sat2)


def test_cog_is_gdals_default_copy_byte_for_byte(tmp_path):
    """The writer's uncompressed temporary overviews (COG_TMP_COMPRESSION) change nothing in the file:
    the same bytes as GDAL's COG copy of the same plain GeoTIFF with its defaults (at our DEFLATE level)."""
    import rasterio.shutil

    prior = _prior()
    grid = prior.grid
    with write.cog_writer(tmp_path / "ours.tif", grid, "float32") as dst:
        dst.write(prior.density.astype(np.float32), 1)
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", **write.geotiff_profile(grid, "float32", None)) as dst:
        dst.write(prior.density.astype(np.float32), 1)
    rasterio.shutil.copy(plain, tmp_path / "gdal.tif", driver="COG", COMPRESS="DEFLATE", LEVEL=write.DEFLATE_LEVEL, BLOCKSIZE=write.BLOCK,
                         OVERVIEW_RESAMPLING="AVERAGE", NUM_THREADS="ALL_CPUS", BIGTIFF="IF_SAFER")
    assert (tmp_path / "ours.tif").read_bytes() == (tmp_path / "gdal.tif").read_bytes()


@pytest.mark.skipif(GDALINFO is None, reason="Debian's gdal-bin (gdalinfo) is not installed")
def test_gdalinfo_reports_cog_layout(written):
    _, path = written
    info = json.loads(subprocess.run([GDALINFO, "-json", str(path)], check=True, capture_output=True, text=True).stdout)
    assert info["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"] == "COG"
    assert len(info["bands"][0]["overviews"]) == 2


def test_prior_style_ramps_to_the_density_quantile_with_zeros_transparent(written):
    prior, path = written
    root = ET.parse(path.with_suffix(".qml")).getroot()
    renderer = root.find("pipe/rasterrenderer")
    assert renderer.get("type") == "singlebandpseudocolor"
    entry = renderer.find("rasterTransparency/singleValuePixelList/pixelListEntry")
    assert (entry.get("min"), entry.get("max"), entry.get("percentTransparent")) == ("0", "0", "100")
    full = prior.density.astype(np.float32)
    assert float(renderer.get("classificationMin")) == 0.0
    assert float(renderer.get("classificationMax")) == np.quantile(full[full > 0], RAMP_QUANTILE)


@pytest.mark.parametrize("rows", [7, 256, 700])
def test_prior_style_of_a_decimated_sample_is_the_same_for_any_strips(tmp_path, monkeypatch, rows):
    monkeypatch.setattr(write, "STYLE_SAMPLE_EDGE", 100)  # every 7th row and column of 700 x 530
    prior = _prior()
    strips = ((prior.density[r : r + rows], prior.sat[r + 1 : r + 1 + rows], prior.sat2[r + 1 : r + 1 + rows])
              for r in range(0, prior.grid.height, rows))
    path = write.write_prior(tmp_path / "prior.tif", prior.grid, prior.model, strips)
    sample = prior.density[::7, ::7].astype(np.float32)
    top = float(ET.parse(path.with_suffix(".qml")).getroot().find("pipe/rasterrenderer").get("classificationMax"))
    assert top == np.quantile(sample[sample > 0], RAMP_QUANTILE)


def test_a_failing_style_writer_leaves_nothing(tmp_path, monkeypatch):
    def broken(density):
        raise RuntimeError("style writer failed")

    monkeypatch.setattr(write, "prior_qml", broken)
    with pytest.raises(RuntimeError, match="style writer failed"):
        _prior(300, 40).write(tmp_path / "prior.tif")
    assert list(tmp_path.iterdir()) == []  # no tables, no GeoTIFF, no scratch folder


def test_feature_geotiffs_are_cogs_with_styles(tmp_path):
    grid = Grid.from_bounds((0.0, 0.0, 6000.0, 3000.0), 10.0, "EPSG:32634")
    codes = (np.arange(600)[None, :] // 200 + np.zeros((300, 1), dtype=int)).astype(np.int16)
    codes[:10] = NODATA_CODE
    dist = np.hypot(*np.meshgrid(np.arange(600.0), np.arange(300.0))) * 10.0
    dist[0, 0] = np.nan
    stack = FeatureStack(grid)
    stack.add(Feature("surface", codes, "categorical", labels={0: "paved", 1: "gravel", 2: "track"}))
    stack.add(Feature("road_distance", dist, "continuous", units="m"))
    paths = write_features(stack, tmp_path)
    for path in paths:
        _assert_cog(path)
    with rasterio.open(paths[0]) as src:
        np.testing.assert_array_equal(src.read(1), codes)
        assert src.nodata == NODATA_CODE
        # NEAREST overviews keep category codes (an average would invent 0.5-codes)
        assert set(np.unique(src.read(1, out_shape=(150, 300)))) <= {0, 1, 2, NODATA_CODE}
    with rasterio.open(paths[1]) as src:
        np.testing.assert_array_equal(src.read(1), dist.astype(np.float32))
    palette = ET.parse(tmp_path / "surface.qml").getroot().find("pipe/rasterrenderer")
    assert palette.get("type") == "paletted"
    assert [(e.get("value"), e.get("label")) for e in palette.iter("paletteEntry")] == [
        ("0", "paved"), ("1", "gravel"), ("2", "track")]
    ramp = ET.parse(tmp_path / "road_distance.qml").getroot().find("pipe/rasterrenderer")
    assert ramp.get("type") == "singlebandpseudocolor"
    # the finite range (the NaN nodata cell left out)
    assert (float(ramp.get("classificationMin")), float(ramp.get("classificationMax"))) == (10.0, np.nanmax(dist))
    assert ramp.find("rasterTransparency/singleValuePixelList") is None  # a zero distance is data
