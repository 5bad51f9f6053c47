"""Tiled prior build on a real 2-process Dask cluster against the in-memory build on the same grid."""

from __future__ import annotations

import dataclasses
import functools
import tempfile
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.build.region import build_features, build_region_prior
from pipeline.config.region import load_config
from pipeline.gis.layers import LayerError
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.terrain import PriorError, TerrainPrior
from pipeline.prior.write import sat_paths
from pipeline.tiled.build import build_prior_tiled
from pipeline.tiled.store import NpyRows
from pipeline.tiled.tiles import tile_features
from pipeline.tiled.windows import TiledBuildError, distance_caps, needed_features, tile_windows
from tests.dask_helpers import shared_client
from tests.pipeline.gis_helpers import REGION_TOML, write_config, write_raster

SUB_BOUNDS = [301000, 6188000, 307000, 6194000]  # 6 km x 6 km of the bundled region: 300 x 300 cells of 20 m


@pytest.fixture(scope="module")
def client():
    return shared_client()


def region(tmp_path: Path, max_distance_m: float | None = 600.0, **likelihood) -> Path:
    """The bundled synthetic region cut to SUB_BOUNDS, layer paths absolute, optional distance cap."""
    doc = tomllib.loads(REGION_TOML.read_text())
    doc["region"]["bounds"] = SUB_BOUNDS
    for layer in doc["layers"].values():
        layer["path"] = str(REGION_TOML.parent / layer["path"])
    if max_distance_m is not None:
        doc["features"]["road_distance"]["max_distance_m"] = max_distance_m
    doc["likelihood"].update(likelihood)
    return write_config(tmp_path / "region.toml", doc)


def in_memory(path: Path) -> TerrainPrior:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return build_region_prior(load_config(path), progress=False)


def test_tiled_build_is_bit_identical_with_a_configured_cap(tmp_path, client):
    cfg_path = region(tmp_path)
    ref = in_memory(cfg_path)
    out = tmp_path / "out" / "prior.tif"
    summary = build_prior_tiled(load_config(cfg_path), out, client=client, tile=96, progress=False)
    assert summary["n_tiles"] == 16  # 300 = 3 x 96 + 12: ragged last row and column of tiles
    assert len(summary["workers"]) == 2
    got = TerrainPrior.read(out)
    assert got.grid == ref.grid
    np.testing.assert_array_equal(got.density, ref.density.astype(np.float32))
    np.testing.assert_array_equal(got.sat, ref.sat)
    np.testing.assert_array_equal(got.sat2, ref.sat2)
    assert got.model == ref.model
    with rasterio.open(out) as src:  # a compressed, tiled GeoTIFF with overviews (the COG layout)
        assert src.compression.name.lower() == "deflate"
        assert src.block_shapes[0] == (256, 256)
        assert src.overviews(1)
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
    assert sorted(p.name for p in out.parent.iterdir()) == ["prior.qml", "prior.sat.npy", "prior.sat2.npy", "prior.tif"]


def test_derived_cap_matches_uncapped_build_within_road_tail(tmp_path, client):
    """No max_distance_m: the cap comes from the road term (within 1e-12 of mv), so r differs by
    at most a relative 1e-12 from the uncapped in-memory build; the prior within that plus rounding."""
    cfg_path = region(tmp_path, max_distance_m=None)
    ref = in_memory(cfg_path)
    out = tmp_path / "prior.tif"
    summary = build_prior_tiled(load_config(cfg_path), out, client=client, tile=128, progress=False)
    rmd, mv = 100.0, 0.1
    assert summary["distance_caps_m"]["road_distance"] == pytest.approx(rmd * (1 + np.sqrt(2 * np.log((1 - mv) / (1e-12 * mv)))))
    got = TerrainPrior.read(out)
    np.testing.assert_allclose(got.sat, ref.sat, rtol=1e-11, atol=0)
    np.testing.assert_allclose(got.sat2, ref.sat2, rtol=1e-11, atol=1e-30)
    np.testing.assert_allclose(got.density, ref.density.astype(np.float32), rtol=1.2e-7, atol=0)


@functools.cache
def whole_grid():
    config = load_config(region(Path(tempfile.mkdtemp())))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return config, build_features(config, progress=False)


