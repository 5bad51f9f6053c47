"""Read input layers onto a Grid: vector layers (pyogrio -> shapely 2, reprojected) and rasters (rasterio reproject).

Every failure names the file and layer. Input files are never modified: a shapefile with a stale
index is restored on a temporary copy only when its config asks for it (``restore_index = true``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pyogrio
import pyogrio.errors
import pyogrio.raw
import rasterio
import rasterio.errors
import shapely
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.warp import reproject, transform_bounds
from rasterio.windows import Window

from pipeline.gis.crs import to_pyproj, transformer
from pipeline.gis.grid import NODATA_CODE, Grid
from pipeline.gis.lidar import PointFilter

log = logging.getLogger(__name__)


class LayerError(ValueError):
    """An input layer that cannot be read; the message names the file and layer."""


class LayerWarning(UserWarning):
    """An input layer that is empty or does not touch the grid."""


@dataclass(frozen=True)
class LayerSpec:
    """How to read one input layer: a vector layer (``layer`` of a multi-layer file, optional OGR SQL
    ``where``), a raster ``band``, or a LiDAR point cloud (its ``crs`` when the file has none or a wrong
    one, and for LAS/LAZ which ``points`` to keep); ``path`` absolute or relative to the working folder."""

    name: str
    path: Path
    kind: Literal["vector", "raster", "pointcloud"]
    layer: str | None = None
    where: str | None = None
    restore_index: bool = False
    band: int = 1
    crs: CRS | None = None
    points: PointFilter | None = None
    allow_empty_geometries: bool = False

    def __post_init__(self) -> None:
        if self.where is not None:
            problem = _where_problem(self.where)
            if problem:
                raise LayerError(f"{_where(self)}: where = {self.where!r}: {problem}; give one SQL expression")


def _where_problem(where: str) -> str | None:
    """Why ``where`` is not a single SQL expression (a ``;`` statement separator, a comment, an unclosed
    quote or an empty filter), or None. OGR keeps only the text before a ``;`` and a comment hides the
    rest, so either would silently change the filter."""
    if not where.strip():
        return "empty filter"
    quote = None
    for i, ch in enumerate(where):
        if quote:
            if ch == quote:
                quote = None  # a doubled quote ('') closes and reopens: same result
        elif ch in "'\"":
            quote = ch
        elif ch == ";":
            return f"';' at character {i + 1} ends the expression (the rest would be dropped)"
        elif where.startswith(("--", "/*"), i):
            return f"SQL comment {where[i:i + 2]!r} at character {i + 1}"
    return f"unclosed {quote} quote" if quote else None


@dataclass(frozen=True)
class VectorLayer:
    """Geometries of one vector layer in the grid CRS (metres), with the requested attributes."""

    name: str
    geometries: np.ndarray  # shapely geometries, object array
    attributes: dict[str, np.ndarray]
    n_repaired: int = 0


def _where(spec: LayerSpec) -> str:
    """How to name a layer in messages: file, layer inside it, config key."""
    inner = f", layer {spec.layer!r}" if spec.layer else ""
    return f"{spec.path}{inner} ([layers.{spec.name}])"


@contextlib.contextmanager
def _restored_copy(path: Path) -> Iterator[Path]:
    """A temporary copy of a shapefile's parts whose .shx GDAL rebuilds; the original stays untouched."""
    with tempfile.TemporaryDirectory(prefix="shx-restore-") as tmp:
        for part in path.parent.glob(path.stem + ".*"):
            if part.suffix.lower() != ".shx":  # a missing .shx is rebuilt from the .shp
                shutil.copyfile(part, Path(tmp) / part.name)
        pyogrio.set_gdal_config_options({"SHAPE_RESTORE_SHX": True})
        try:
            yield Path(tmp) / path.name
        finally:
            pyogrio.set_gdal_config_options({"SHAPE_RESTORE_SHX": None})


def open_source(spec: LayerSpec) -> contextlib.AbstractContextManager[Path]:
    """The path to read ``spec`` from: the file itself, or with ``restore_index`` a shapefile's temporary
    copy with its .shx rebuilt; a missing file is a :class:`LayerError` naming the layer."""
    if not spec.path.exists():
        raise LayerError(f"{_where(spec)}: file not found")
    if spec.restore_index and spec.path.suffix.lower() == ".shp":
        return _restored_copy(spec.path)
    return contextlib.nullcontext(spec.path)


