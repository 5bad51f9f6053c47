"""LiDAR point clouds (LAS, LAZ, PLY, PCD, XYZ) -> ground elevation and slope grids, usable instead of a DEM.

Reading (:func:`read_point_cloud`, one reader per format):

- LAS/LAZ (laspy, lazrs for LAZ): points are kept by :class:`PointFilter`, by default the ground
  (ASPRS class 2) of every return. The CRS comes from the file's WKT VLR, else its GeoTIFF keys; a
  ``crs`` given by the caller (the layer's config) overrides it, and a file without one needs it.
  z is converted to metres by the vertical unit: the vertical part of a compound CRS, else the
  GeoTIFF ``VerticalUnitsGeoKey``, else the horizontal unit (international or US survey feet alike).
- PLY/PCD/XYZ (open3d) carry no CRS: x, y, z are in ``crs`` when given, else in the grid's CRS.

x, y are reprojected to the grid's CRS through :func:`pipeline.gis.crs.transformer`. Per cell, the elevation is taken at the cell centre from the points falling in the cell:

- ``"plane"`` (default): the mean point of the cell moved to the cell centre along the plane of the
  cell's mean normal, ``z = mean_z - (nx (xc - mean_x) + ny (yc - mean_y)) / nz``; exact for planar
  ground, second-order accurate on curved ground, works with a single point, and unbiased by where in
  the cell the points lie (a plain mean is not: on a 20 % slope, points clustered in one half of a
  20 m cell shift the mean by a metre).
- ``"mean"``: mean z.
- ``"lowest"``: the ``percentile``-th lowest z (default 10), a simple ground filter for vegetated clouds.

Slope comes from normals by local PCA of open3d's neighbourhood covariances (neighbours within
``normal_radius``), oriented upward, ignoring points whose neighbours do not span a plane (see
:data:`PLANAR`); per cell the unit normals are averaged and the slope is the angle of the mean normal from
vertical, in degrees. Averaging normals rather than angles keeps noise on flat ground from
reading as slope (angles are >= 0, so their mean is biased upward).

Cells without points are filled by harmonic interpolation (the discrete Laplace equation with the
cells that have points as boundary values): smooth, exact for planes unless a grid corner is
empty, one sparse solve for all gaps; ``count`` tells which cells had data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS as ProjCRS
from scipy import sparse
from scipy.sparse.linalg import spsolve

from pipeline.gis.crs import to_pyproj, transformer
from pipeline.gis.grid import Grid

LAS_SUFFIXES = (".las", ".laz")
SUFFIXES = (*LAS_SUFFIXES, ".ply", ".pcd", ".xyz")
RETURNS = ("all", "first", "last", "single")
GROUND = 2
PLANAR = 0.05
"""A point's normal counts when its neighbours' middle covariance eigenvalue is at least this times the
largest (a disc of points gives 1, a line 0); sparse LiDAR ground has many single-scan-line neighbourhoods."""
"""ASPRS LAS classification code of ground points."""
VERTICAL_UNITS = {9001: 1.0, 9002: 0.3048, 9003: 1200.0 / 3937.0}
"""GeoTIFF VerticalUnitsGeoKey (EPSG unit code) -> metres: metre, international foot, US survey foot."""
_VERTICAL_UNITS_GEOKEY = 4099


class LidarError(ValueError):
    """A point cloud that cannot be read or does not cover the grid."""


@dataclass(frozen=True)
class PointFilter:
    """Which LAS/LAZ points to keep: ASPRS ``classes`` (``None``: all) and ``returns``, one of
    "all", "first" (return 1), "last" (return = number of returns), "single" (the only return),
    or a tuple of return numbers (1-based). Validated on construction (LidarError)."""

    classes: tuple[int, ...] | None = (GROUND,)
    returns: str | tuple[int, ...] = "all"

    def __post_init__(self) -> None:
        if self.classes is not None and not (
            self.classes and all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255 for c in self.classes)
        ):
            raise LidarError(f"classes must be a non-empty list of LAS class codes 0-255 (2 = ground), got {self.classes!r}")
        if isinstance(self.returns, str):
            if self.returns not in RETURNS:
                raise LidarError(f"returns must be one of {RETURNS} or a list of return numbers, got {self.returns!r}")
        elif not (self.returns and all(isinstance(r, int) and not isinstance(r, bool) and 1 <= r <= 15 for r in self.returns)):
            raise LidarError(f"returns must be one of {RETURNS} or a non-empty list of return numbers 1-15, got {self.returns!r}")

    def mask(self, classification: np.ndarray, return_number: np.ndarray, number_of_returns: np.ndarray) -> np.ndarray:
        """Boolean mask of the points kept."""
        keep = np.ones(classification.shape, dtype=bool) if self.classes is None else np.isin(classification, self.classes)
        if self.returns == "first":
            keep &= return_number == 1
        elif self.returns == "last":
            keep &= return_number == number_of_returns
        elif self.returns == "single":
            keep &= number_of_returns == 1
        elif not isinstance(self.returns, str):
            keep &= np.isin(return_number, self.returns)
        return keep

    def describe(self) -> str:
        """E.g. "classes [2], all returns", for messages."""
        classes = "all classes" if self.classes is None else f"classes {list(self.classes)}"
        returns = f"{self.returns} returns" if isinstance(self.returns, str) else f"return numbers {list(self.returns)}"
        return f"{classes}, {returns}"


@dataclass(frozen=True)
class _Stored:
    """A cloud as a reader found it: x, y, z in the file's units, its CRS, and its vertical unit in
    metres when the file states one apart from the CRS (GeoTIFF keys)."""

    points: np.ndarray
    crs: ProjCRS | None
    z_to_m: float | None = None


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


def _read_open3d(path: Path, keep: PointFilter | None) -> _Stored:
    """PLY, PCD or XYZ through open3d: no CRS, no classes."""
    if keep is not None:
        raise LidarError(f"{path}: {path.suffix} point clouds have no classes or returns to filter by; only LAS/LAZ do")
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
    return _Stored(points, None)


def _read_las(path: Path, keep: PointFilter | None) -> _Stored:
    """LAS or LAZ through laspy, read in chunks so only the kept points are held."""
    try:
        import laspy
    except ImportError as exc:  # the optional "lidar" extra
        raise LidarError("LAS/LAZ input needs laspy and lazrs: pip install 'terrain-prior-tracker[lidar]'") from exc
    keep = PointFilter() if keep is None else keep
    parts, seen = [], np.zeros(256, dtype=np.int64)
    try:
        with laspy.open(path) as f:
            header = f.header
            for chunk in f.chunk_iterator(1_000_000):
                cls = np.asarray(chunk.classification, dtype=np.uint8)
                seen += np.bincount(cls, minlength=256)
                m = keep.mask(cls, np.asarray(chunk.return_number), np.asarray(chunk.number_of_returns))
                parts.append(np.c_[np.asarray(chunk.x)[m], np.asarray(chunk.y)[m], np.asarray(chunk.z)[m]])
            crs = header.parse_crs()
    except Exception as exc:  # laspy raises LaspyException, OSError, ValueError... for unreadable files
        raise LidarError(f"{path}: not a readable LAS/LAZ file ({type(exc).__name__}: {exc})") from None
    total = int(seen.sum())
    if total == 0:
        raise LidarError(f"{path}: the file holds no points")
    points = np.concatenate(parts) if parts else np.empty((0, 3))
    if points.shape[0] == 0:
        present = {int(c): int(n) for c, n in enumerate(seen) if n}
        raise LidarError(f"{path}: none of its {total} points is of {keep.describe()} (points per class: {present})")
    z_unit = None
    for vlr in header.vlrs:
        for key in getattr(vlr, "geo_keys", ()):
            if key.id == _VERTICAL_UNITS_GEOKEY:
                if key.value_offset not in VERTICAL_UNITS:
                    raise LidarError(f"{path}: GeoTIFF VerticalUnitsGeoKey {key.value_offset} is not metre (9001), foot (9002) or US survey foot (9003)")
                z_unit = VERTICAL_UNITS[key.value_offset]
    return _Stored(points, crs, z_unit)


_READERS: dict[str, Callable[[Path, PointFilter | None], _Stored]] = {
    ".las": _read_las,
    ".laz": _read_las,
    ".ply": _read_open3d,
    ".pcd": _read_open3d,
    ".xyz": _read_open3d,
}


def _parts(crs: ProjCRS) -> tuple[ProjCRS, float]:
    """The horizontal CRS of ``crs`` and its vertical unit in metres: the vertical part of a compound
    CRS, else a third axis (ellipsoidal height), else the horizontal unit (metres for degrees)."""
    if crs.is_compound:
        vertical = next((c for c in crs.sub_crs_list[1:] if c.is_vertical), None)
        crs = crs.sub_crs_list[0]
        if vertical is not None:
            return crs, float(vertical.axis_info[0].unit_conversion_factor)
    axes = crs.axis_info
    if len(axes) >= 3:
        return crs, float(axes[2].unit_conversion_factor)
    return crs, 1.0 if crs.is_geographic else float(axes[0].unit_conversion_factor)


def read_point_cloud(
    path: str | Path, to_crs: Any = None, crs: Any = None, keep: PointFilter | None = None
) -> np.ndarray:
    """(N, 3) float64 x, y, z of a LAS, LAZ, PLY, PCD or XYZ file, z in metres; LidarError naming the file.

    ``keep`` filters LAS/LAZ points (default :class:`PointFilter`: ground, all returns). ``crs``
    (anything pyproj reads) overrides the file's CRS; with ``to_crs`` x, y are reprojected into it
    (a PLY/PCD/XYZ without ``crs`` is taken to be in ``to_crs`` already), else they stay in the
    file's CRS units.
    """
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise LidarError(f"{path}: unsupported point-cloud format {path.suffix!r}; use one of {SUFFIXES}")
    if not path.is_file():
        raise LidarError(f"{path}: point-cloud file not found")
    stored = reader(path, keep)
    points = stored.points
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise LidarError(f"{path}: {bad.sum()} points have NaN or infinite coordinates, first at index {np.argmax(bad)}")
    source = to_pyproj(crs) if crs is not None else stored.crs
    if source is None:
        if path.suffix.lower() in LAS_SUFFIXES and to_crs is not None:
            raise LidarError(
                f"{path}: the file has no CRS (no WKT or GeoTIFF-keys VLR); give its layer one, e.g. crs = \"EPSG:2992\""
            )
        return points
    horizontal, z_to_m = _parts(source)
    if stored.z_to_m is not None and crs is None:
        z_to_m = stored.z_to_m
    out = points.copy()
    out[:, 2] *= z_to_m
    if to_crs is not None and horizontal != to_pyproj(to_crs):
        out[:, 0], out[:, 1] = transformer(horizontal, to_crs).transform(points[:, 0], points[:, 1])
    return out


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
    """Unit normals (N, 3) from the local PCA of open3d's neighbourhood covariances, pointing up (+z);
    zero where the neighbourhood does not fix a plane, whose normal would be arbitrary: points along
    one scan line (middle eigenvalue below PLANAR times the largest), or no flat direction (smallest
    eigenvalue over half the middle one; open3d gives under 3 neighbours an identity covariance)."""
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - points.mean(axis=0)))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    eigenvalues, eigenvectors = np.linalg.eigh(np.asarray(cloud.covariances))  # ascending eigenvalues
    normals = eigenvectors[:, :, 0] * np.where(eigenvectors[:, 2:3, 0] < 0, -1.0, 1.0)
    lam0, lam1, lam2 = eigenvalues.T
    normals[~((lam1 > PLANAR * lam2) & (lam0 < 0.5 * lam1))] = 0.0
    return normals


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
    crs: Any = None,
    keep: PointFilter | None = None,
) -> LidarSurface:
    """Ground elevation (m) and slope (degrees) on ``grid`` from a point-cloud file or an (N, 3) array.

    ``method``: "plane", "mean" or "lowest" (see the module docstring). ``normal_radius`` (metres) is the
    neighbourhood for open3d's normals, default 1.5 cell sizes; ``max_nn`` caps the neighbours used.
    A file is read with :func:`read_point_cloud` (``crs``, ``keep``) into the grid's CRS; an array
    is taken to be in the grid's CRS, in metres.
    """
    name = str(source) if not isinstance(source, np.ndarray) else "point array"
    if isinstance(source, np.ndarray):
        points = np.asarray(source, dtype=np.float64)
    else:
        points = read_point_cloud(source, grid.crs, crs, keep)
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
        has_normal = np.linalg.norm(normal, axis=1) > 0
        if method == "plane":
            # Move the cells' mean point to the centre along the plane of the mean normal (none: the mean).
            xc, yc = (a.ravel() for a in grid.cell_centres())
            nz = np.maximum(normal[:, 2], 1e-9 * np.linalg.norm(normal, axis=1))
            shift = (normal[:, 0] * (xc - mean[:, 0]) + normal[:, 1] * (yc - mean[:, 1])) / nz
            elevation = mean[:, 2] - np.where(has_normal, shift, 0.0) + z_ref
        elif method == "mean":
            elevation = mean[:, 2] + z_ref
        else:
            elevation = _lowest(pts[:, 2], cell, count, percentile)
    known = (count > 0).reshape(grid.shape)
    if not has_normal.any():
        raise LidarError(f"{name}: no point on the grid has neighbours spanning a plane within {radius} m; raise normal_radius")
    return LidarSurface(
        grid,
        _fill_gaps(elevation.reshape(grid.shape), known),
        _fill_gaps(slope.reshape(grid.shape), has_normal.reshape(grid.shape)),
        count.reshape(grid.shape),
    )
