"""Tiled prior build: features and r tile by tile on Dask workers, the prior written without the whole raster in memory.

Each tile (a rasterio ``Window`` of the region grid) is built by :func:`pipeline.build.region.build_features`
on the tile's own sub-grid grown by a halo, then cropped: one cell for slope (Horn's 3x3 window),
and for distances the distance cap in cells — a road farther than the cap cannot change a capped
distance, so the halo makes every tile's distances exact. Features are grouped by halo, so a
cheap mask is not rasterised on the wide distance halo. The halo stops at the grid's edge, where
the in-memory build has its edge too (slope extrapolates there the same way). A tile reads only the
part of each raster it needs (a VRT window) and only the vector features within reach of its cells
(an OGR VRT spatial filter grown by margin_m + buffer_m + 2 cells), so its cost is its own area,
not the region's.

Pass 1 (parallel): each tile's unnormalised r (the likelihood product, in the same order as
:func:`pipeline.build.region.build_prior`) goes to a float64 ``.npy`` scratch file beside the output.
Pass 2 (one process, row strips read and appended with plain file I/O): the global sum of r, with numpy's own pairwise-summation tree
(so it is bit-identical to ``r.sum()`` of the whole array), then the density strips into a tiled
GeoTIFF and the summed-area tables into ``.sat.npy`` / ``.sat2.npy`` with a carried row (the same
additions as :func:`pipeline.prior.terrain.density_table_rows` over the whole grid), then a compressed
Cloud-Optimized GeoTIFF with overviews. Memory: a few tiles per worker plus a few strips.

Equality with the in-memory build on the same grid: bit-identical when every distance feature has
``max_distance_m`` in its config and rasters share the grid's CRS. Without a configured cap the cap
comes from the likelihood: the road term at the cap is within a relative 1e-12 of its floor mv
(binned tables and slope-like classes cap at their last edge, which is exact). Rasters in another
CRS are resampled per tile, which moves GDAL's approximate-transform nodes (small float differences).
Workers and client must see the output folder (a shared filesystem on a multi-machine cluster).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pyogrio
import pyogrio.errors
import rasterio
import rasterio.errors
import rasterio.shutil
from distributed import Client, as_completed
from rasterio.crs import CRS
from rasterio.windows import Window
from tqdm import tqdm

from common.atomic import atomic_paths
from common.dask import get_client
from pipeline.build.region import build_features
from pipeline.config.region import FeatureSpec, RegionConfig
from pipeline.features.stack import FeatureStack
from pipeline.gis.grid import Grid
from pipeline.gis.layers import LayerSpec, LayerWarning
from pipeline.prior.likelihood import BinnedLikelihood, LikelihoodModel, RoadDistanceLikelihood
from pipeline.prior.terrain import PriorError, density_table_rows, sat_paths

DEFAULT_TILE = 1024
"""Tile edge in cells: a multiple of the GeoTIFF block (256), small enough for a few per worker."""
STRIP_ROWS = 256
"""Rows per strip in pass 2 (one GeoTIFF block row)."""
ROAD_TAIL = 1e-12
"""Derived distance caps put the road term within this relative distance of its floor mv."""
GDAL_CACHE_BYTES = 256 << 20
"""GDAL block cache during pass 2 (bytes)."""
_SUM_LEAF = 1 << 22
"""Elements per leaf of the pairwise global sum read from the scratch file (32 MiB of float64)."""

_GDAL_TYPES = {
    "uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16", "uint32": "UInt32",
    "int32": "Int32", "uint64": "UInt64", "int64": "Int64", "float32": "Float32", "float64": "Float64",
}


class TiledBuildError(ValueError):
    """A region config or model that the tiled build cannot handle; the message names the feature."""


# ----------------------------------------------------------------------------------- windows
def tile_windows(grid: Grid, tile: int = DEFAULT_TILE) -> list[Window]:
    """Row-major windows of at most ``tile`` x ``tile`` cells covering the grid."""
    if tile < 1:
        raise ValueError(f"tile must be >= 1 cell, got {tile}")
    return [
        Window(c, r, min(tile, grid.width - c), min(tile, grid.height - r))
        for r in range(0, grid.height, tile)
        for c in range(0, grid.width, tile)
    ]


def halo_window(core: Window, rows: int, cols: int, grid: Grid) -> Window:
    """``core`` grown by ``rows`` / ``cols`` cells on each side, clipped to the grid."""
    r0, c0 = max(0, core.row_off - rows), max(0, core.col_off - cols)
    r1 = min(grid.height, core.row_off + core.height + rows)
    c1 = min(grid.width, core.col_off + core.width + cols)
    return Window(c0, r0, c1 - c0, r1 - r0)


# ---------------------------------------------------------------------------------- features
def needed_features(config: RegionConfig, names) -> dict[str, FeatureSpec]:
    """The feature specs behind ``names`` plus the sources of classes features among them."""
    out: dict[str, FeatureSpec] = {}
    for name in names:
        if name not in config.features:
            raise TiledBuildError(f"{config.path}: no [features.{name}] for the likelihood term {name!r}")
        spec = config.features[name]
        if spec.type == "classes":
            out[spec.source] = config.features[spec.source]
        out[name] = spec
    for spec in out.values():
        for layer in spec.layers:
            if config.layers[layer].kind == "pointcloud":
                raise TiledBuildError(
                    f"{config.path}: [features.{spec.name}] uses the point cloud [layers.{layer}]; "
                    "the tiled build needs a DEM raster (point clouds are gridded whole)"
                )
    return out


def _road_cap(term: RoadDistanceLikelihood) -> float:
    """Distance (m) beyond which the road term is within ROAD_TAIL (relative) of its floor mv."""
    ratio = (1.0 - term.mv) / (ROAD_TAIL * term.mv)
    return term.rmd * (1.0 + (math.sqrt(2.0 * math.log(ratio)) if ratio > 1.0 else 0.0))


def distance_caps(config: RegionConfig, model: LikelihoodModel | None, specs: dict[str, FeatureSpec]) -> dict[str, float]:
    """Cap (m) of each distance feature in ``specs``: its ``max_distance_m``, else the largest distance
    its uses can tell apart (road term: ROAD_TAIL; binned table or classes: their last edge)."""
    caps = {}
    terms = model.terms if model else {}
    for spec in specs.values():
        if spec.type != "distance":
            continue
        if spec.max_distance_m is not None:
            caps[spec.name] = spec.max_distance_m
            continue
        uses = []
        term = terms.get(spec.name)
        if isinstance(term, RoadDistanceLikelihood):
            uses.append(_road_cap(term))
        elif isinstance(term, BinnedLikelihood):
            uses.append(float(term.edges[-1]))
        uses += [s.breaks[-1] for s in specs.values() if s.type == "classes" and s.source == spec.name]
        if not uses:
            raise TiledBuildError(
                f"{config.path}: [features.{spec.name}]: the tiled build needs max_distance_m (metres) "
                "for a distance that no road/binned likelihood or classes breaks bound"
            )
        caps[spec.name] = max(uses)
    return caps


def feature_halos(specs: dict[str, FeatureSpec], caps: dict[str, float], grid: Grid) -> dict[str, tuple[int, int]]:
    """Halo (rows, cols) each feature needs: 1 cell for slope, the cap in cells for distances, else 0."""
    halos = {}
    for spec in specs.values():
        if spec.type == "slope":
            halos[spec.name] = (1, 1)
        elif spec.type == "distance":
            cap = caps[spec.name]
            halos[spec.name] = (math.ceil(cap / grid.dy), math.ceil(cap / grid.dx))
        else:
            halos[spec.name] = (0, 0)
    for spec in specs.values():
        if spec.type == "classes":
            halos[spec.name] = halos[spec.source]
    return halos


def _windowed_layer(spec: LayerSpec, grid: Grid, folder: Path) -> LayerSpec:
    """A VRT of the part of a raster layer that covers ``grid`` (plus a resampling margin), so
    :func:`pipeline.gis.layers.read_raster` reads that part only, with its own transform and no data."""
    from rasterio.warp import transform_bounds

    try:
        src = rasterio.open(spec.path)
    except rasterio.errors.RasterioIOError:
        return spec  # read_raster reports the missing or unreadable file, naming the layer
    with src:
        if src.crs is None or not 1 <= spec.band <= src.count:
            return spec  # likewise: read_raster's own messages
        bounds = grid.bounds if src.crs == grid.crs else transform_bounds(grid.crs, src.crs, *grid.bounds, densify_pts=21)
        win = src.window(*bounds)
        margin = 3  # source cells: bilinear reads 2 x 2, and the window edge rounds outward
        c0 = max(0, math.floor(win.col_off) - margin)
        r0 = max(0, math.floor(win.row_off) - margin)
        c1 = min(src.width, math.ceil(win.col_off + win.width) + margin)
        r1 = min(src.height, math.ceil(win.row_off + win.height) + margin)
        if c1 <= c0 or r1 <= r0:  # off the raster: read_raster then reports no data as it would
            return spec
        t = src.window_transform(Window(c0, r0, c1 - c0, r1 - r0))
        dtype = src.dtypes[spec.band - 1]
        nodata = src.nodata
        crs_wkt = src.crs.to_wkt() if src.crs else ""
    nodata_xml = f"<NoDataValue>{nodata!r}</NoDataValue>" if nodata is not None else ""
    vrt = (
        f'<VRTDataset rasterXSize="{c1 - c0}" rasterYSize="{r1 - r0}">'
        f"<SRS>{_xml_escape(crs_wkt)}</SRS>"
        f"<GeoTransform>{t.c!r}, {t.a!r}, {t.b!r}, {t.f!r}, {t.d!r}, {t.e!r}</GeoTransform>"
        f'<VRTRasterBand dataType="{_GDAL_TYPES[dtype]}" band="1">{nodata_xml}'
        f'<SimpleSource><SourceFilename relativeToVRT="0">{_xml_escape(str(spec.path.resolve()))}</SourceFilename>'
        f"<SourceBand>{spec.band}</SourceBand>"
        f'<SrcRect xOff="{c0}" yOff="{r0}" xSize="{c1 - c0}" ySize="{r1 - r0}"/>'
        f'<DstRect xOff="0" yOff="0" xSize="{c1 - c0}" ySize="{r1 - r0}"/>'
        "</SimpleSource></VRTRasterBand></VRTDataset>"
    )
    path = folder / f"{spec.name}.vrt"
    path.write_text(vrt)
    return dataclasses.replace(spec, path=path, band=1)


def _filtered_vector_layer(spec: LayerSpec, bounds: tuple[float, float, float, float], crs, folder: Path) -> LayerSpec:
    """An OGR VRT of a vector layer that yields only the features touching ``bounds`` (grid CRS,
    metres), in source order, so a tile reads and burns its own roads instead of the whole layer.
    Layers in another CRS (or with a restored index) are returned as they are: their box would
    need reprojecting, and read_vector's own checks apply to the original file."""
    if spec.restore_index or spec.path.suffix.lower() == ".vrt":
        return spec
    try:
        info = pyogrio.read_info(spec.path, layer=spec.layer)
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError):
        return spec  # read_vector reports the missing or unreadable file or layer, naming it
    if info["crs"] is None or not CRS.from_user_input(info["crs"]) == crs:
        return spec
    layer = spec.layer if spec.layer is not None else str(pyogrio.list_layers(spec.path)[0, 0])
    x0, y0, x1, y1 = bounds
    vrt = (
        "<OGRVRTDataSource>"
        f'<OGRVRTLayer name="{_xml_escape(layer)}">'
        f'<SrcDataSource relativeToVRT="0">{_xml_escape(str(spec.path.resolve()))}</SrcDataSource>'
        f"<SrcLayer>{_xml_escape(layer)}</SrcLayer>"
        f'<SrcRegion clip="false">POLYGON(({x0!r} {y0!r},{x1!r} {y0!r},{x1!r} {y1!r},{x0!r} {y1!r},{x0!r} {y0!r}))</SrcRegion>'
        "</OGRVRTLayer></OGRVRTDataSource>"
    )
    path = folder / f"{spec.name}.vrt"
    path.write_text(vrt)
    return dataclasses.replace(spec, path=path, layer=layer)


