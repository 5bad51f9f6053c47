"""FeatureStack.to_xarray: one variable per feature, coordinates, CRS, nodata and labels, against the stack and rasterio."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE, Grid

pytest.importorskip("rioxarray")

GRID = Grid.from_bounds((500000.0, 4000000.0, 500300.0, 4000200.0), 10.0, "EPSG:32610")  # 20 x 30 cells


@pytest.fixture(scope="module")
def stack() -> FeatureStack:
    rng = np.random.default_rng(0)
    s = FeatureStack(GRID)
    slope = rng.uniform(0, 40, GRID.shape)
    slope[3, 4] = np.nan
    s.add(Feature("slope", slope, "continuous", units="deg"))
    codes = rng.integers(0, 3, GRID.shape).astype(np.int16)
    codes[0, 0] = NODATA_CODE
    s.add(Feature("land", codes, "categorical", labels={0: "grass", 1: "forest", 2: "water"}))
    return s


def test_dataset_matches_stack(stack):
    ds = stack.to_xarray()
    assert sorted(ds.data_vars) == ["land", "slope"]
    np.testing.assert_array_equal(ds["slope"].values, stack["slope"].values)
    np.testing.assert_array_equal(ds["land"].values, stack["land"].values)
    assert ds["land"].dtype == np.int16
    assert json.loads(ds["land"].attrs["labels"]) == {"0": "grass", "1": "forest", "2": "water"}
    assert ds["slope"].attrs["units"] == "deg" and ds["slope"].attrs["kind"] == "continuous"
    assert ds["land"].rio.nodata == NODATA_CODE and np.isnan(ds["slope"].rio.nodata)
    xs, ys = GRID.axes()
    np.testing.assert_allclose(ds.x.values, xs)
    np.testing.assert_allclose(ds.y.values, ys)
    assert ds.rio.crs == GRID.crs and ds.rio.transform() == GRID.transform


def test_sel_nearest_equals_sample(stack):
    rng = np.random.default_rng(2)
    xmin, ymin, xmax, ymax = GRID.bounds
    u = rng.integers(0, GRID.width, 100) + 0.5 + rng.uniform(-0.45, 0.45, 100)
    v = rng.integers(0, GRID.height, 100) + 0.5 + rng.uniform(-0.45, 0.45, 100)
    x, y = xmin + u * GRID.dx, ymax - v * GRID.dy
    want = stack.sample(x, y)
    ds = stack.to_xarray()
    for name in ("slope", "land"):
        got = np.array([ds[name].sel(x=xi, y=yi, method="nearest").item() for xi, yi in zip(x, y, strict=True)])
        np.testing.assert_array_equal(got, want[name])


@pytest.mark.parametrize("name", ["slope", "land"])
def test_to_raster_round_trip(stack, tmp_path, name):
    path = tmp_path / f"{name}.tif"
    stack.to_xarray()[name].rio.to_raster(path)
    with rasterio.open(path) as src:
        np.testing.assert_array_equal(src.read(1), stack[name].values)
        assert src.transform == GRID.transform and src.crs == GRID.crs
        assert src.nodata == NODATA_CODE if name == "land" else np.isnan(src.nodata)
