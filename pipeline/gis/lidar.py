"""LiDAR point clouds (PLY, PCD, XYZ) -> ground elevation and slope grids, usable instead of a DEM.

Points are (x, y, z) in metres in the grid's CRS (point-cloud files carry no CRS; reproject before).
Per cell, the elevation is taken at the cell centre from the points falling in the cell:

- ``"plane"`` (default): the mean point of the cell moved to the cell centre along the plane of the
  cell's mean normal, ``z = mean_z - (nx (xc - mean_x) + ny (yc - mean_y)) / nz``; exact for planar
  ground, second-order accurate on curved ground, works with a single point, and unbiased by where in
  the cell the points lie (a plain mean is not: on a 20 % slope, points clustered in one half of a
  20 m cell shift the mean by a metre).
- ``"mean"``: mean z.
- ``"lowest"``: the ``percentile``-th lowest z (default 10), a simple ground filter for vegetated clouds.

Slope comes from open3d's normals (local PCA over neighbours within ``normal_radius``), oriented
upward; per cell the unit normals are averaged and the slope is the angle of the mean normal from
vertical, in degrees. Averaging normals rather than angles keeps noise on flat ground from
reading as slope (angles are >= 0, so their mean is biased upward).

Cells without points are filled by harmonic interpolation (the discrete Laplace equation with the
cells that have points as boundary values): smooth, exact for planes unless a grid corner is
empty, one sparse solve for all gaps; ``count`` tells which cells had data.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from pipeline.gis.grid import Grid

SUFFIXES = (".ply", ".pcd", ".xyz")


class LidarError(ValueError):
    """A point cloud that cannot be read or does not cover the grid."""


@dataclass(frozen=True)
class LidarSurface:
    """Gridded ground from a point cloud: ``elevation`` (m), ``slope`` (degrees), ``count`` (points per cell)."""

    grid: Grid
    elevation: np.ndarray
    slope: np.ndarray
    count: np.ndarray


def _o3d():
    try:
        import open3d
    except ImportError as exc:  # the optional "lidar" extra
        raise LidarError("LiDAR input needs open3d: pip install 'terrain-prior-tracker[lidar]'") from exc
    return open3d


def read_point_cloud(path: str | Path) -> np.ndarray:
    """(N, 3) float64 x, y, z (metres) from a PLY, PCD or XYZ file; LidarError naming the file on failure."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise LidarError(f"{path}: unsupported point-cloud format {path.suffix!r}; use one of {SUFFIXES}")
    if not path.is_file():
        raise LidarError(f"{path}: point-cloud file not found")
    o3d = _o3d()
    # open3d reports unreadable files only as a printed warning and an empty cloud.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    points = np.asarray(cloud.points, dtype=np.float64)
    if points.shape[0] == 0:
        raise LidarError(f"{path}: no points read (the file is empty, corrupt, or not a {path.suffix} point cloud)")
    if path.suffix.lower() == ".xyz":
        # open3d skips XYZ lines it cannot parse; a partly garbled file must not pass silently.
        with path.open("rb") as f:
            lines = sum(1 for line in f if line.strip() and not line.lstrip().startswith(b"#"))
        if lines != points.shape[0]:
            raise LidarError(f"{path}: {lines - points.shape[0]} of {lines} lines are not 'x y z' numbers")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise LidarError(f"{path}: {bad.sum()} points have NaN or infinite coordinates, first at index {np.argmax(bad)}")
    return points


