"""Geometries with NaN vertices and features with no geometry (issue 13): named errors, not GEOS
exceptions or silently dropped features; the real Swellendam rivers read whole."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import shapely

from pipeline.cli import main
from pipeline.gis.grid import Grid
from pipeline.gis.layers import LayerError, LayerSpec, read_vector
from tests.pipeline.gis_helpers import REGION_TOML, REPO, tree_hashes, write_config, write_vector

GRID = Grid.from_bounds((0.0, 0.0, 1000.0, 1000.0), 20.0, "EPSG:32734")


def shp_records(path: Path) -> int:
    """Records of a .shp counted by walking its record headers (independent of the .shx and of GDAL)."""
    shp = path.read_bytes()
    offset, records = 100, 0
    while offset + 8 <= len(shp):
        records += 1
        offset += 8 + 2 * int.from_bytes(shp[offset + 4:offset + 8], "big")
    return records


@pytest.mark.parametrize("bad", [
    shapely.Polygon([(100, 100), (np.nan, 300), (300, 300), (300, 100)]),   # GEOSException in make_valid before
    shapely.LineString([(10, 10), (np.nan, 100), (200, 200)]),              # silently rasterized before
    shapely.Point(np.inf, 5.0),
])
def test_nan_vertices_are_a_named_error(tmp_path: Path, bad) -> None:
    good = shapely.box(400, 400, 500, 500) if bad.geom_type == "Polygon" else shapely.LineString([(0, 0), (9, 9)])
    if bad.geom_type == "Point":
        good = shapely.Point(1, 1)
    path = write_vector(tmp_path / "x.gpkg", [good, good, bad], layer="obstacles")
    before = tree_hashes(tmp_path)
    with pytest.raises(LayerError) as info:
        read_vector(LayerSpec("obstacles", path, "vector"), GRID)
    msg = str(info.value)
    assert str(path) in msg and "[layers.obstacles]" in msg and "1 features have NaN or infinite coordinates (FIDs 3)" in msg
    assert tree_hashes(tmp_path) == before


def test_coordinates_that_do_not_reproject_are_a_named_error(tmp_path: Path) -> None:
    """A latitude past the pole (a bad file) has no place in UTM: an error naming the layer, not inf later."""
    path = write_vector(tmp_path / "p.gpkg", [shapely.Point(20.0, -34.0), shapely.Point(20.0, -95.0)], crs="EPSG:4326")
    grid = Grid.from_bounds((400_000.0, 6_200_000.0, 410_000.0, 6_210_000.0), 100.0, "EPSG:32734")
    with pytest.raises(LayerError, match=r"p\.gpkg.*\[layers\.pts\].*once reprojected to EPSG:32734.*FIDs 2"):
        read_vector(LayerSpec("pts", path, "vector"), grid)


def test_nan_vertices_from_the_cli(tmp_path: Path, capsys) -> None:
    doc = tomllib.loads(REGION_TOML.read_text())
    for layer in doc["layers"].values():
        layer["path"] = str((REGION_TOML.parent / layer["path"]).resolve())
    bad = write_vector(tmp_path / "obstacles.gpkg", [shapely.box(0, 0, 1, 1),
                                                      shapely.Polygon([(0, 0), (np.nan, 1), (1, 1), (1, 0)])])
    doc["layers"]["obstacles"] = {"path": str(bad)}
    cfg = write_config(tmp_path / "r.toml", doc)
    rc = main(["-q", "features", str(cfg), "--out", str(tmp_path / "features")])
    err = capsys.readouterr().err
    assert rc == 1 and "terrain-prior: error:" in err and "Traceback" not in err
    assert str(bad) in err and "[layers.obstacles]" in err and "NaN or infinite coordinates" in err
    assert not (tmp_path / "features").exists() or not any((tmp_path / "features").iterdir())


def test_empty_geometries_need_the_config_key(tmp_path: Path, capsys) -> None:
    """A feature with no geometry is an error naming the key that allows it; with the key, a warning."""
    geoms = np.array([shapely.LineString([(0, 0), (500, 500)]), None, shapely.LineString([(0, 500), (500, 0)])])
    path = tmp_path / "roads.gpkg"
    import pyogrio.raw

    pyogrio.raw.write(path, shapely.to_wkb(geoms), [], [], crs="EPSG:32734", geometry_type="LineString")
    doc = tomllib.loads(REGION_TOML.read_text())
    for layer in doc["layers"].values():
        layer["path"] = str((REGION_TOML.parent / layer["path"]).resolve())
    doc["layers"]["roads"] = {"path": str(path)}
    cfg = write_config(tmp_path / "r.toml", doc)
    rc = main(["-q", "features", str(cfg), "--out", str(tmp_path / "f")])
    err = capsys.readouterr().err
    assert rc == 1 and "1 of 3 features have no geometry (FIDs 2)" in err
    assert "allow_empty_geometries = true in [layers.roads]" in err and "Traceback" not in err
    doc["layers"]["roads"]["allow_empty_geometries"] = True
    spec = LayerSpec("roads", path, "vector", allow_empty_geometries=True)
    with pytest.warns(UserWarning, match="skipped"):
        assert read_vector(spec, GRID).geometries.size == 2
    from pipeline.config.region import ConfigError, load_config

    assert load_config(write_config(cfg, doc)).layers["roads"].allow_empty_geometries
    doc["layers"]["roads"]["allow_empty_geometries"] = "yes"
    with pytest.raises(ConfigError, match=r"layers\.roads\.allow_empty_geometries.*true or false"):
        load_config(write_config(cfg, doc))


# ---- the real Swellendam rivers ----------------------------------------------------------------------

@pytest.mark.realdata
def test_swellendam_rivers_read_whole(swellendam: Path) -> None:
    """The committed config restores rivers.shp's stale index: all 20 lines of the .shp, none lost."""
    from pipeline.config.region import load_config

    cfg = load_config(REPO / "terrain_data" / "swellendam.toml")
    spec = cfg.layers["rivers"]
    assert spec.restore_index and spec.path.resolve() == (swellendam / "rivers.shp").resolve()
    before = tree_hashes(swellendam, "rivers.*")
    layer = read_vector(spec, cfg.grid)
    assert layer.geometries.size == shp_records(swellendam / "rivers.shp") == 20
    assert tree_hashes(swellendam, "rivers.*") == before


@pytest.mark.realdata
def test_swellendam_rivers_without_restore_is_an_error(swellendam: Path) -> None:
    """GDAL reads the stale index as 19 records, 7 of them without geometry: refused, naming both fixes."""
    from dataclasses import replace

    from pipeline.config.region import load_config

    cfg = load_config(REPO / "terrain_data" / "swellendam.toml")
    with pytest.raises(LayerError) as info:
        read_vector(replace(cfg.layers["rivers"], restore_index=False), cfg.grid)
    msg = str(info.value)
    assert "rivers.shp" in msg and "[layers.rivers]" in msg and "have no geometry" in msg
    assert "restore_index = true" in msg and "allow_empty_geometries = true" in msg
