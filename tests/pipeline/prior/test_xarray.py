"""TerrainPrior.to_xarray: coordinates, CRS and transform the rioxarray way, against the prior itself and rasterio."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior

pytest.importorskip("rioxarray")

GRID = Grid.from_bounds((300000.0, 6186000.0, 300700.0, 6186400.0), 20.0, "EPSG:32734")  # 20 x 35 cells


@pytest.fixture(scope="module")
def prior() -> TerrainPrior:
    rng = np.random.default_rng(0)
    return TerrainPrior.from_array(rng.gamma(2.0, 1.0, GRID.shape), GRID, {"test": True})


def test_coordinates_are_cell_centres_in_metres(prior):
    da = prior.to_xarray()
    assert da.dims == ("y", "x") and da.name == "density"
    np.testing.assert_array_equal(da.values, prior.density)
    np.testing.assert_allclose(da.x.values, 300010.0 + 20.0 * np.arange(35))
    np.testing.assert_allclose(da.y.values, 6186390.0 - 20.0 * np.arange(20))
    assert da.rio.crs == GRID.crs
    assert da.rio.transform() == GRID.transform
    assert json.loads(da.attrs["model"]) == {"test": True}


def test_sel_nearest_equals_density_at(prior):
    rng = np.random.default_rng(1)
    xmin, ymin, xmax, ymax = GRID.bounds
    # keep off the cell edges, where "nearest" and the half-open cells of density_at may differ
    u = rng.integers(0, GRID.width, 200) + rng.uniform(0.05, 0.95, 200)
    v = rng.integers(0, GRID.height, 200) + rng.uniform(0.05, 0.95, 200)
    x, y = xmin + u * GRID.dx, ymax - v * GRID.dy
    da = prior.to_xarray()
    got = np.array([float(da.sel(x=xi, y=yi, method="nearest")) for xi, yi in zip(x, y, strict=True)])
    np.testing.assert_array_equal(got, prior.density_at(x, y))


def test_to_raster_round_trip(prior, tmp_path):
    path = tmp_path / "density.tif"
    prior.to_xarray().rio.to_raster(path)
    with rasterio.open(path) as src:
        np.testing.assert_array_equal(src.read(1), prior.density)
        assert src.transform == GRID.transform
        assert src.crs == GRID.crs


def test_plot(prior):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    mesh = prior.to_xarray().plot()
    assert mesh.get_array().size == GRID.height * GRID.width
    matplotlib.pyplot.close("all")
