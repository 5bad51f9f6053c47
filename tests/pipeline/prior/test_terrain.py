"""TerrainPrior against direct sums of cell mass x overlap area, normalisation, and atomic file round trips."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import stats

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import PriorError, TerrainPrior, density_table_rows


def make_grid(h: int, w: int, dx: float, dy: float) -> Grid:
    return Grid("EPSG:32734", Affine(dx, 0.0, 250_000.0, 0.0, -dy, 6_200_000.0), h, w)


def direct_rect_sum(values: np.ndarray, grid: Grid, x0, x1, y0, y1) -> float:
    """Sum over cells of value per m^2 x area of the cell inside [x0, x1] x [y0, y1].

    Overlaps are computed from the grid's north-west corner: at UTM northings (~6e6 m) absolute
    cell edges carry ~1e-9 m rounding, too much for sub-metre cells at this test's tolerance."""
    xmin, _, _, ymax = grid.bounds
    x0, x1 = x0 - xmin, x1 - xmin
    s0, s1 = ymax - y1, ymax - y0  # distances south of the top edge
    c = np.arange(grid.width)
    r = np.arange(grid.height)
    ox = np.maximum(0.0, np.minimum(x1, (c + 1) * grid.dx) - np.maximum(x0, c * grid.dx))
    oy = np.maximum(0.0, np.minimum(s1, (r + 1) * grid.dy) - np.maximum(s0, r * grid.dy))
    return float((values * oy[:, None] * ox[None, :]).sum())


