"""The real Autzen LAZ (feet, Lambert conformal conic) -> ground elevation and slope at 1 m and 2 m cells
in UTM 10N through ``terrain-prior features``, against scipy's linear interpolation of the ground points
and PDAL's writers.gdal when a ``pdal`` command exists. docs/pipeline.md states the differences."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
import rasterio
from matplotlib.path import Path as Polygon
from scipy.interpolate import griddata
from scipy.spatial import ConvexHull
from threadpoolctl import threadpool_limits

from pipeline import cli
from pipeline.gis.grid import Grid
from pipeline.gis.lidar import PointFilter, read_point_cloud

pytestmark = pytest.mark.realdata
pytest.importorskip("laspy")
pytest.importorskip("open3d")

UTM = "EPSG:32610"
BOUNDS = (494120.0, 4877430.0, 494470.0, 4877590.0)


@pytest.fixture(scope="module")
def laz(real_data):
    path = real_data / "autzen" / "autzen_trim.laz"
    if not path.is_file():
        pytest.skip(f"{path} missing")
    return path


def features(laz, tmp_path, cell: float) -> tuple[Grid, np.ndarray, np.ndarray]:
    cfg = tmp_path / "autzen.toml"
    cfg.write_text(
        f'[region]\nname = "autzen"\ncrs = "{UTM}"\nbounds = {list(BOUNDS)}\ncell_size = {cell}\n\n'
        f"[layers.lidar]\npath = {json.dumps(str(laz))}\n\n"
        '[features.elevation]\ntype = "elevation"\nlayer = "lidar"\n\n'
        '[features.slope]\ntype = "slope"\nlayer = "lidar"\n'
    )
    assert cli.main(["-q", "features", str(cfg), "--out", str(tmp_path)]) == 0
    with rasterio.open(tmp_path / "elevation.tif") as e, rasterio.open(tmp_path / "slope.tif") as s:
        grid = Grid(e.crs, e.transform, e.height, e.width)
        return grid, e.read(1).astype(np.float64), s.read(1).astype(np.float64)


def linear(points: np.ndarray, grid: Grid) -> np.ndarray:
    """scipy's linear interpolation of the points at the cell centres, NaN outside their hull. Cells
    outside are masked first: qhull's point location is slow for points outside the triangulation."""
    xc, yc = grid.cell_centres()
    o = points[:, :2].mean(axis=0)  # conditioning: qhull on coordinates of order 1e6 m
    xy = points[:, :2] - o
    q = np.c_[xc.ravel() - o[0], yc.ravel() - o[1]]
    inside = Polygon(xy[ConvexHull(xy).vertices]).contains_points(q)
    out = np.full(q.shape[0], np.nan)
    # qhull's per-triangle transforms are 52k tiny LAPACK calls: threaded BLAS on a busy machine takes 30 s
    with threadpool_limits(1):
        out[inside] = griddata(xy, points[:, 2], q[inside], method="linear")
    return out.reshape(grid.shape)


def test_point_counts_and_units(laz):
    ground = read_point_cloud(laz, UTM)
    assert ground.shape == (26107, 3)
    assert read_point_cloud(laz, UTM, keep=PointFilter(None)).shape == (110000, 3)
    # z 406-521 ft in the file: metres here
    assert 123.5 < ground[:, 2].min() and ground[:, 2].max() < 159.0


@pytest.mark.parametrize(
    ("cell", "elev_med", "elev_p95", "slope_med", "slope_p95"),
    [(1.0, 0.02, 0.1, 1.0, 8.0), (2.0, 0.02, 0.12, 0.6, 7.0)],
)
def test_against_scipy_linear(laz, tmp_path, cell, elev_med, elev_p95, slope_med, slope_p95):
    grid, elevation, slope = features(laz, tmp_path, cell)
    ground = read_point_cloud(laz, UTM)
    ref = linear(ground, grid)
    gy, gx = np.gradient(ref, grid.dy, grid.dx)
    ref_slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    # compare where the cell has ground points (elsewhere both methods interpolate, differently)
    r, c, inside = grid.cell_index(ground[:, 0], ground[:, 1])
    has = np.zeros(grid.shape, bool)
    has[r[inside], c[inside]] = True
    m = has & np.isfinite(ref_slope)
    de, ds = np.abs(elevation - ref)[m], np.abs(slope - ref_slope)[m]
    assert m.sum() > 0.3 * grid.height * grid.width
    assert np.median(de) < elev_med and np.percentile(de, 95) < elev_p95
    assert np.median(ds) < slope_med and np.percentile(ds, 95) < slope_p95


@pytest.mark.skipif(shutil.which("pdal") is None, reason="pdal (PDAL command line) not installed; not in Debian bookworm")
def test_against_pdal_writers_gdal(laz, tmp_path):
    grid, elevation, _ = features(laz, tmp_path, 2.0)
    out = tmp_path / "pdal.tif"
    pipeline = [
        str(laz),
        {"type": "filters.range", "limits": "Classification[2:2]"},
        {"type": "filters.reprojection", "out_srs": UTM},
        {"type": "writers.gdal", "filename": str(out), "resolution": 2.0, "output_type": "idw",
         "origin_x": BOUNDS[0], "origin_y": BOUNDS[1], "width": grid.width, "height": grid.height},
    ]
    (tmp_path / "p.json").write_text(json.dumps(pipeline))
    subprocess.run(["pdal", "pipeline", str(tmp_path / "p.json")], check=True)
    with rasterio.open(out) as src:
        ref = src.read(1, masked=True).astype(np.float64).filled(np.nan)
    d = np.abs(elevation - ref)[np.isfinite(ref)]
    assert d.size > 0 and np.median(d) < 0.05 and np.percentile(d, 95) < 0.3
