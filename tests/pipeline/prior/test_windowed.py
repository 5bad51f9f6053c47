"""A prior read window by window holds the numbers an in-memory read holds, and checks the file as fully.

Oracle: ``TerrainPrior.read(path, windowed=False)`` (the whole float32 band as float64)."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.gis.grid import Grid
from pipeline.prior import TerrainPrior
from pipeline.prior.terrain import PriorError
from pipeline.prior.windowed import WINDOWED_CELLS, WindowedDensity

H, W = 600, 333  # more than one 256-row band and block column


@pytest.fixture(scope="module")
def prior_path(tmp_path_factory) -> Path:
    rng = np.random.default_rng(3)
    r = rng.random((H, W)) ** 3
    r[100:140, 50:90] = 0.0
    grid = Grid("EPSG:32734", Affine(20.0, 0.0, 300_000.0, 0.0, -20.0, 6_200_000.0), H, W)
    return TerrainPrior.from_array(r, grid, {"seed": 3}).write(tmp_path_factory.mktemp("w") / "prior.tif")


@pytest.fixture(scope="module")
def both(prior_path: Path) -> tuple[TerrainPrior, TerrainPrior]:
    return TerrainPrior.read(prior_path, windowed=False), TerrainPrior.read(prior_path, windowed=True)


def test_small_priors_are_read_into_memory_by_default(prior_path: Path) -> None:
    assert H * W <= WINDOWED_CELLS
    assert isinstance(TerrainPrior.read(prior_path).density, np.ndarray)


def test_the_windowed_density_is_the_in_memory_one(both) -> None:
    mem, win = both
    assert isinstance(win.density, WindowedDensity) and win.density.shape == (H, W)
    np.testing.assert_array_equal(np.asarray(win.density), mem.density)
    assert win.max_density == mem.max_density == float(mem.density.max())
    np.testing.assert_array_equal(win.sat, mem.sat)


@settings(max_examples=40, deadline=None)
@given(r0=st.integers(-5, H + 5), r1=st.integers(-5, H + 5), c0=st.integers(-5, W + 5), c1=st.integers(-5, W + 5))
def test_any_window_is_the_array_slice(both, r0: int, r1: int, c0: int, c1: int) -> None:
    mem, win = both
    lo_r, lo_c = max(r0, 0), max(c0, 0)  # slices with numpy's meaning of non-negative bounds
    np.testing.assert_array_equal(win.density[lo_r:r1, lo_c:c1], mem.density[lo_r:r1, lo_c:c1])


def test_cells_and_points_are_the_array_values(both) -> None:
    mem, win = both
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, H, 5000), rng.integers(0, W, 5000)
    np.testing.assert_array_equal(win.density[rows, cols], mem.density[rows, cols])
    x0, y0, x1, y1 = mem.grid.bounds
    x, y = rng.uniform(x0 - 500, x1 + 500, 3000), rng.uniform(y0 - 500, y1 + 500, 3000)
    np.testing.assert_array_equal(win.density_at(x, y), mem.density_at(x, y))
    with pytest.raises(IndexError, match="outside the"):
        win.density[np.array([H]), np.array([0])]


def test_a_pickled_density_reopens_its_file(both) -> None:
    """What a Dask worker gets: the path, not an open dataset."""
    mem, win = both
    copy = pickle.loads(pickle.dumps(win.density))
    np.testing.assert_array_equal(copy[300:320, 200:333], mem.density[300:320, 200:333])
    assert copy.max == win.density.max


def test_a_bad_cell_in_a_later_band_is_named(tmp_path: Path, prior_path: Path) -> None:
    bad = tmp_path / "prior.tif"
    for p in prior_path.parent.iterdir():
        (tmp_path / p.name).write_bytes(p.read_bytes())
    with rasterio.open(bad, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:
        d = dst.read(1)
        d[400, 7] = np.nan
        dst.write(d, 1)
    with pytest.raises(PriorError, match=r"density must be finite and >= 0; 1 bad cells, first at row 400, col 7 \(in rows 256-511\)"):
        TerrainPrior.read(bad, windowed=True)
    with pytest.raises(PriorError, match=r"density must be finite and >= 0; 1 bad cells, first at row 400, col 7;"):
        TerrainPrior.read(bad, windowed=False)
