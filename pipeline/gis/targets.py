"""Past target locations as (N, 2) map coordinates in metres on a grid's CRS.

Vector files (GeoPackage, Shapefile, GeoJSON) go through :func:`pipeline.gis.layers.read_vector`
(reprojected to the grid CRS); polygons and lines become their centroids *after* reprojection, so
centroids are taken in metres. CSV files need ``x`` and ``y`` columns (names configurable), in the
grid's CRS unless ``crs`` says otherwise. A file none of whose points lies on the grid is refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyogrio
import shapely

from common.tables import numeric_column, read_csv_table
from pipeline.gis.crs import transformer
from pipeline.gis.grid import Grid
from pipeline.gis.layers import LayerSpec, read_vector


def read_targets(
    path: str | Path, grid: Grid, layer: str | None = None, x: str = "x", y: str = "y", crs: str | None = None
) -> np.ndarray:
    """Target points (N, 2) in metres in ``grid.crs``; ``layer`` picks a layer of a multi-layer file."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: targets file not found")
    if path.suffix.lower() == ".csv":
        if layer is not None:
            raise ValueError(f"{path}: --layer (layer=) picks a layer of a vector file; a CSV has none")
        pts = _read_csv(path, grid, x, y, crs)
        _check_on_grid(path, pts, grid, "" if crs else "; if they are in another CRS, say which with --targets-crs")
        return pts
    _check_layer(path, layer)
    geoms = read_vector(LayerSpec("targets", path, "vector", layer=layer), grid).geometries
    if geoms.size == 0:
        raise ValueError(f"{path}" + (f", layer {layer!r}" if layer else "") + ": no target geometries")
    pts = shapely.get_coordinates(shapely.centroid(geoms))
    if len(pts) != len(geoms):
        raise ValueError(f"{path}: some target geometries have no centroid")
    _check_on_grid(path, pts, grid, " (reprojected from the file's CRS)")
    return pts


def _check_layer(path: Path, layer: str | None) -> None:
    """The layer choice of a targets file, refused with the fix (``layer=``, i.e. ``--layer``): the
    targets file is no config layer, so read_vector's ``[layers.*]`` hint does not apply."""
    try:
        available = [str(n) for n in pyogrio.list_layers(path)[:, 0]]
    except pyogrio.errors.DataSourceError:
        return  # read_vector names the unreadable file
    if layer is None and len(available) > 1:
        raise ValueError(f"{path}: the targets file has several layers {available}; pick one with --layer NAME (layer=)")
    if layer is not None and layer not in available:
        raise ValueError(f"{path}: no layer {layer!r} (--layer); the targets file has {available}")


def _read_csv(path: Path, grid: Grid, x: str, y: str, crs: str | None) -> np.ndarray:
    table = read_csv_table(path, "target points")
    missing = [c for c in (x, y) if c not in table.columns]
    if missing:
        raise ValueError(f"{path}: no column {missing[0]!r}; the CSV has {list(table.columns)}")
    if table.empty:
        raise ValueError(f"{path}: no data rows, only a header; a CSV of target points has one row per point")
    pts = np.column_stack([numeric_column(table, x), numeric_column(table, y)])
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: non-numeric or missing {x}/{y} on data rows {bad[:10].tolist()} (0-based)")
    if crs is not None:
        tr = transformer(crs, grid.crs)
        pts = np.column_stack(tr.transform(pts[:, 0], pts[:, 1]))
    return pts


def _check_on_grid(path: Path, pts: np.ndarray, grid: Grid, hint: str) -> None:
    """Refuse targets none of which lies on the grid (the usual cause: coordinates in another CRS)."""
    if grid.contains(pts[:, 0], pts[:, 1]).any():
        return
    x0, y0, x1, y1 = grid.bounds
    raise ValueError(
        f"{path}: none of its {len(pts)} target points lies on the grid: they span x {pts[:, 0].min():.6g} to "
        f"{pts[:, 0].max():.6g}, y {pts[:, 1].min():.6g} to {pts[:, 1].max():.6g}; the grid spans x {x0:.0f} to {x1:.0f}, "
        f"y {y0:.0f} to {y1:.0f} m in {grid.crs}{hint}")