def _stale_index_hint(spec: LayerSpec, exc: Exception) -> str:
    msg = str(exc)
    if spec.path.suffix.lower() == ".shp" and ("shx" in msg.lower() or "corrupt" in msg.lower()):
        return (
            f"{_where(spec)}: unreadable shapefile, its .shx index looks stale or broken ({msg}). "
            f"GDAL can rebuild it (config option SHAPE_RESTORE_SHX=YES); set restore_index = true "
            f"in [layers.{spec.name}] to restore it on a temporary copy (the input is not modified)"
        )
    return f"{_where(spec)}: cannot read: {msg}"


def _fid_list(fids: np.ndarray, most: int = 10) -> str:
    shown = ", ".join(str(int(f)) for f in fids[:most])
    return shown + (f", ... ({fids.size} in all)" if fids.size > most else "")


def _check_finite(spec: LayerSpec, geoms: np.ndarray, fids: np.ndarray, where: str) -> None:
    """Refuse geometries with NaN or infinite vertices (GEOS cannot repair or buffer them)."""
    coords, index = shapely.get_coordinates(geoms, return_index=True)
    bad = np.unique(index[~np.isfinite(coords).all(axis=1)])
    if bad.size:
        raise LayerError(f"{_where(spec)}: {bad.size} features have NaN or infinite coordinates{where} "
                         f"(FIDs {_fid_list(fids[bad])}); fix or remove them")


def read_vector(spec: LayerSpec, grid: Grid, columns: list[str] | None = None) -> VectorLayer:
    """Read a vector layer (optionally filtered by ``spec.where``), repair it, and reproject it to ``grid.crs``.

    ``columns``: attributes to keep (none by default). Empty layers and layers that miss the grid warn.
    """
    with open_source(spec) as path:
        try:
            available = [str(n) for n in pyogrio.list_layers(path)[:, 0]]
        except pyogrio.errors.DataSourceError as exc:
            raise LayerError(f"{_where(spec)}: not a readable vector file: {exc}") from None
        if spec.layer is not None and spec.layer not in available:
            raise LayerError(f"{_where(spec)}: no layer {spec.layer!r}; the file has {available}")
        if spec.layer is None and len(available) > 1:
            raise LayerError(f"{_where(spec)}: the file has several layers {available}; set layer = \"...\"")
        layer = spec.layer if spec.layer is not None else available[0]
        try:
            info = pyogrio.read_info(path, layer=layer)
        except pyogrio.errors.DataLayerError as exc:
            raise LayerError(_stale_index_hint(spec, exc)) from None
        fields = [str(f) for f in info["fields"]]
        missing = [c for c in columns or [] if c not in fields]
        if missing:
            raise LayerError(f"{_where(spec)}: no attribute {missing[0]!r}; the layer has {fields}")
        if info["crs"] is None:
            raise LayerError(f"{_where(spec)}: the layer has no CRS (for a shapefile, a .prj is missing); cannot place it on the grid")
        try:
            _, fids, wkb, values = pyogrio.raw.read(
                path, layer=layer, where=spec.where, columns=columns or [], return_fids=True
            )
        except pyogrio.errors.FieldError as exc:
            raise LayerError(f"{_where(spec)}: bad attribute filter where = {spec.where!r}: {exc}") from None
        except pyogrio.errors.DataLayerError as exc:
            if spec.where and "sql" in str(exc).lower():
                raise LayerError(f"{_where(spec)}: bad attribute filter where = {spec.where!r}: {exc}") from None
            raise LayerError(_stale_index_hint(spec, exc)) from None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # NaN coordinates: refused by name just below
        geoms = shapely.from_wkb(wkb) if wkb is not None else np.empty(0, dtype=object)
    fids = np.asarray(fids) if fids is not None else np.arange(geoms.size)
    keep = ~shapely.is_missing(geoms) & ~shapely.is_empty(geoms)
    if not keep.all():
        msg = (f"{_where(spec)}: {int((~keep).sum())} of {keep.size} features have no geometry "
               f"(FIDs {_fid_list(fids[~keep])})")
        if not spec.allow_empty_geometries:
            hint = ""
            if spec.path.suffix.lower() == ".shp" and not spec.restore_index:
                hint = "; a stale .shx index reads as missing shapes: try restore_index = true, or"
            raise LayerError(f"{msg}{hint} set allow_empty_geometries = true in [layers.{spec.name}] to skip them")
        warnings.warn(f"{msg}; skipped (allow_empty_geometries = true)", LayerWarning, stacklevel=2)
    geoms, fids = geoms[keep], fids[keep]
    _check_finite(spec, geoms, fids, "")
    attributes = {c: np.asarray(v)[keep] for c, v in zip(columns or [], values, strict=True)}
    invalid = ~shapely.is_valid(geoms)
    n_repaired = int(invalid.sum())
    if n_repaired:
        geoms[invalid] = shapely.make_valid(geoms[invalid])
        log.warning("%s: repaired %d invalid geometries with make_valid", _where(spec), n_repaired)
    src_crs = to_pyproj(info["crs"])
    if not src_crs.equals(to_pyproj(grid.crs)):
        tr = transformer(src_crs, grid.crs)
        geoms = shapely.transform(geoms, lambda xy: np.column_stack(tr.transform(xy[:, 0], xy[:, 1])))
        _check_finite(spec, geoms, fids, f" once reprojected to {grid.crs.to_string()} (outside its area of use?)")
    if geoms.size == 0:
        warnings.warn(f"{_where(spec)}: layer is empty" + (f" after where = {spec.where!r}" if spec.where else ""),
                      LayerWarning, stacklevel=2)
    elif not shapely.intersects(shapely.box(*grid.bounds), geoms).any():
        warnings.warn(f"{_where(spec)}: no geometry touches the grid {grid.bounds} ({grid.crs.to_string()})",
                      LayerWarning, stacklevel=2)
    return VectorLayer(spec.name, geoms, attributes, n_repaired)


