"""Rasterized masks and categories vs shapely geometry tests at cell centres and on cell boxes."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from affine import Affine
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from pipeline.features import rasterize
from pipeline.gis.grid import NODATA_CODE, Grid
from tests.pipeline.gis_helpers import cell_boxes

# non-square cells, 20 m wide and 25 m tall, so row/column mix-ups show
GRID = Grid("EPSG:32634", Affine(20.0, 0.0, 1000.0, 0.0, -25.0, 2600.0), 24, 30)
XC, YC = GRID.cell_centres()
BOXES = cell_boxes(GRID.transform, GRID.shape)
INTERIORS = shapely.buffer(BOXES, -1e-6, join_style="mitre")


def near_boundary(geom, tol: float = 1e-6) -> np.ndarray:
    """Cell centres within ``tol`` metres of the geometry's boundary, where inside/outside is a tie."""
    return shapely.distance(shapely.boundary(geom), shapely.points(XC, YC)) < tol


coords = st.tuples(st.floats(950, 1650), st.floats(1950, 2650))


@st.composite
def polygons(draw) -> shapely.Geometry:
    """Random valid polygons, some with holes, some off the grid edges."""
    pts = draw(st.lists(coords, min_size=3, max_size=12))
    hull = shapely.convex_hull(shapely.multipoints(pts))
    assume(hull.geom_type == "Polygon" and hull.area > 1.0)  # collinear points make lines, not areas
    if draw(st.booleans()):
        hull = shapely.difference(hull, shapely.buffer(shapely.centroid(hull), draw(st.floats(5, 80))))
    return hull


@settings(max_examples=60, deadline=None)
@given(polygons())
def test_polygon_mask_is_cell_centre_containment(poly) -> None:
    m = rasterize.mask(np.array([poly]), GRID)
    expected = shapely.contains_xy(poly, XC, YC)
    tie = near_boundary(poly)
    np.testing.assert_array_equal(m[~tie], expected[~tie])
    codes = rasterize.mask(np.array([poly]), GRID, dtype=np.int16)  # burned as 0/1 codes: the same cells
    assert codes.dtype == np.int16
    np.testing.assert_array_equal(codes, m.astype(np.int16))


@settings(max_examples=40, deadline=None)
@given(st.lists(coords, min_size=2, max_size=6), st.floats(3.0, 60.0))
def test_buffered_line_mask(pts, width) -> None:
    line = shapely.LineString(pts)
    if line.length == 0:
        return
    m = rasterize.mask(np.array([line]), GRID, buffer_m=width)
    band = shapely.buffer(line, width)
    # shapely's buffer approximates arcs with segments; centres that close to the edge are ties
    tie = near_boundary(band, tol=width * 0.02 + 1e-6)
    expected = shapely.distance(line, shapely.points(XC, YC)) <= width
    np.testing.assert_array_equal(m[~tie], expected[~tie])


@settings(max_examples=40, deadline=None)
@given(st.lists(coords, min_size=2, max_size=6))
@example(pts=[(950.0, 2000.0), (1001.0, 2000.0)])  # along the grid's southern edge
@example(pts=[(1040.0, 2100.0), (1040.0, 2500.0)])  # along an inner cell edge
def test_all_touched_line_mask_covers_every_crossed_cell(pts) -> None:
    line = shapely.LineString(pts)
    if line.length == 0:
        return
    m = rasterize.mask(np.array([line]), GRID, all_touched=True)
    # the line runs through the cell's interior (a line along a cell edge belongs to either side)
    crossed = shapely.length(shapely.intersection(INTERIORS, line)) > 1e-6
    touching = shapely.intersects(shapely.buffer(BOXES, 1e-6), line)  # or at least meets its closure
    assert np.all(m[crossed]), "a cell the road crosses is missing from the all_touched mask"
    assert not np.any(m & ~touching), "the mask marks a cell the road never touches"


def test_mask_without_all_touched_can_miss_thin_lines() -> None:
    """Why roads are burned all_touched: a diagonal line clips corners that centre-sampling skips."""
    line = shapely.LineString([(1000.0, 2600.0), (1600.0, 2000.0)])
    crossed = shapely.length(shapely.intersection(INTERIORS, line)) > 1e-6
    assert rasterize.mask(np.array([line]), GRID, all_touched=True)[crossed].all()
    assert not rasterize.mask(np.array([line]), GRID)[crossed].all()


def test_union_of_several_polygons_and_empty_input() -> None:
    a = shapely.box(1010, 2010, 1200, 2300)
    b = shapely.Polygon([(1300, 2100), (1550, 2150), (1400, 2500)])
    m = rasterize.mask(np.array([a, b]), GRID)
    expected = shapely.contains_xy(a, XC, YC) | shapely.contains_xy(b, XC, YC)
    tie = near_boundary(a) | near_boundary(b)
    np.testing.assert_array_equal(m[~tie], expected[~tie])
    assert not rasterize.mask(np.empty(0, dtype=object), GRID).any()
    assert rasterize.mask(np.empty(0, dtype=object), GRID, dtype=np.int16).dtype == np.int16


@settings(max_examples=40, deadline=None)
@given(st.lists(polygons(), min_size=1, max_size=5), st.data())
def test_categories_later_polygons_win(polys, data) -> None:
    codes = np.array(data.draw(st.lists(st.integers(0, 9), min_size=len(polys), max_size=len(polys))))
    got = rasterize.categories(np.array(polys, dtype=object), codes, GRID)
    expected = np.full(GRID.shape, NODATA_CODE)
    tie = np.zeros(GRID.shape, dtype=bool)
    for poly, code in zip(polys, codes, strict=True):  # brute force, in drawing order
        expected[shapely.contains_xy(poly, XC, YC)] = code
        tie |= near_boundary(poly)
    np.testing.assert_array_equal(got[~tie], expected[~tie])
    assert got.dtype == np.int32


lines = st.lists(coords, min_size=2, max_size=6).map(shapely.LineString)


@given(st.lists(st.one_of(lines, st.lists(lines, min_size=1, max_size=3).map(shapely.MultiLineString)), max_size=5))
@settings(max_examples=40, deadline=None)
def test_line_ends_are_each_parts_first_and_last_vertex(geoms) -> None:
    """Vectorised end points against a loop over every part's coordinate list."""
    brute = sorted(c for g in geoms for part in getattr(g, "geoms", [g]) for c in (part.coords[0], part.coords[-1]))
    got = sorted(tuple(p.coords[0]) for p in rasterize.line_ends(np.asarray(geoms, dtype=object)))
    assert got == brute


def test_line_ends_refuse_points_and_polygons() -> None:
    for bad, kind in ((shapely.Point(1, 2), "Point"), (shapely.box(0, 0, 1, 1), "Polygon")):
        with pytest.raises(ValueError, match=f"end points need lines.*{kind}"):
            rasterize.line_ends(np.asarray([shapely.LineString([(0, 0), (1, 1)]), bad], dtype=object))
    assert rasterize.line_ends(np.empty(0, dtype=object)).size == 0
