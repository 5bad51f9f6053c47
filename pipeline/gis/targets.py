"""Past target locations as (N, 2) map coordinates in metres on a grid's CRS.

Vector files (GeoPackage, Shapefile, GeoJSON) go through :func:`pipeline.gis.layers.read_vector`
(reprojected to the grid CRS); polygons and lines become their centroids *after* reprojection, so
centroids are taken in metres. CSV files need ``x`` and ``y`` columns (names configurable), in the
grid's CRS unless ``crs`` says otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyogrio
import shapely

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
        return _read_csv(path, grid, x, y, crs)
    _check_layer(path, layer)
    geoms = read_vector(LayerSpec("targets", path, "vector", layer=layer), grid).geometries
    if geoms.size == 0:
        raise ValueError(f"{path}" + (f", layer {layer!r}" if layer else "") + ": no target geometries")
    pts = shapely.get_coordinates(shapely.centroid(geoms))
    if len(pts) != len(geoms):
        raise ValueError(f"{path}: some target geometries have no centroid")
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
    try:
        table = np.genfromtxt(path, delimiter=",", names=True, dtype=np.float64, encoding="utf-8")
    except ValueError as exc:
        raise ValueError(f"{path}: not a readable CSV: {exc}") from None
    names = table.dtype.names or ()
    missing = [c for c in (x, y) if c not in names]
    if missing:
        raise ValueError(f"{path}: no column {missing[0]!r}; the CSV has {list(names)}")
    pts = np.column_stack([np.atleast_1d(table[x]), np.atleast_1d(table[y])])
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: non-numeric or missing {x}/{y} on data rows {(bad + 1)[:10].tolist()}")
    if crs is not None:
        tr = transformer(crs, grid.crs)
        pts = np.column_stack(tr.transform(pts[:, 0], pts[:, 1]))
    return pts