RASTER_MARGIN = 3
"""Source pixels read beyond the grid's footprint on each side when the warp does not downsample
(bilinear resampling reads 2 x 2); :func:`covering_window` widens it where it does."""


def covering_window(src: rasterio.io.DatasetReader, grid: Grid) -> Window | None:
    """The window of ``src`` that covers ``grid`` plus the resampling kernel's reach, clipped to it;
    None off the raster. The reach is RASTER_MARGIN pixels, or more when GDAL downsamples: its bilinear
    kernel then spans one grid cell either side of a cell centre, half a cell past the grid's edge,
    i.e. 0.5 / scale source pixels (:func:`warp_scale`)."""
    bounds = grid.bounds if src.crs == grid.crs else transform_bounds(grid.crs, src.crs, *grid.bounds, densify_pts=21)
    win = src.window(*bounds)
    xscale, yscale = warp_scale(src, grid)
    mx, my = (max(RASTER_MARGIN, math.ceil(0.5 / s) + 2) for s in (xscale, yscale))
    c0 = max(0, math.floor(win.col_off) - mx)
    r0 = max(0, math.floor(win.row_off) - my)
    c1 = min(src.width, math.ceil(win.col_off + win.width) + mx)
    r1 = min(src.height, math.ceil(win.row_off + win.height) + my)
    return None if c1 <= c0 or r1 <= r0 else Window(c0, r0, c1 - c0, r1 - r0)


def warp_scale(src: rasterio.io.DatasetReader, grid: Grid) -> tuple[float, float]:
    """GDAL's XSCALE, YSCALE warp options: grid cells per source pixel along x and y (below one when
    the warp downsamples). Left to itself GDAL computes them per warp chunk from that chunk's source
    extent, so a window of the raster (a tile's, or the part under a grid) would resample with a wider
    or narrower kernel than the whole raster. In the grid's CRS they are the ratio of pixel sizes, the
    same for any window; across CRSs they are measured at the centre of ``src``."""
    t = src.transform
    if src.crs == grid.crs:
        return math.hypot(t.a, t.d) / grid.dx, math.hypot(t.b, t.e) / grid.dy
    cx, cy = t * (src.width / 2, src.height / 2)
    xs, ys = transformer(src.crs, grid.crs).transform(np.array([cx, cx + t.a, cx + t.b]), np.array([cy, cy + t.d, cy + t.e]))
    return math.hypot(xs[1] - xs[0], ys[1] - ys[0]) / grid.dx, math.hypot(xs[2] - xs[0], ys[2] - ys[0]) / grid.dy


