"""Burn geometries (grid CRS, metres) into Grid arrays: masks and categorical codes.

A cell is inside a polygon when its centre is (rasterio's default rule); ``all_touched`` marks every
cell a geometry touches, which keeps thin lines such as roads connected.
"""

from __future__ import annotations

import numpy as np
import shapely
from rasterio.features import rasterize

from pipeline.gis.grid import NODATA_CODE, Grid


def _buffered(geoms: np.ndarray, buffer_m: float) -> np.ndarray:
    """Lines and points widened by ``buffer_m`` metres on each side; polygons grown by it."""
    if buffer_m <= 0:
        return geoms
    return shapely.buffer(geoms, buffer_m)


def line_ends(geoms: np.ndarray) -> np.ndarray:
    """Both end points of every line (multi-lines: of every part), as shapely Points in the lines' CRS;
    ValueError naming the first geometry that is not a line (points and polygons have no ends)."""
    geoms = np.asarray(geoms, dtype=object)
    if geoms.size == 0:
        return np.empty(0, dtype=object)
    parts = shapely.get_parts(geoms[~shapely.is_empty(geoms)])
    kinds = shapely.get_type_id(parts)
    bad = np.flatnonzero((kinds != shapely.GeometryType.LINESTRING) & (kinds != shapely.GeometryType.LINEARRING))
    if bad.size:
        raise ValueError(f"end points need lines, got {bad.size} other geometries (the first a {parts[bad[0]].geom_type})")
    return np.concatenate([shapely.get_point(parts, 0), shapely.get_point(parts, -1)])


def mask(geoms: np.ndarray, grid: Grid, buffer_m: float = 0.0, all_touched: bool = False, dtype: type = bool) -> np.ndarray:
    """(H, W) mask of the cells covered by ``geoms`` (optionally buffered by ``buffer_m`` metres):
    boolean, or 0/1 in ``dtype`` (e.g. int16 category codes), burned in that type (no copy)."""
    geoms = _buffered(np.asarray(geoms, dtype=object), buffer_m)
    as_bool = np.dtype(dtype) == np.bool_
    if geoms.size == 0:
        return np.zeros(grid.shape, dtype=dtype)
    burned = rasterize(
        ((g, 1) for g in geoms),
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        all_touched=all_touched,
        dtype="uint8" if as_bool else np.dtype(dtype).name,
    )
    return burned.view(bool) if as_bool else burned  # 0/1 bytes are valid booleans


def categories(geoms: np.ndarray, codes: np.ndarray, grid: Grid, fill: int = NODATA_CODE) -> np.ndarray:
    """int32 (H, W) category codes burned from polygons (later polygons win where they overlap)."""
    geoms = np.asarray(geoms, dtype=object)
    codes = np.asarray(codes)
    if geoms.shape != codes.shape:
        raise ValueError(f"categories: {geoms.shape[0]} geometries but {codes.shape[0]} codes")
    if geoms.size == 0:
        return np.full(grid.shape, fill, dtype=np.int32)
    return rasterize(
        zip(geoms, codes.astype(np.int32).tolist(), strict=True),
        out_shape=grid.shape,
        transform=grid.transform,
        fill=fill,
        dtype="int32",
    )