def _cells(points: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Flat cell index of each point inside the grid, and the mask of those points."""
    r, c, inside = grid.cell_index(points[:, 0], points[:, 1])
    return r[inside] * grid.width + c[inside], inside


def _fill_gaps(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill the cells where ``known`` is False by harmonic interpolation from the known cells.

    Each gap cell equals the mean of its two neighbours along every axis where both exist (the
    discrete Laplace equation; on an edge, along the edge only). A plane satisfies every such
    equation, so planes are reproduced exactly, gaps on edges included. A gap in a grid corner
    has no complete pair and takes the mean of its neighbours, which is not exact for planes.
    One sparse solve for all gaps; every gap touches a known cell, so the system is non-singular.
    """
    if known.all():
        return values
    h, w = values.shape
    gr, gc = np.nonzero(~known)
    n = gr.size
    index = np.full((h, w), -1, dtype=np.int64)
    index[gr, gc] = np.arange(n)
    horizontal = (gc > 0) & (gc < w - 1)
    vertical = (gr > 0) & (gr < h - 1)
    corner = ~horizontal & ~vertical
    diag = np.zeros(n)
    rhs = np.zeros(n)
    rows, cols = [], []
    for dr, dc, axis_ok in ((0, -1, horizontal), (0, 1, horizontal), (-1, 0, vertical), (1, 0, vertical)):
        nr, nc = gr + dr, gc + dc
        use = (axis_ok | corner) & (nr >= 0) & (nr < h) & (nc >= 0) & (nc < w)
        eq = np.nonzero(use)[0]
        nr, nc = nr[use], nc[use]
        diag[eq] += 1.0
        unknown = index[nr, nc]
        is_unknown = unknown >= 0
        rows.append(eq[is_unknown])
        cols.append(unknown[is_unknown])
        np.add.at(rhs, eq[~is_unknown], values[nr[~is_unknown], nc[~is_unknown]])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    a = sparse.csr_matrix((-np.ones(rows.size), (rows, cols)), shape=(n, n)) + sparse.diags(diag)
    out = values.copy()
    out[gr, gc] = spsolve(a.tocsc(), rhs)
    return out


def _upward_normals(points: np.ndarray, radius: float, max_nn: int) -> np.ndarray:
    """Unit normals (N, 3) from open3d's local PCA, flipped to point up (+z)."""
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    cloud.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    return np.asarray(cloud.normals)


def _lowest(z: np.ndarray, cell: np.ndarray, count: np.ndarray, percentile: float) -> np.ndarray:
    """Per cell, the ``percentile``-th lowest z (numpy's "lower" percentile); NaN for empty cells."""
    order = np.lexsort((z, cell))
    start = np.concatenate(([0], np.cumsum(count)[:-1]))
    pick = start + np.floor(percentile / 100.0 * np.maximum(count - 1, 0)).astype(np.intp)
    out = np.full(count.shape, np.nan)
    has = count > 0
    out[has] = z[order[pick[has]]]
    return out


def lidar_surface(
    source: str | Path | np.ndarray,
    grid: Grid,
    method: str = "plane",
    percentile: float = 10.0,
    normal_radius: float | None = None,
    max_nn: int = 30,
) -> LidarSurface:
    """Ground elevation (m) and slope (degrees) on ``grid`` from a point-cloud file or an (N, 3) array.

    ``method``: "plane", "mean" or "lowest" (see the module docstring). ``normal_radius`` (metres) is the
    neighbourhood for open3d's normals, default 1.5 cell sizes; ``max_nn`` caps the neighbours used.
    """
    name = str(source) if not isinstance(source, np.ndarray) else "point array"
    points = read_point_cloud(source) if not isinstance(source, np.ndarray) else np.asarray(source, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise LidarError(f"{name}: points must be an (N, 3) array of x, y, z, got shape {points.shape}")
    if method not in ("plane", "mean", "lowest"):
        raise LidarError(f"method must be 'plane', 'mean' or 'lowest', got {method!r}")
    if not 0 <= percentile <= 100:
        raise LidarError(f"percentile must be in [0, 100], got {percentile}")
    if normal_radius is not None and not normal_radius > 0:
        raise LidarError(f"normal_radius must be a positive distance in metres, got {normal_radius}")
    if not max_nn >= 3:
        raise LidarError(f"max_nn must be at least 3 neighbours to fit a plane, got {max_nn}")
    radius = 1.5 * max(grid.dx, grid.dy) if normal_radius is None else float(normal_radius)
    # Normals from the points on the grid and within one radius of it: edge cells get full
    # neighbourhoods, and a cloud much larger than the grid costs only what the grid needs.
    xmin, ymin, xmax, ymax = grid.bounds
    x, y = points[:, 0], points[:, 1]
    near = points[(x >= xmin - radius) & (x <= xmax + radius) & (y >= ymin - radius) & (y <= ymax + radius)]
    cell, inside = _cells(near, grid)
    if cell.size == 0:
        raise LidarError(f"{name}: none of its {points.shape[0]} points falls on the grid {grid.bounds}")
    n_cells = grid.height * grid.width
    count = np.bincount(cell, minlength=n_cells)
    normals = _upward_normals(near, radius, max_nn)[inside]
    pts = near[inside]
    z_ref = float(pts[:, 2].mean())  # keeps per-cell sums precise at any altitude
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.stack(
            [np.bincount(cell, w, minlength=n_cells) for w in (pts[:, 0], pts[:, 1], pts[:, 2] - z_ref)], -1
        ) / count[:, None]
        normal = np.stack([np.bincount(cell, normals[:, k], minlength=n_cells) for k in range(3)], -1)
        slope = np.degrees(np.arctan2(np.hypot(normal[:, 0], normal[:, 1]), normal[:, 2]))
        if method == "plane":
            # Move the cells' mean point to the centre along the plane of the mean normal.
            xc, yc = (a.ravel() for a in grid.cell_centres())
            nz = np.maximum(normal[:, 2], 1e-9 * np.linalg.norm(normal, axis=1))
            elevation = mean[:, 2] - (normal[:, 0] * (xc - mean[:, 0]) + normal[:, 1] * (yc - mean[:, 1])) / nz + z_ref
        elif method == "mean":
            elevation = mean[:, 2] + z_ref
        else:
            elevation = _lowest(pts[:, 2], cell, count, percentile)
    known = (count > 0).reshape(grid.shape)
    return LidarSurface(
        grid,
        _fill_gaps(elevation.reshape(grid.shape), known),
        _fill_gaps(slope.reshape(grid.shape), known),
        count.reshape(grid.shape),
    )