def _all_nodata(values: np.ndarray, nodata: float) -> bool:
    """Whether every cell of ``values`` is ``nodata`` (NaN: is NaN), a band of rows at a time: no
    grid-size temporary, and it stops at the first band with data."""
    for r0 in range(0, values.shape[0], 256):
        band = values[r0 : r0 + 256]
        if not (np.isnan(band).all() if nodata != nodata else (band == nodata).all()):
            return False
    return True


def read_raster(spec: LayerSpec, grid: Grid, categorical: bool = False, warn_empty: bool = True) -> np.ndarray:
    """One raster band resampled onto ``grid``: bilinear float32 with NaN no data (the precision of the
    feature GeoTIFFs; a float64 raster rounds to it), or (categorical)
    nearest int32 codes with ``NODATA_CODE`` no data. A LayerWarning when no cell gets data (``warn_empty``)."""
    if not spec.path.exists():
        raise LayerError(f"{_where(spec)}: file not found")
    try:
        with rasterio.open(spec.path) as src:
            if src.crs is None:
                raise LayerError(f"{_where(spec)}: the raster has no CRS; cannot place it on the grid")
            if not 1 <= spec.band <= src.count:
                raise LayerError(f"{_where(spec)}: band {spec.band} requested, the raster has {src.count}")
            # Only the part under the grid (the tiled build's windows): a region's corner of a large DEM
            # does not read, convert and reproject the whole raster.
            window = covering_window(src, grid)
            data = src.read(spec.band, window=window)
            src_nodata = src.nodata
            src_transform, src_crs = (src.transform if window is None else src.window_transform(window)), src.crs
            xscale, yscale = warp_scale(src, grid)
    except rasterio.errors.RasterioIOError as exc:
        raise LayerError(f"{_where(spec)}: not a readable raster: {exc}") from None
    if categorical:
        if not np.issubdtype(data.dtype, np.integer):
            raise LayerError(f"{_where(spec)}: categorical raster needs integer codes, got {data.dtype}")
        src_data = data.astype(np.int32, copy=False)  # data is this call's own array: no copy when int32
        if src_nodata is not None:
            src_data[data == src_nodata] = NODATA_CODE
        holes = (src_data == NODATA_CODE).any()
        nodata, method = NODATA_CODE, Resampling.nearest
    else:
        src_data = data.astype(np.float32, copy=False)
        if src_nodata is not None:
            src_data[data == src_nodata] = np.nan
        holes = np.isnan(src_data).any()
        nodata, method = np.nan, Resampling.bilinear
    # GDAL fills ``out`` with no data chunk by chunk on its warp threads (INIT_DEST), so it is not filled here.
    out = np.empty(grid.shape, dtype=src_data.dtype)
    # Without no-data cells in the source the warp needs no validity masks: GDAL's unmasked kernels are
    # 2.4x faster and give the same numbers, the cells they do not reach initialised to the fill (GDAL
    # reads a NaN there only as "1.#QNAN"; tests/pipeline/gis/test_layers.py checks both paths against
    # the masked warp of a no-data-filled grid).
    fill = "1.#QNAN" if nodata != nodata else str(nodata)
    masks = {"src_nodata": nodata, "dst_nodata": nodata} if holes else {"init_dest_nodata": False, "INIT_DEST": fill}
    reproject(
        src_data, out, src_transform=src_transform, src_crs=src_crs,
        dst_transform=grid.transform, dst_crs=grid.crs, resampling=method,
        num_threads=os.cpu_count() or 1,  # GDAL warps chunks independently: the same numbers on any count
        XSCALE=repr(xscale), YSCALE=repr(yscale), **masks,
    )
    if warn_empty and _all_nodata(out, nodata):
        warnings.warn(f"{_where(spec)}: no data on the grid {grid.bounds} ({grid.crs.to_string()})",
                      LayerWarning, stacklevel=2)
    return out


def read_dem(spec: LayerSpec, grid: Grid) -> np.ndarray:
    """Elevation in metres on ``grid`` (NaN no data); a DEM with no data on the grid is an error."""
    dem = read_raster(spec, grid, warn_empty=False)  # an error here, not a warning
    if _all_nodata(dem, np.nan):
        raise LayerError(f"{_where(spec)}: the DEM has no data on the grid (all nodata or off the grid {grid.bounds})")
    return dem