def _xml_escape(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def tile_features(config: RegionConfig, specs: dict[str, FeatureSpec], caps: dict[str, float], core: Window) -> FeatureStack:
    """The features ``specs`` on the window ``core`` of the region grid, each built on its halo
    window by :func:`pipeline.build.region.build_features` (distances capped at ``caps``) and cropped."""
    grid = config.grid
    halos = feature_halos(specs, caps, grid)
    stack = FeatureStack(grid.window_grid(core.row_off, core.col_off, core.height, core.width))
    for halo in sorted(set(halos.values())):
        group = {
            n: (dataclasses.replace(s, max_distance_m=caps[n]) if s.type == "distance" else s)
            for n, s in specs.items() if halos[n] == halo
        }
        win = halo_window(core, *halo, grid)
        sub_grid = grid.window_grid(win.row_off, win.col_off, win.height, win.width)
        # Vector features reach a tile's cells from at most margin_m + buffer_m (+ a cell for
        # all_touched) outside it; categories read whole layers (their classes and checks are global).
        reach = max((s.margin_m + s.buffer_m for s in group.values() if s.type in ("mask", "distance")), default=0.0)
        reach += 2 * max(grid.dx, grid.dy)
        x0, y0, x1, y1 = sub_grid.bounds
        box = (x0 - reach, y0 - reach, x1 + reach, y1 + reach)
        whole = {s.layer for s in specs.values() if s.type == "categories"}
        with tempfile.TemporaryDirectory(prefix="tile-vrt-") as tmp:
            layers = dict(config.layers)
            for name in {ly for s in group.values() for ly in s.layers}:
                if layers[name].kind == "raster":
                    layers[name] = _windowed_layer(layers[name], sub_grid, Path(tmp))
                elif layers[name].kind == "vector" and name not in whole:
                    layers[name] = _filtered_vector_layer(layers[name], box, grid.crs, Path(tmp))
            sub = dataclasses.replace(config, grid=sub_grid, layers=layers, features=group)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LayerWarning)  # "no geometry touches the grid" is normal for a tile
                built = build_features(sub, progress=False)
        r0, c0 = core.row_off - win.row_off, core.col_off - win.col_off
        for f in built:
            values = np.ascontiguousarray(f.values[r0 : r0 + core.height, c0 : c0 + core.width])
            stack.add(dataclasses.replace(f, values=values))
    return stack


