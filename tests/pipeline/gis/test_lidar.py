"""LiDAR clouds sampled from known surfaces, written as PLY/PCD/XYZ -> elevation and slope vs closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.gis.grid import Grid
from pipeline.gis.lidar import LidarError, _fill_gaps, lidar_surface, read_point_cloud

o3d = pytest.importorskip("open3d")

GRID = Grid.from_bounds((1000.0, 2000.0, 1080.0, 2060.0), 2.0, "EPSG:32734")  # 30 x 40 cells


def sample(f, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = GRID.bounds
    x = rng.uniform(xmin, xmax, n)
    y = rng.uniform(ymin, ymax, n)
    return np.c_[x, y, f(x, y)]


def write(points: np.ndarray, path) -> None:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=path.suffix == ".xyz")


def plane(x, y):
    return 0.3 * (x - 1000) - 0.2 * (y - 2000) + 120.0


PLANE_SLOPE = np.degrees(np.arctan(np.hypot(0.3, 0.2)))


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz"])
def test_plane_from_file(tmp_path, suffix):
    points = sample(plane, 12000)
    path = tmp_path / f"cloud{suffix}"
    write(points, path)
    read = read_point_cloud(path)
    # open3d writes PCD coordinates as float32: ~1e-4 m at these magnitudes.
    np.testing.assert_allclose(read, points, atol=1e-3)
    s = lidar_surface(path, GRID)
    xc, yc = GRID.cell_centres()
    assert (s.count > 0).all()
    np.testing.assert_allclose(s.elevation, plane(xc, yc), atol=2e-3)
    np.testing.assert_allclose(s.slope, PLANE_SLOPE, atol=0.01)


def test_paraboloid():
    """z = r^2 / (2R): gradient r / R. Cell-centre elevation error of the plane fit is about
    (dx^2 + dy^2) / 12 / (2R) ~ 7 mm here; normals average over a cell whose slope is linear across it."""
    big_r = 60.0
    cx, cy = 1040.0, 2030.0

    def f(x, y):
        return ((x - cx) ** 2 + (y - cy) ** 2) / (2 * big_r)

    s = lidar_surface(sample(f, 40000, seed=1), GRID)
    xc, yc = GRID.cell_centres()
    np.testing.assert_allclose(s.elevation, f(xc, yc), atol=0.02)
    want = np.degrees(np.arctan(np.hypot(xc - cx, yc - cy) / big_r))
    np.testing.assert_allclose(s.slope[1:-1, 1:-1], want[1:-1, 1:-1], atol=0.5)


def test_gaps_are_interpolated():
    """An inner hole and a strip along the grid's edge: the harmonic fill reproduces a plane exactly."""
    points = sample(plane, 12000, seed=2)
    u, v = GRID.to_pixel(points[:, 0], points[:, 1])
    hole = (u >= 10) & (u < 16) & (v >= 5) & (v < 9)
    edge = (u >= 20) & (u < 35) & (v >= 27)
    s = lidar_surface(points[~(hole | edge)], GRID)
    assert (s.count[5:9, 10:16] == 0).all() and (s.count[27:, 20:35] == 0).all()
    xc, yc = GRID.cell_centres()
    np.testing.assert_allclose(s.elevation, plane(xc, yc), atol=1e-9)
    np.testing.assert_allclose(s.slope, PLANE_SLOPE, atol=1e-6)


@pytest.mark.parametrize("method", ["mean", "lowest"])
def test_statistics_match_per_cell_brute_force(method):
    rng = np.random.default_rng(3)
    points = sample(lambda x, y: rng.normal(50.0, 2.0, x.shape), 6000, seed=3)
    s = lidar_surface(points, GRID, method=method, percentile=20.0)
    u, v = GRID.to_pixel(points[:, 0], points[:, 1])
    r, c = v.astype(int), u.astype(int)
    for row, col in [(0, 0), (7, 21), (29, 39), (15, 3)]:
        zs = points[(r == row) & (c == col), 2]
        want = zs.mean() if method == "mean" else np.percentile(zs, 20.0, method="lower")
        assert s.elevation[row, col] == pytest.approx(want, abs=1e-9)
        assert s.count[row, col] == zs.size


