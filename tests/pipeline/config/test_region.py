"""Region config parsing: the bundled config, UTM zone choice, relative paths, and every error naming file and key."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyproj import Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from pipeline.config.region import ConfigError, load_config, parse_config, utm_crs
from pipeline.prior.likelihood import CategoricalLikelihood, RoadDistanceLikelihood
from tests.pipeline.gis_helpers import REGION_TOML, write_config


def minimal(**region) -> dict:
    return {
        "region": {"crs": "EPSG:32734", "bounds": [0, 0, 1000, 600], "cell_size": 20.0} | region,
        "layers": {"roads": {"path": "roads.gpkg"}, "dem": {"path": "dem.tif"}},
        "features": {"road_distance": {"type": "distance", "layers": ["roads"]},
                     "slope": {"type": "slope", "layer": "dem"}},
    }


def test_bundled_region_config() -> None:
    cfg = load_config(REGION_TOML)
    assert cfg.grid.shape == (700, 700)
    assert cfg.grid.dx == cfg.grid.dy == 20.0
    assert cfg.grid.crs.to_epsg() == 32734
    assert cfg.grid.bounds == (300000.0, 6186000.0, 314000.0, 6200000.0)
    assert cfg.layers["dem"].kind == "raster" and cfg.layers["roads"].kind == "vector"
    assert cfg.layers["dem"].path == REGION_TOML.parent / "dem.tif"
    assert cfg.features["slope_class"].labels == ("<4", "4-8", "8-12", ">=12")
    assert isinstance(cfg.model.terms["road_distance"], RoadDistanceLikelihood)
    assert isinstance(cfg.model.terms["water"], CategoricalLikelihood)
    assert cfg.model.terms["water"].values["water"] == 0.0


def test_paths_resolve_relative_to_the_config_file(tmp_path: Path) -> None:
    sub = tmp_path / "configs" / "here"
    sub.mkdir(parents=True)
    doc = minimal()
    doc["layers"]["roads"]["path"] = "../data/roads.gpkg"
    cfg = load_config(write_config(sub / "r.toml", doc))
    assert cfg.layers["roads"].path.resolve() == (tmp_path / "configs" / "data" / "roads.gpkg").resolve()
    assert cfg.layers["dem"].path == sub / "dem.tif"


@settings(max_examples=40, deadline=None)
@given(lon=st.floats(-179.0, 178.0), lat=st.floats(-79.0, 83.0))
def test_utm_zone_matches_pyproj_database(lon: float, lat: float) -> None:
    """Our zone choice vs pyproj's UTM CRS query for the same small area (skipping Norway/Svalbard exceptions)."""
    if 56 <= lat <= 84 and 0 <= lon <= 42:
        return
    lon_c = math.floor((lon + 180) / 6) * 6 - 180 + 3  # a box centred in its zone, as pyproj needs one zone
    infos = query_utm_crs_info(datum_name="WGS 84",
                               area_of_interest=AreaOfInterest(lon_c - 0.1, lat, lon_c + 0.1, lat + 0.05))
    expected = {int(i.code) for i in infos if i.name.startswith("WGS 84 / UTM")}
    got = utm_crs(lon_c - 0.1, lat, lon_c + 0.1, lat + 0.05).to_epsg()
    assert got in expected
    assert (got // 100 == 327) == (lat + 0.025 < 0)


def test_utm_grid_covers_the_lonlat_bounds(tmp_path: Path) -> None:
    bounds = [20.30, -34.15, 20.60, -33.95]
    cfg = parse_config(minimal(crs="utm", bounds=bounds), tmp_path / "r.toml")
    assert cfg.grid.crs.to_epsg() == 32734  # Swellendam: zone 34 south
    tr = Transformer.from_crs("EPSG:4326", "EPSG:32734", always_xy=True)
    xmin, ymin, xmax, ymax = cfg.grid.bounds
    for lon in (bounds[0], bounds[2]):
        for lat in (bounds[1], bounds[3]):
            x, y = tr.transform(lon, lat)
            assert xmin - 1e-6 <= x <= xmax + 1e-6 and ymin - 1e-6 <= y <= ymax + 1e-6
    assert xmax - xmin < 29_000 and ymax - ymin < 23_000  # tight, not the whole zone


def test_bounds_in_another_crs(tmp_path: Path) -> None:
    doc = minimal(bounds=[21.0, -34.1, 21.01, -34.09], bounds_crs="EPSG:4326")
    cfg = parse_config(doc, tmp_path / "r.toml")
    # lon 21 E is zone 34's central meridian: easting 500 km exactly
    assert cfg.grid.bounds[0] == pytest.approx(500_000.0, abs=1e-3)


def err(tmp_path: Path, doc: dict | str, *needles: str) -> str:
    path = tmp_path / "bad.toml"
    if isinstance(doc, str):
        path.write_text(doc)
    else:
        write_config(path, doc)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert str(path) in msg
    for n in needles:
        assert n in msg, msg
    return msg


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nope.toml: region config not found"):
        load_config(tmp_path / "nope.toml")


def test_invalid_toml(tmp_path: Path) -> None:
    err(tmp_path, "[region\ncrs = 1", "not valid TOML")


def test_geographic_grid_refused_with_hint(tmp_path: Path) -> None:
    err(tmp_path, minimal(crs="EPSG:4326", bounds=[20, -34, 20.1, -33.9]), "geographic", 'crs = "utm"')


@pytest.mark.parametrize(
    ("mutate", "needles"),
    [
        (lambda d: d.pop("region"), ["missing [region]"]),
        (lambda d: d["region"].pop("bounds"), ["region.bounds", "missing"]),
        (lambda d: d["region"].update(bounds=[0, 0, 1]), ["region.bounds", "4 numbers"]),
        (lambda d: d["region"].update(bounds=[10, 0, 0, 10]), ["xmax > xmin"]),
        (lambda d: d["region"].update(cell_size=-5), ["region.cell_size", "positive"]),
        (lambda d: d["region"].update(crs="EPSG:999999"), ["region.crs", "not a CRS"]),
        (lambda d: d["region"].update(crs="utm", bounds=[200, -34, 201, -33]), ["region.bounds", "degrees"]),
        (lambda d: d["region"].update(colour="red"), ["[region]", "unknown keys ['colour']"]),
        (lambda d: d.update(extra={}), ["unknown top-level tables ['extra']"]),
        (lambda d: d["layers"]["roads"].pop("path"), ["layers.roads.path", "missing"]),
        (lambda d: d["layers"]["roads"].update(restore_index="yes"), ["layers.roads.restore_index", "true or false"]),
        (lambda d: d["layers"]["dem"].update(kind="image"), ["layers.dem.kind"]),
        (lambda d: d["layers"]["roads"].update(restore_index=True), ["layers.roads.restore_index", "roads.gpkg"]),
        (lambda d: d["features"]["road_distance"].update(layers=["highways"]), ["features.road_distance.layers", "no layer 'highways'"]),
        (lambda d: d["features"]["road_distance"].update(layers=["dem"]), ["features.road_distance.layers", "raster layer"]),
        (lambda d: d["features"]["slope"].update(type="gradient"), ["features.slope.type", "'gradient'"]),
        (lambda d: d["features"]["slope"].pop("layer"), ["features.slope.layer", "missing"]),
        (lambda d: d["features"]["road_distance"].update(buffer_m=-1), ["features.road_distance.buffer_m"]),
        (lambda d: d["features"]["road_distance"].update(to="starts"), ["features.road_distance.to", "'starts'"]),
        (lambda d: d["features"]["road_distance"].update(to=1), ["features.road_distance.to"]),
        (lambda d: d["features"].update(c={"type": "classes", "source": "slope", "breaks": [5, 5]}), ["features.c.breaks", "increase"]),
        (lambda d: d["features"].update(c={"type": "classes", "source": "slope", "breaks": [5], "labels": ["a"]}), ["features.c.labels", "2 classes"]),
        (lambda d: d["features"].update(c={"type": "classes", "source": "aspect", "breaks": [5]}), ["features.c.source", "'aspect'"]),
        (lambda d: d["features"].update(m={"type": "mask", "layers": ["roads"], "labels": ["a", "a"]}), ["features.m.labels", "distinct"]),
        (lambda d: d.update(features={}), ["no [features.<name>] tables"]),
        (lambda d: d.update(likelihood={"water": {"type": "categorical", "values": {"dry": 1}}}), ["[likelihood.water]", "no feature"]),
        (lambda d: d.update(likelihood={"slope": {"type": "gaussian"}}), ["[likelihood.slope]", "type"]),
        (lambda d: d.update(likelihood={"road_distance": {"type": "road", "rmd": 0, "mv": 0.1}}), ["rmd must be > 0"]),
    ],
)
def test_bad_config_names_file_and_key(tmp_path: Path, mutate, needles) -> None:
    doc = minimal()
    mutate(doc)
    err(tmp_path, doc, *needles)