# ----------------------------------------------------------------------------- scratch files
class NpyRows:
    """A 2-D ``.npy`` file written in windows with positioned writes and summed through short-lived
    memory maps, so a process's resident memory holds only the rows it touches (several processes
    may write disjoint windows of one file)."""

    def __init__(self, path: Path, shape: tuple[int, int], dtype=np.float64, create: bool = False) -> None:
        self.path, self.shape, self.dtype = Path(path), tuple(shape), np.dtype(dtype)
        # Mapping the whole file touches no pages; only its header offset is kept.
        mm = np.lib.format.open_memmap(self.path, mode="w+" if create else "r", dtype=self.dtype, shape=self.shape)
        self.offset = mm.offset
        del mm

    def _map(self, start: int, shape: tuple[int, ...], mode: str) -> np.memmap:
        return np.memmap(self.path, dtype=self.dtype, mode=mode, offset=self.offset + start * self.dtype.itemsize, shape=shape)

    def write(self, row_off: int, col_off: int, block: np.ndarray) -> None:
        """Write ``block`` at (row_off, col_off) with one positioned write per row: no memory map
        to fault in and msync, and closing the file publishes it (close-to-open on a shared FS)."""
        block = np.ascontiguousarray(block, dtype=self.dtype)
        size, width = self.dtype.itemsize, self.shape[1]
        with open(self.path, "r+b") as f:
            for i, row in enumerate(block):
                os.pwrite(f.fileno(), memoryview(row).cast("B"), self.offset + ((row_off + i) * width + col_off) * size)

    def pairwise_sum(self) -> float:
        """Sum of all elements, bit-identical to numpy's ``a.sum()`` of the whole C-ordered array:
        numpy splits a contiguous reduction pairwise (halves rounded down to a multiple of 8), so
        evaluating the same tree with leaves summed by numpy reproduces it exactly."""

        def node(start: int, n: int) -> float:
            if n <= _SUM_LEAF:
                leaf = self._map(start, (n,), "r")
                s = np.add.reduce(leaf, initial=0.0)
                del leaf
                return s
            n2 = n // 2
            n2 -= n2 % 8
            return node(start, n2) + node(start + n2, n - n2)

        return float(node(0, self.shape[0] * self.shape[1]))


