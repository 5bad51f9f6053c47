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
Pass 2 (one process, row strips read with plain file I/O): the global sum of r, with numpy's own
pairwise-summation tree (so it is bit-identical to ``r.sum()`` of the whole array), then density and
summed-area table strips with a carried row (the same additions as
:func:`pipeline.prior.terrain.density_table_rows` over the whole grid) into the one prior writer,
:func:`pipeline.prior.write.write_prior`, as a Cloud-Optimized GeoTIFF with overviews. Memory: a few
tiles per worker plus a few strips.

Modules: :mod:`pipeline.tiled.windows` (tiles, halos, distance caps), :mod:`pipeline.tiled.vrt`
(windowed inputs), :mod:`pipeline.tiled.tiles` (one tile's features), :mod:`pipeline.tiled.store`
(the scratch file of r).

Equality with the in-memory build on the same grid: bit-identical when every distance feature has
``max_distance_m`` in its config and rasters share the grid's CRS. Without a configured cap the cap
comes from the likelihood: the road term at the cap is within a relative 1e-12 of its floor mv
(binned tables and slope-like classes cap at their last edge, which is exact). Rasters in another
CRS are resampled per tile, which moves GDAL's approximate-transform nodes (small float differences).
Workers and client must see the output folder (a shared filesystem on a multi-machine cluster).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from distributed import Client, as_completed
from rasterio.windows import Window
from tqdm import tqdm

from common.dask import using_client
from pipeline.build.region import (
    learned_calibration,
    region_model,
    region_provenance,
    temper_rows,
    uniform_share,
)
from pipeline.config.region import RegionConfig
from pipeline.gis.grid import Grid
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.terrain import PriorError, density_table_rows
from pipeline.prior.write import write_prior
from pipeline.tiled.store import NpyRows
from pipeline.tiled.tiles import tile_features
from pipeline.tiled.windows import DEFAULT_TILE, distance_caps, needed_features, tile_windows

STRIP_ROWS = 256
"""Rows per strip in pass 2 (one GeoTIFF block row)."""


# ------------------------------------------------------------------------------------ pass 1
def _r_tile(config: RegionConfig, model: LikelihoodModel, specs, caps, core: Window, r_path: str) -> dict:
    """Pass 1 for one tile: features, r = Π r_i in build_prior's order (tempered by a learned model's τ),
    written to the scratch file."""
    t0 = time.perf_counter()
    stack = tile_features(config, specs, caps, core)
    r = np.ones(stack.grid.shape, dtype=np.float64)
    nonzero = {}
    for name, term in model.terms.items():
        single = LikelihoodModel({name: term}).evaluate(stack)
        nonzero[name] = bool(single.any())
        r *= single
    temper_rows(r, learned_calibration(model)[0])
    bad = ~np.isfinite(r) | (r < 0)
    first_bad = None
    if bad.any():
        rows, cols = np.nonzero(bad)
        first_bad = (int(rows[0]) + core.row_off, int(cols[0]) + core.col_off)
    NpyRows(Path(r_path), config.grid.shape).write(core.row_off, core.col_off, r)
    return {"nonzero": nonzero, "n_bad": int(bad.sum()), "first_bad": first_bad, "n_support": int((r > 0).sum()),
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
def _prior_strips(r_store: NpyRows, total_r: float, grid: Grid, progress: bool,
                  share: float = 0.0, n_support: int = 0) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Density and table strips of STRIP_ROWS rows for :func:`pipeline.prior.write.write_prior`, each
    under the last table row of the strip before. Rows of r are read with plain file I/O (no memory
    maps, no per-strip msync) into buffers allocated once and reused for every strip. ``share``: the
    defensive mixture's constant added to each of the ``n_support`` cells with r > 0
    (:func:`pipeline.build.region.uniform_share`)."""
    h, w = grid.shape
    total = (total_r + share * n_support) * grid.cell_area
    rows = STRIP_ROWS
    r_buf = np.empty((rows, w))
    density = np.empty((rows, w), dtype=np.float32)  # the kernel rounds float64 -> float32 as astype does
    block = np.empty((rows + 1, w + 1))  # row 0: the last table row of the strip before (zeros at first)
    block2 = np.empty((rows + 1, w + 1))
    block[0] = 0.0
    block2[0] = 0.0
    with open(r_store.path, "rb") as f_r:
        f_r.seek(r_store.offset)
        for r0 in tqdm(range(0, h, rows), desc="prior strips", unit="strip", disable=not progress):
            n = min(rows, h - r0)
            f_r.readinto(memoryview(r_buf[:n]).cast("B"))
            if share:
                r_buf[:n] += share * (r_buf[:n] > 0)
            density_table_rows(r_buf[:n], total, grid.cell_area, block[0], block2[0], density[:n], block[1 : n + 1], block2[1 : n + 1])
            yield density[:n], block[1 : n + 1], block2[1 : n + 1]
            block[0] = block[n]
            block2[0] = block2[n]


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
    model = region_model(config, model)
    eps = learned_calibration(model)[1]  # checked here, before the tiles (which apply τ) run
    out = Path(out)
    specs = needed_features(config, model.terms)
    caps = distance_caps(config, model, specs)
    windows = tile_windows(config.grid, tile)
    description = model.to_dict()
    description["provenance"] = region_provenance(config) if provenance is None else provenance
    t0 = time.perf_counter()
    with using_client(client) as client:
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
            n_support = sum(res["n_support"] for res in results)
            share = uniform_share(total_r, n_support, eps)
            # write_prior caps GDAL's block cache itself (WRITE_CACHE_BYTES)
            write_prior(out, config.grid, description, _prior_strips(r_store, total_r, config.grid, progress, share, n_support))
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