def test_corrupt_ply(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_bytes(b"not a ply\x00\x01")
    with pytest.raises(LidarError, match="bad.ply"):
        read_point_cloud(path)


def test_empty_pcd(tmp_path):
    path = tmp_path / "empty.pcd"
    path.write_text("")
    with pytest.raises(LidarError, match="empty.pcd.*no points"):
        read_point_cloud(path)


def test_garbled_xyz_lines(tmp_path):
    path = tmp_path / "cloud.xyz"
    path.write_text("1 2 3\nhello world\n4 5 6\n")
    with pytest.raises(LidarError, match=r"cloud.xyz: 1 of 3 lines"):
        read_point_cloud(path)


def test_missing_and_unsupported(tmp_path):
    with pytest.raises(LidarError, match="nothere.ply.*not found"):
        read_point_cloud(tmp_path / "nothere.ply")
    with pytest.raises(LidarError, match="cloud.e57.*unsupported"):
        read_point_cloud(tmp_path / "cloud.e57")


def test_cloud_off_grid(tmp_path):
    path = tmp_path / "far.ply"
    write(np.array([[0.0, 0.0, 1.0], [1.0, 1.0, 2.0], [2.0, 0.5, 3.0]]), path)
    with pytest.raises(LidarError, match="far.ply: none of its 3 points"):
        lidar_surface(path, GRID)


def test_bad_arguments():
    points = sample(plane, 100)
    with pytest.raises(LidarError, match="method"):
        lidar_surface(points, GRID, method="median")
    with pytest.raises(LidarError, match=r"\(N, 3\)"):
        lidar_surface(points[:, :2], GRID)
    with pytest.raises(LidarError, match="percentile"):
        lidar_surface(points, GRID, method="lowest", percentile=101)
    with pytest.raises(LidarError, match="normal_radius"):
        lidar_surface(points, GRID, normal_radius=0.0)
    with pytest.raises(LidarError, match="max_nn"):
        lidar_surface(points, GRID, max_nn=2)


@settings(max_examples=40, deadline=None)
@given(
    shape=st.tuples(st.integers(2, 15), st.integers(2, 15)),
    seed=st.integers(0, 2**32 - 1),
    density=st.floats(0.05, 0.95),
)
def test_fill_gaps_reproduces_planes(shape, seed, density):
    """Any gap pattern that leaves the four grid corners known: the fill is the plane itself."""
    rng = np.random.default_rng(seed)
    known = rng.random(shape) < density
    known[[0, 0, -1, -1], [0, -1, 0, -1]] = True
    r, c = np.indices(shape)
    values = 0.37 * c - 1.3 * r + 4.0
    np.testing.assert_allclose(_fill_gaps(np.where(known, values, np.nan), known), values, atol=1e-9)


def test_points_far_off_the_grid_do_not_matter():
    """Only neighbours within the normal radius count, so a cloud three times the grid's size gives
    the same surface as the part of it within two radii of the grid."""
    rng = np.random.default_rng(5)
    xmin, ymin, xmax, ymax = GRID.bounds
    x = rng.uniform(xmin - 80, xmax + 80, 40000)
    y = rng.uniform(ymin - 60, ymax + 60, 40000)
    points = np.c_[x, y, np.sin(x / 9.0) * 3 + 0.1 * y]
    margin = 2 * 1.5 * GRID.dx
    close = (x > xmin - margin) & (x < xmax + margin) & (y > ymin - margin) & (y < ymax + margin)
    big, small = lidar_surface(points, GRID), lidar_surface(points[close], GRID)
    np.testing.assert_allclose(big.elevation, small.elevation, rtol=1e-12)
    np.testing.assert_allclose(big.slope, small.slope, rtol=1e-12)
    np.testing.assert_array_equal(big.count, small.count)