# ------------------------------------------------------------------------------------ pass 1
def _r_tile(config: RegionConfig, model: LikelihoodModel, specs, caps, core: Window, r_path: str) -> dict:
    """Pass 1 for one tile: features, r = Π r_i in build_prior's order, written to the scratch file."""
    t0 = time.perf_counter()
    stack = tile_features(config, specs, caps, core)
    r = np.ones(stack.grid.shape, dtype=np.float64)
    nonzero = {}
    for name, term in model.terms.items():
        single = LikelihoodModel({name: term}).evaluate(stack)
        nonzero[name] = bool(single.any())
        r *= single
    bad = ~np.isfinite(r) | (r < 0)
    first_bad = None
    if bad.any():
        rows, cols = np.nonzero(bad)
        first_bad = (int(rows[0]) + core.row_off, int(cols[0]) + core.col_off)
    NpyRows(Path(r_path), config.grid.shape).write(core.row_off, core.col_off, r)
    return {"nonzero": nonzero, "n_bad": int(bad.sum()), "first_bad": first_bad,
            "cells": int(r.size), "seconds": time.perf_counter() - t0}


def _worker_name() -> str:
    from distributed import get_worker

    try:
        return get_worker().address
    except ValueError:
        return "local"


def _timed_r_tile(*args) -> dict:
    out = _r_tile(*args)
    out["worker"] = _worker_name()
    return out