@settings(max_examples=4, deadline=None)
@given(tile=st.integers(17, 200), pick=st.integers(0, 10**6))
def test_tile_features_equal_whole_grid_features(tile, pick):
    """Tiles' features (halos: slope 1 cell, distance the cap) equal the whole-grid features: the
    first and last tile (grid corners) and one picked at random."""
    config, whole = whole_grid()
    specs = needed_features(config, config.model.terms)
    caps = distance_caps(config, config.model, specs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        windows = tile_windows(config.grid, tile)
        for win in {windows[0], windows[-1], windows[pick % len(windows)]}:
            part = tile_features(config, specs, caps, win)
            for f in part:
                ref = whole[f.name].values[win.row_off : win.row_off + win.height, win.col_off : win.col_off + win.width]
                np.testing.assert_array_equal(f.values, ref, err_msg=f"{f.name} at {win}")


def test_vector_reads_near_a_tile_reach_its_margin_and_buffer(tmp_path):
    """Each tile reads only the vector features near it; roads that reach a tile through a wide
    margin_m, a buffer_m or all_touched still count, so every tile equals the whole-grid features."""
    doc = tomllib.loads(region(tmp_path).read_text())
    doc["features"]["road_distance"].update(margin_m=400.0, buffer_m=35.0, all_touched=True)
    doc["features"]["road_band"] = {"type": "mask", "layers": ["roads"], "buffer_m": 130.0, "all_touched": True}
    config = load_config(write_config(tmp_path / "reach.toml", doc))
    specs = needed_features(config, ["road_distance", "road_band", "water", "surface"])
    caps = distance_caps(config, config.model, specs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = build_features(dataclasses.replace(config, features=specs), progress=False)
        for win in tile_windows(config.grid, 37):
            for f in tile_features(config, specs, caps, win):
                ref = whole[f.name].values[win.row_off : win.row_off + win.height, win.col_off : win.col_off + win.width]
                np.testing.assert_array_equal(f.values, ref, err_msg=f"{f.name} at {win}")


@settings(max_examples=20, deadline=None)
@given(h=st.integers(1, 300), w=st.integers(1, 300), seed=st.integers(0, 2**16))
def test_npy_rows_sum_and_windows(h, w, seed, tmp_path_factory):
    """Writes into windows land where a plain array would have them; the pairwise sum is numpy's, bit for bit."""
    rng = np.random.default_rng(seed)
    a = rng.random((h, w)) ** 3 * 10.0 ** rng.integers(-5, 5)
    store = NpyRows(tmp_path_factory.mktemp("rows") / "a.npy", (h, w), create=True)
    for r0 in range(0, h, 97):
        for c0 in range(0, w, 61):
            store.write(r0, c0, a[r0 : r0 + 97, c0 : c0 + 61])
    np.testing.assert_array_equal(np.load(store.path), a)
    assert store.pairwise_sum() == float(a.sum())


def test_pairwise_sum_over_many_leaves(tmp_path, monkeypatch):
    import pipeline.tiled.store as store_module

    monkeypatch.setattr(store_module, "_SUM_LEAF", 1000)
    a = np.random.default_rng(3).random((401, 377))
    store = NpyRows(tmp_path / "a.npy", a.shape, create=True)
    store.write(0, 0, a)
    assert store.pairwise_sum() == float(a.sum())


def test_distance_caps_from_config_classes_and_tables(tmp_path):
    """A configured max_distance_m wins; else classes breaks and binned edges bound the distance
    exactly (their last class/bin is open); a distance nothing bounds is an error naming it."""
    doc = tomllib.loads(region(tmp_path, max_distance_m=None).read_text())
    doc["features"]["near_road"] = {"type": "classes", "source": "road_distance", "breaks": [50.0, 250.0]}
    config = load_config(write_config(tmp_path / "caps.toml", doc))
    binned = LikelihoodModel.from_dict({"likelihood": {"road_distance": {"type": "binned", "edges": [0.0, 400.0], "values": [1.0, 0.5]}}})
    specs = needed_features(config, ["near_road"])
    assert set(specs) == {"near_road", "road_distance"}
    assert distance_caps(config, binned, specs) == {"road_distance": 400.0}
    assert distance_caps(config, LikelihoodModel({}), specs) == {"road_distance": 250.0}
    with pytest.raises(TiledBuildError, match=r"features.road_distance.*max_distance_m"):
        distance_caps(config, LikelihoodModel({}), needed_features(config, ["road_distance"]))
    doc["features"]["road_distance"]["max_distance_m"] = 900.0
    config = load_config(write_config(tmp_path / "caps.toml", doc))
    assert distance_caps(config, binned, needed_features(config, ["road_distance"])) == {"road_distance": 900.0}


def test_zero_prior_fails_and_writes_nothing(tmp_path, client):
    cfg = region(tmp_path, water={"type": "categorical", "values": {"dry": 0.0, "water": 0.0}})
    out = tmp_path / "out" / "prior.tif"
    with pytest.raises(PriorError, match="water"):
        build_prior_tiled(load_config(cfg), out, client=client, tile=150, progress=False)
    assert not out.exists() and not any(p.exists() for p in sat_paths(out))
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize("problem", ["missing", "no_crs"])
def test_bad_dem_fails_per_tile_as_in_memory(tmp_path, problem):
    """A tile reports a bad raster layer with read_raster's own error, naming the file and layer."""
    doc = tomllib.loads(region(tmp_path).read_text())
    dem = tmp_path / "dem.tif"
    if problem == "no_crs":
        write_raster(dem, np.zeros((50, 50), dtype=np.float32), Affine(100.0, 0, 300000, 0, -100.0, 6200000), None)
    doc["layers"]["dem"]["path"] = str(dem)
    config = load_config(write_config(tmp_path / "bad.toml", doc))
    specs = needed_features(config, ["slope_class"])
    with pytest.raises(LayerError, match=r"dem.tif.*\[layers.dem\].*(not found|no CRS)"):
        tile_features(config, specs, {}, tile_windows(config.grid, 100)[0])