@st.composite
def prior_and_rects(draw):
    h, w = draw(st.integers(1, 7)), draw(st.integers(1, 7))
    dx, dy = draw(st.floats(0.5, 40.0)), draw(st.floats(0.5, 40.0))
    r = draw(arrays(np.float64, (h, w), elements=st.one_of(st.just(0.0), st.floats(0.01, 100.0))))
    if not r.any():
        r[draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = 1.0
    grid = make_grid(h, w, dx, dy)
    xmin, ymin, xmax, ymax = grid.bounds
    # corners anywhere from two cells outside the grid, fractional in general
    xs = st.floats(xmin - 2 * dx, xmax + 2 * dx)
    ys = st.floats(ymin - 2 * dy, ymax + 2 * dy)
    rects = draw(st.lists(st.tuples(xs, xs, ys, ys), min_size=1, max_size=8))
    rects = np.array([(min(a, b), max(a, b), min(c, d), max(c, d)) for a, b, c, d in rects])
    return TerrainPrior.from_array(r, grid), rects


@settings(max_examples=100, deadline=None)
@given(pr=prior_and_rects())
def test_rect_sum_matches_direct_sum(pr):
    prior, rects = pr
    x0, x1, y0, y1 = rects.T
    got = prior.rect_sum(x0, x1, y0, y1)
    got2 = prior.rect_sum(x0, x1, y0, y1, squared=True)
    for k, (a, b, c, d) in enumerate(rects):
        assert got[k] == pytest.approx(direct_rect_sum(prior.density, prior.grid, a, b, c, d), rel=1e-9, abs=1e-12)
        want2 = direct_rect_sum(prior.density**2, prior.grid, a, b, c, d)
        assert got2[k] == pytest.approx(want2, rel=1e-9, abs=1e-12 * max(1.0, float(prior.density.max() ** 2)))


@settings(max_examples=40, deadline=None)
@given(pr=prior_and_rects())
def test_pixel_and_world_rectangles_agree(pr):
    prior, rects = pr
    x0, x1, y0, y1 = rects.T
    u0, v1 = prior.grid.to_pixel(x0, y0)
    u1, v0 = prior.grid.to_pixel(x1, y1)
    np.testing.assert_allclose(prior.rect_sum_px(u0, u1, v0, v1), prior.rect_sum(x0, x1, y0, y1), rtol=1e-12, atol=1e-15)


def test_single_cell_fraction_and_outside():
    grid = make_grid(3, 4, 20.0, 10.0)
    r = np.arange(12, dtype=float).reshape(3, 4) + 1
    prior = TerrainPrior.from_array(r, grid)
    xmin, ymin, xmax, ymax = grid.bounds
    mass = r / r.sum()
    # a quarter of cell (1, 2): x in [xmin+40, xmin+50], y in [ymax-20, ymax-15]
    q = prior.rect_sum(xmin + 40, xmin + 50, ymax - 20, ymax - 15)
    assert q == pytest.approx(mass[1, 2] / 4)
    # wholly outside, and degenerate
    assert prior.rect_sum(xmax + 1, xmax + 50, ymin, ymax) == 0.0
    assert prior.rect_sum(xmin, xmax, ymax + 1, ymax + 9) == 0.0
    assert prior.rect_sum(xmin + 5, xmin + 5, ymin, ymax) == 0.0
    # a rectangle covering the grid and more holds all the mass
    assert prior.rect_sum(xmin - 100, xmax + 100, ymin - 100, ymax + 100) == pytest.approx(1.0)


@settings(max_examples=50, deadline=None)
@given(pr=prior_and_rects())
def test_density_integrates_to_one(pr):
    prior, _ = pr
    assert prior.density.sum() * prior.grid.cell_area == pytest.approx(1.0, rel=1e-12)
    assert prior.sat[-1, -1] == pytest.approx(1.0, rel=1e-12)
    assert (prior.density >= 0).all()


def test_density_at_points():
    grid = make_grid(4, 5, 10.0, 30.0)
    r = np.random.default_rng(0).random((4, 5))
    prior = TerrainPrior.from_array(r, grid)
    xc, yc = grid.cell_centres()
    np.testing.assert_allclose(prior.density_at(xc, yc), r / (r.sum() * grid.cell_area))
    xmin, ymin, xmax, ymax = grid.bounds
    np.testing.assert_array_equal(prior.density_at(np.array([xmin - 1, xmax + 1]), np.array([ymin, ymax])), 0.0)


def test_uniform():
    grid = make_grid(3, 3, 20.0, 20.0)
    prior = TerrainPrior.uniform(grid)
    np.testing.assert_allclose(prior.density, 1.0 / (9 * 400.0))


@pytest.mark.parametrize(
    ("r", "match"),
    [
        (np.array([[1.0, np.nan], [1.0, 1.0]]), "row 0, col 1"),
        (np.array([[1.0, 1.0], [-0.5, 1.0]]), "row 1, col 0"),
        (np.array([[1.0, 1.0], [1.0, np.inf]]), "row 1, col 1"),
        (np.zeros((2, 2)), "zero everywhere"),
        (np.ones((3, 2)), "shape"),
    ],
)
def test_bad_likelihood(r, match):
    with pytest.raises(PriorError, match=match):
        TerrainPrior.from_array(r, make_grid(2, 2, 1.0, 1.0))
    assert issubclass(PriorError, ValueError)


def test_rect_sum_needs_ordered_corners():
    prior = TerrainPrior.uniform(make_grid(2, 2, 1.0, 1.0))
    with pytest.raises(ValueError, match="x0 <= x1"):
        prior.rect_sum(1.0, 0.0, 0.0, 1.0)


def test_write_read_round_trip(tmp_path):
    grid = make_grid(30, 20, 20.0, 15.0)
    r = np.random.default_rng(1).random((30, 20)) ** 3
    prior = TerrainPrior.from_array(r, grid, {"features": ["slope", "road_distance"], "seed": 1})
    path = prior.write(tmp_path / "out" / "prior.tif")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["prior.qml", "prior.sat.npy", "prior.sat2.npy", "prior.tif"]
    back = TerrainPrior.read(path)
    assert back.grid == grid
    assert back.model == prior.model
    np.testing.assert_allclose(back.density, prior.density, rtol=1e-6)  # float32 on disk
    np.testing.assert_array_equal(back.sat, prior.sat)
    np.testing.assert_array_equal(back.sat2, prior.sat2)
    with rasterio.open(path) as src:
        assert src.dtypes == ("float32",)
        assert src.crs == grid.crs
    rects = (grid.bounds[0] + 3.3, grid.bounds[0] + 207.1, grid.bounds[1] + 1.9, grid.bounds[1] + 300.0)
    assert back.rect_sum(*rects) == prior.rect_sum(*rects)


def test_failed_write_leaves_nothing(tmp_path):
    grid = make_grid(5, 5, 10.0, 10.0)
    bad = TerrainPrior.from_array(np.ones((5, 5)), grid, {"unserialisable": object()})
    with pytest.raises(TypeError):
        bad.write(tmp_path / "prior.tif")
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_previous_prior(tmp_path):
    grid = make_grid(5, 5, 10.0, 10.0)
    good = TerrainPrior.from_array(np.arange(25.0).reshape(5, 5) + 1, grid)
    path = good.write(tmp_path / "prior.tif")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    bad = TerrainPrior.from_array(np.ones((5, 5)), grid, {"unserialisable": object()})
    with pytest.raises(TypeError):
        bad.write(path)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(PriorError, match="prior.tif: missing"):
        TerrainPrior.read(tmp_path / "prior.tif")
    TerrainPrior.uniform(make_grid(2, 2, 1.0, 1.0)).write(tmp_path / "prior.tif")
    (tmp_path / "prior.sat2.npy").unlink()
    with pytest.raises(PriorError, match="prior.sat2.npy: missing"):
        TerrainPrior.read(tmp_path / "prior.tif")
    corrupt = tmp_path / "c" / "prior.tif"
    TerrainPrior.uniform(make_grid(2, 2, 1.0, 1.0)).write(corrupt)
    corrupt.write_bytes(b"not a tiff")
    with pytest.raises(PriorError, match="prior.tif: cannot read"):
        TerrainPrior.read(corrupt)


def random_prior(height: int, width: int, cell: float, seed: int, zeros: bool = True) -> TerrainPrior:
    """A seeded uneven prior (cubed uniform values, 20 % structural zeros unless ``zeros`` is False)."""
    rng = np.random.default_rng(seed)
    r = rng.random((height, width)) ** 3
    if zeros:
        r[rng.random((height, width)) < 0.2] = 0.0  # structural zeros, like water
    grid = Grid("EPSG:32633", Affine(cell, 0.0, 300000.0, 0.0, -cell, 6200000.0), height, width)
    return TerrainPrior.from_array(r, grid)


def _sampled_cell_counts(prior: TerrainPrior, pts: np.ndarray) -> np.ndarray:
    u, v = prior.grid.to_pixel(pts[:, 0], pts[:, 1])
    counts = np.zeros(prior.grid.shape, dtype=np.int64)
    np.add.at(counts, (v.astype(int), u.astype(int)), 1)
    return counts


def test_sampler_cell_frequencies_matchrandom_prior() -> None:
    prior = random_prior(6, 9, 20.0, 0)
    n = 40000
    pts = prior.sample(n, np.random.default_rng(1))
    counts = _sampled_cell_counts(prior, pts)
    mass = prior.density * prior.grid.cell_area
    assert counts[mass == 0].sum() == 0
    pos = mass > 0
    _, p = stats.chisquare(counts[pos], n * mass[pos] / mass[pos].sum())
    assert p > 1e-3


def test_sampler_is_uniform_inside_cells() -> None:
    prior = random_prior(4, 5, 30.0, 2)
    pts = prior.sample(20000, np.random.default_rng(3))
    u, v = prior.grid.to_pixel(pts[:, 0], pts[:, 1])
    for frac in (u % 1.0, v % 1.0):
        assert stats.kstest(frac, "uniform").pvalue > 1e-3


def test_sampler_respects_region() -> None:
    prior = random_prior(20, 20, 10.0, 4, zeros=False)
    region = (300050.0, 6199850.0, 300120.0, 6199950.0)  # columns 5..12, rows 5..15
    pts = prior.sample(30000, np.random.default_rng(5), region)
    assert (pts[:, 0] >= region[0]).all() and (pts[:, 0] < region[2]).all()
    assert (pts[:, 1] >= region[1]).all() and (pts[:, 1] < region[3]).all()
    counts = _sampled_cell_counts(prior, pts)[5:15, 5:12]
    mass = prior.density[5:15, 5:12]
    _, p = stats.chisquare(counts.ravel(), 30000 * mass.ravel() / mass.sum())
    assert p > 1e-3
    with pytest.raises(ValueError, match="cell-aligned"):
        prior.sample(10, np.random.default_rng(0), (300055.0, 6199850.0, 300120.0, 6199950.0))


def test_tables_made_on_use_and_streamed_are_the_fused_kernels(tmp_path):
    """A prior from from_array has no tables until used; made whole, or band by band as write() streams
    them (600 rows: three 256-row strips), they are the numbers of density_table_rows over the whole grid."""
    grid = make_grid(600, 9, 20.0, 15.0)
    r = np.random.default_rng(3).random((600, 9)) ** 2
    r[100:130] = 0.0
    total = float(r.sum()) * grid.cell_area
    density, sat, sat2 = np.empty_like(r), np.zeros((601, 10)), np.zeros((601, 10))
    density_table_rows(r, total, grid.cell_area, np.zeros(10), np.zeros(10), density, sat[1:], sat2[1:])
    streamed = TerrainPrior.from_array(r, grid)
    assert streamed._tables is None
    back = TerrainPrior.read(streamed.write(tmp_path / "prior.tif"))
    assert streamed._tables is None  # writing did not make the whole tables
    np.testing.assert_array_equal(streamed.density, density)
    for table, expected in ((back.sat, sat), (back.sat2, sat2), (streamed.sat, sat), (streamed.sat2, sat2)):
        np.testing.assert_array_equal(table, expected)
    reused = r.copy()
    assert TerrainPrior.from_array(reused, grid, reuse=True).density is reused


def test_tables_both_or_neither():
    grid = make_grid(3, 4, 10.0, 10.0)
    with pytest.raises(PriorError, match="both sat and sat2"):
        TerrainPrior(grid, np.ones((3, 4)), np.zeros((4, 5)), None)
    with pytest.raises(PriorError, match="float64 density"):
        TerrainPrior(grid, np.ones((3, 4), dtype=np.float32), None, None)