# ------------------------------------------------------------------------------------ pass 2
def _write_prior(r_store: NpyRows, total_r: float, grid: Grid, t_sat: Path, t_sat2: Path, t_tif: Path,
                 description: dict, scratch: Path, progress: bool) -> None:
    """Density strips -> tiled GeoTIFF -> COG, and both summed-area tables, each strip under the
    last table row of the strip before. Rows are read and appended with plain file I/O (no memory
    maps, no per-strip msync), into buffers allocated once."""
    h, w = grid.shape
    total = total_r * grid.cell_area
    rows = STRIP_ROWS
    r_buf = np.empty((rows, w))
    density = np.empty((rows, w), dtype=np.float32)  # the kernel rounds float64 -> float32 as astype does
    block = np.empty((rows + 1, w + 1))  # row 0: the last table row of the strip before (zeros at first)
    block2 = np.empty((rows + 1, w + 1))
    block[0] = 0.0
    block2[0] = 0.0
    plain = scratch / "density.tif"
    profile = {
        "driver": "GTiff", "height": h, "width": w, "count": 1, "dtype": "float32", "crs": grid.crs,
        "transform": grid.transform, "tiled": True, "blockxsize": 256, "blockysize": 256, "BIGTIFF": "IF_SAFER",
    }
    header = NpyRows(t_sat, (h + 1, w + 1), create=True).offset
    NpyRows(t_sat2, (h + 1, w + 1), create=True)
    with (rasterio.open(plain, "w", **profile) as dst, open(r_store.path, "rb") as f_r,
          open(t_sat, "r+b") as f_sat, open(t_sat2, "r+b") as f_sat2):
        f_r.seek(r_store.offset)
        for f_out in (f_sat, f_sat2):
            f_out.seek(header)
            f_out.write(memoryview(block[0]))  # the zero top row of the padded table
        for r0 in tqdm(range(0, h, rows), desc="prior strips", unit="strip", disable=not progress):
            n = min(rows, h - r0)
            f_r.readinto(memoryview(r_buf[:n]).cast("B"))
            density_table_rows(r_buf[:n], total, grid.cell_area, block[0], block2[0], density[:n], block[1 : n + 1], block2[1 : n + 1])
            dst.write(density[:n], 1, window=Window(0, r0, w, n))
            f_sat.write(memoryview(block[1 : n + 1]).cast("B"))
            f_sat2.write(memoryview(block2[1 : n + 1]).cast("B"))
            block[0] = block[n]
            block2[0] = block2[n]
        dst.update_tags(MODEL=json.dumps(description), UNITS="probability density per square metre")
    rasterio.shutil.copy(
        plain, t_tif, driver="COG", COMPRESS="DEFLATE", BLOCKSIZE=256,
        OVERVIEW_RESAMPLING="AVERAGE", NUM_THREADS="ALL_CPUS", BIGTIFF="IF_SAFER",
    )


