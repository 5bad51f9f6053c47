"""slope_deg against closed forms (planes, quadratics), gdaldem's no-data rule, and gdaldem itself when installed."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
import rasterio
from affine import Affine
from hypothesis import example, given, settings
from hypothesis import strategies as st

from pipeline.features.slope import slope_classes, slope_deg
from pipeline.gis.grid import NODATA_CODE


def centres(h: int, w: int, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """Map x (east) and y (north) of cell centres, row 0 at the north."""
    r, c = np.indices((h, w), dtype=np.float64)
    return (c + 0.5) * dx, -(r + 0.5) * dy


def angle(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan(np.hypot(gx, gy)))


shapes = st.tuples(st.integers(2, 12), st.integers(2, 12))
cell = st.floats(0.5, 40.0)
coef = st.floats(-3.0, 3.0)


@settings(max_examples=80, deadline=None)
@given(shape=shapes, dx=cell, dy=cell, a=coef, b=coef, c0=st.floats(-500, 500))
def test_plane_any_orientation_non_square(shape, dx, dy, a, b, c0):
    x, y = centres(*shape, dx, dy)
    dem = a * x + b * y + c0
    np.testing.assert_allclose(slope_deg(dem, dx, dy), angle(a, b) * np.ones(shape), atol=1e-8)


@settings(max_examples=80, deadline=None)
@given(shape=shapes, dx=cell, dy=cell, q=st.tuples(coef, coef, coef, coef, coef))
def test_quadratic_surface(shape, dx, dy, q):
    """Horn's 1-2-1 stencil is exact for quadratics inside the grid. At an edge the linear extrapolation
    turns the derivative across it into a one-sided difference, which for a quadratic is the exact
    derivative half a cell inward; the derivative along the edge stays central."""
    a, b, c, d, e = (v / 100.0 for v in q)
    h, w = shape
    x, y = centres(h, w, dx, dy)
    dem = a * x**2 + b * y**2 + c * x * y + d * x + e * y
    shift_x = np.zeros(w)
    shift_x[0], shift_x[-1] = dx / 2, -dx / 2
    shift_y = np.zeros((h, 1))
    shift_y[0], shift_y[-1] = -dy / 2, dy / 2  # row 0 is north: inward is south, -y
    gx = 2 * a * (x + shift_x) + c * y + d
    gy = 2 * b * (y + shift_y) + c * x + e
    np.testing.assert_allclose(slope_deg(dem, dx, dy), angle(gx, gy), atol=1e-7)


def test_paraboloid_interior_is_exact_gradient():
    dx, dy = 20.0, 12.5
    x, y = centres(60, 80, dx, dy)
    x0, y0 = x.mean(), y.mean()
    dem = 0.002 * (x - x0) ** 2 + 0.004 * (y - y0) ** 2
    got = slope_deg(dem, dx, dy)
    want = angle(0.004 * (x - x0), 0.008 * (y - y0))
    np.testing.assert_allclose(got[1:-1, 1:-1], want[1:-1, 1:-1], atol=1e-9)


def test_nan_neighbour_takes_centre_value():
    """z = a x with the east neighbour of cell (3, 3) missing: the Horn x-difference becomes
    (4 a x + 2 a dx) - 4 a (x - dx) = 6 a dx over 8 dx, i.e. 3/4 of the gradient."""
    dx, dy, a = 10.0, 10.0, 0.5
    x, _ = centres(7, 7, dx, dy)
    dem = a * x
    dem[3, 4] = np.nan
    got = slope_deg(dem, dx, dy)
    assert np.isnan(got[3, 4])
    assert got[3, 3] == pytest.approx(angle(0.75 * a, 0.0))
    # (2, 3) sees the hole in its south-east corner: x-difference (3a(x + dx) + a x) - 4a(x - dx) = 7 a dx;
    # y-difference: the south row sum loses a dx against the north one.
    assert got[2, 3] == pytest.approx(angle(7 / 8 * a, a * dx / (8 * dy)))
    assert got[1, 1] == pytest.approx(angle(a, 0.0))


def test_float32_keeps_dtype():
    x, y = centres(5, 6, 20.0, 20.0)
    dem = (0.1 * x + 0.2 * y).astype(np.float32)
    got = slope_deg(dem, 20.0, 20.0)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, angle(0.1, 0.2), atol=1e-3)


@pytest.mark.parametrize(
    ("dem", "dx", "match"),
    [
        (np.full((4, 4), np.nan), 1.0, "no data"),
        (np.zeros(4), 1.0, "2-D"),
        (np.zeros((1, 4)), 1.0, "2 x 2"),
        (np.zeros((3, 3)), -1.0, "dx"),
    ],
)
def test_bad_input(dem, dx, match):
    with pytest.raises(ValueError, match=match):
        slope_deg(dem, dx, 1.0)


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(st.one_of(st.floats(0, 90), st.just(float("nan"))), min_size=1, max_size=40),
    breaks=st.lists(st.floats(0.1, 89.0), min_size=1, max_size=5, unique=True).map(sorted),
    dtype=st.sampled_from([np.float64, np.float32]),
)
@example(values=[0.1, 0.09999999], breaks=[0.1], dtype=np.float32)  # float32(0.1) lies above the float64 break
def test_slope_classes_definition(values, breaks, dtype):
    """Class = the number of breaks at or above which the slope lies, a float32 slope compared as the
    float64 it holds (a break between a float32 and its float64 neighbours counts exactly)."""
    values = np.array(values, dtype=dtype)
    got = slope_classes(values.reshape(2, -1) if values.size % 2 == 0 else values.reshape(1, -1), breaks)
    for v, code in zip(values, got.ravel(), strict=True):
        if np.isnan(v):
            assert code == NODATA_CODE
        else:
            assert code == sum(float(v) >= b for b in breaks)


@pytest.mark.parametrize("breaks", [[], [10, 5], [1, np.nan]])
def test_slope_classes_bad_breaks(breaks):
    with pytest.raises(ValueError, match="breaks_deg"):
        slope_classes(np.zeros((2, 2)), breaks)


def gdaldem_slope(dem: np.ndarray, dx: float, dy: float, tmp_path) -> np.ndarray:
    src, dst = tmp_path / "dem.tif", tmp_path / "slope.tif"
    profile = dict(driver="GTiff", height=dem.shape[0], width=dem.shape[1], count=1, dtype="float32",
                   crs="EPSG:32734", transform=Affine(dx, 0, 0, 0, -dy, 0), nodata=np.nan)
    with rasterio.open(src, "w", **profile) as f:
        f.write(dem, 1)
    subprocess.run(["gdaldem", "slope", "-compute_edges", "-q", str(src), str(dst)], check=True)
    with rasterio.open(dst) as f:
        return f.read(1, masked=True).filled(np.nan)


needs_gdaldem = pytest.mark.skipif(shutil.which("gdaldem") is None, reason="gdaldem (GDAL command line tools) not installed")


@needs_gdaldem
def test_matches_gdaldem(tmp_path):
    """gdaldem slope -compute_edges on a rough DEM with holes; corner cells differ by design (module docstring)."""
    rng = np.random.default_rng(3)
    dem = rng.normal(0, 30, (40, 50)).cumsum(0).cumsum(1).astype(np.float32)
    dem[10:13, 20:22] = np.nan
    dx, dy = 20.0, 15.0
    ref = gdaldem_slope(dem, dx, dy, tmp_path)
    got = slope_deg(dem, dx, dy)
    corners = np.zeros(dem.shape, dtype=bool)
    corners[[0, 0, -1, -1], [0, -1, 0, -1]] = True
    np.testing.assert_allclose(got[~corners], ref[~corners], atol=1e-3)


@needs_gdaldem
def test_gdaldem_corners_halve_a_plane(tmp_path):
    """The one documented difference: gdaldem repeats the corner column, halving a plane's x-gradient there."""
    x, _ = centres(6, 7, 20.0, 20.0)
    dem = (0.5 * x).astype(np.float32)
    ref = gdaldem_slope(dem, 20.0, 20.0, tmp_path)
    corners = ([0, 0, -1, -1], [0, -1, 0, -1])
    np.testing.assert_allclose(ref[corners], angle(0.25, 0.0), atol=1e-4)
    np.testing.assert_allclose(slope_deg(dem, 20.0, 20.0)[corners], angle(0.5, 0.0), atol=1e-4)


@settings(max_examples=25, deadline=None)
@given(shape=st.tuples(st.integers(2, 40), st.integers(2, 40)), holes=st.floats(0.0, 0.5),
       dtype=st.sampled_from([np.float32, np.float64]), seed=st.integers(0, 2**31))
def test_in_place_is_the_same_slope(shape, holes, dtype, seed):
    """Writing over the DEM (each band of rows keeping copies of the original rows it reads) gives
    the out-of-place slopes bit for bit, no-data holes and edges included."""
    rng = np.random.default_rng(seed)
    dem = rng.normal(0.0, 30.0, shape).cumsum(0).cumsum(1).astype(dtype)
    dem[rng.random(shape) < holes] = np.nan
    dem[0, 0] = 1.0  # not all no data
    want = slope_deg(dem, 20.0, 25.0)
    got = dem.copy()
    assert slope_deg(got, 20.0, 25.0, in_place=True) is got
    np.testing.assert_array_equal(got, want)


def test_in_place_needs_a_writeable_float_grid():
    with pytest.raises(ValueError, match="in_place"):
        slope_deg(np.zeros((3, 3), dtype=np.int16), 1.0, 1.0, in_place=True)