# -------------------------------------------------------------------------------------- build
def build_prior_tiled(
    config: RegionConfig,
    out: str | Path,
    model: LikelihoodModel | None = None,
    client: Client | None = None,
    tile: int = DEFAULT_TILE,
    provenance: dict | None = None,
    progress: bool = True,
) -> dict:
    """Build the region's prior tile by tile on ``client`` (default: an in-process cluster) and write
    ``out`` (a COG: float32 density per m², deflate, overviews) with its summed-area tables beside it,
    atomically. Readable with :meth:`pipeline.prior.terrain.TerrainPrior.read`.

    Returns a summary: path, shape, tiles, seconds of each pass, tile seconds per worker.
    """
    model = model or config.model
    if model is None:
        raise PriorError(f"{config.path}: no [likelihood.<feature>] tables and no model given")
    out = Path(out)
    specs = needed_features(config, model.terms)
    caps = distance_caps(config, model, specs)
    windows = tile_windows(config.grid, tile)
    description = model.to_dict()
    description["provenance"] = provenance if provenance is not None else {"region": config.name, "config": str(config.path)}
    own_client = client is None
    client = client or get_client(None)
    t0 = time.perf_counter()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{out.stem}.tiles-", dir=out.parent) as scratch:
            scratch = Path(scratch)
            r_store = NpyRows(scratch / "r.npy", config.grid.shape, create=True)
            futures = client.map(_timed_r_tile, [config] * len(windows), [model] * len(windows), [specs] * len(windows),
                                 [caps] * len(windows), windows, [str(r_store.path)] * len(windows), pure=False)
            results = []
            for fut in tqdm(as_completed(futures), total=len(futures), desc="prior tiles", unit="tile", disable=not progress):
                results.append(fut.result())
            t1 = time.perf_counter()
            _check_tiles(config, results)
            total_r = r_store.pairwise_sum()
            if not total_r * config.grid.cell_area > 0:
                raise PriorError(
                    "the likelihood table makes r zero everywhere on the grid; check for structural zeros covering the region"
                )
            # GDAL's block cache defaults to 5% of RAM; pass 2 streams, so a small cache keeps the client small.
            with atomic_paths(*sat_paths(out), out) as (t_sat, t_sat2, t_tif), rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_BYTES):
                _write_prior(r_store, total_r, config.grid, t_sat, t_sat2, t_tif, description, scratch, progress)
    finally:
        if own_client:
            client.close()
    t2 = time.perf_counter()
    per_worker: dict[str, dict] = {}
    for res in results:
        wk = per_worker.setdefault(res["worker"], {"tiles": 0, "cells": 0, "seconds": 0.0})
        wk["tiles"] += 1
        wk["cells"] += res["cells"]
        wk["seconds"] += res["seconds"]
    return {
        "path": str(out), "shape": list(config.grid.shape), "tile": tile, "n_tiles": len(windows),
        "distance_caps_m": caps, "tiles_seconds": t1 - t0, "write_seconds": t2 - t1, "total_seconds": t2 - t0,
        "workers": per_worker,
    }


def _check_tiles(config: RegionConfig, results: list[dict]) -> None:
    """The checks build_prior and TerrainPrior.from_array make, over all tiles."""
    names = results[0]["nonzero"] if results else {}
    for name in names:
        if not any(res["nonzero"][name] for res in results):
            raise PriorError(f"[likelihood.{name}] is zero on every cell of the grid, so the prior would be zero everywhere")
    n_bad = sum(res["n_bad"] for res in results)
    if n_bad:
        first = min(res["first_bad"] for res in results if res["first_bad"] is not None)
        raise PriorError(
            f"likelihood must be finite and >= 0; {n_bad} bad cells, first at row {first[0]}, col {first[1]}"
        )
