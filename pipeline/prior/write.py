"""The one writer of GeoTIFFs on a grid and of the prior set: ``prior.tif`` (float32 density per m^2,
the model as tags) with ``prior.sat.npy`` / ``prior.sat2.npy`` beside it, committed together.

The density and tables arrive in row strips, so a prior larger than memory is written as it is
computed (the tiled build) and an in-memory one is written the same way.

One build binds the three files: ``prior.tif`` carries a random build id (tag ``PRIOR_BUILD``) and the
SHA-1 of each table's data (tags ``SAT_SHA1``, ``SAT2_SHA1``); the tables stay plain ``.npy`` files.
The GeoTIFF is renamed into place last, and the old one is removed just before the tables are, so an
interrupted rebuild leaves no ``prior.tif`` (absent) rather than an old one beside new tables, and
:meth:`pipeline.prior.terrain.TerrainPrior.read` refuses any set whose tables do not match the tags.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.windows import Window

from common.atomic import atomic_paths, scratch_dir
from pipeline.gis.grid import Grid

BLOCK = 256
"""GeoTIFF tile edge in cells."""
UNITS = "probability density per square metre"
"""The ``UNITS`` tag of a prior GeoTIFF."""
BUILD_TAG = "PRIOR_BUILD"
"""The tag holding a prior's build id (32 hex digits, random per build)."""
TABLE_TAGS = ("SAT_SHA1", "SAT2_SHA1")
"""The tags holding the SHA-1 (hex) of the data bytes after the ``.npy`` header of each table, as
:func:`sat_paths` orders them."""


def table_hash() -> hashlib._Hash:
    """A fresh hash of table data (SHA-1: it guards against mixed or damaged files, not against forgery,
    and is twice as fast as SHA-256 here)."""
    return hashlib.sha1(usedforsecurity=False)


def geotiff_profile(grid: Grid, dtype: str, compress: str | None = "deflate", **options) -> dict:
    """rasterio profile of a one-band GeoTIFF on ``grid``: BLOCK x BLOCK tiles, ``compress`` (None:
    uncompressed), plus any creation ``options`` (e.g. ``nodata``, ``BIGTIFF``)."""
    profile = {
        "driver": "GTiff", "height": grid.height, "width": grid.width, "count": 1, "dtype": dtype,
        "crs": grid.crs, "transform": grid.transform, "tiled": True, "blockxsize": BLOCK, "blockysize": BLOCK,
    }
    if compress is not None:
        profile["compress"] = compress
    return profile | options


def prior_tags(model: dict) -> dict[str, str]:
    """Tags of a prior GeoTIFF: the model description as JSON (``MODEL``) and the density's ``UNITS``."""
    return {"MODEL": json.dumps(model), "UNITS": UNITS}


def build_tags(build: str, digests: Iterable[str]) -> dict[str, str]:
    """Tags binding a prior GeoTIFF to its tables: the build id and each table's digest (hex)."""
    return {BUILD_TAG: build, **dict(zip(TABLE_TAGS, digests, strict=True))}


def sat_paths(path: str | Path) -> tuple[Path, Path]:
    """Where the summed-area tables of r and r^2 live beside a prior GeoTIFF."""
    p = Path(path)
    return p.with_suffix(".sat.npy"), p.with_suffix(".sat2.npy")


def write_prior(
    path: str | Path,
    grid: Grid,
    model: dict,
    strips: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
    cog: bool = False,
) -> Path:
    """Write the prior set of ``path`` atomically from ``strips``: successive (density, sat, sat2) row
    bands from the top, density (n, W) per m^2 (written as float32), tables (n, W+1) float64 — the rows
    below the zero top row of the padded (H+1, W+1) summed-area tables. The strips' buffers may be reused
    between strips. ``cog``: a Cloud-Optimized GeoTIFF with overviews instead of a deflated tiled one.
    Returns the GeoTIFF path."""
    path = Path(path)
    # Tables first, GeoTIFF last: a complete prior.tif implies complete tables.
    with atomic_paths(*sat_paths(path), path) as (t_sat, t_sat2, t_tif):
        if cog:
            with scratch_dir(path) as scratch:
                plain = scratch / "density.tif"
                _write_set(t_sat, t_sat2, plain, grid, model, strips, cog)
                rasterio.shutil.copy(
                    plain, t_tif, driver="COG", COMPRESS="DEFLATE", BLOCKSIZE=BLOCK,
                    OVERVIEW_RESAMPLING="AVERAGE", NUM_THREADS="ALL_CPUS", BIGTIFF="IF_SAFER",
                )
        else:
            _write_set(t_sat, t_sat2, t_tif, grid, model, strips, cog)
        # The renames follow one by one: without the old prior.tif, a kill between them leaves no prior
        # (and tables that read refuses) instead of an old GeoTIFF beside new tables.
        path.unlink(missing_ok=True)
    return path


def _write_set(t_sat: Path, t_sat2: Path, plain: Path, grid: Grid, model: dict,
               strips: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], cog: bool) -> None:
    """Write the tables to ``t_sat`` / ``t_sat2`` and the density GeoTIFF to ``plain``, hashing the table
    data as it is written, then tag the GeoTIFF with the model and the build binding."""
    h, w = grid.shape
    hashes = (table_hash(), table_hash())
    # the COG copy compresses; its uncompressed source is cheaper to write
    profile = geotiff_profile(grid, "float32", None, BIGTIFF="IF_SAFER") if cog else geotiff_profile(grid, "float32")
    header = np.lib.format.open_memmap(t_sat, mode="w+", dtype=np.float64, shape=(h + 1, w + 1)).offset
    np.lib.format.open_memmap(t_sat2, mode="w+", dtype=np.float64, shape=(h + 1, w + 1))
    with (rasterio.open(plain, "w", **profile) as dst, open(t_sat, "r+b") as f_sat, open(t_sat2, "r+b") as f_sat2):
        outs = ((f_sat, hashes[0]), (f_sat2, hashes[1]))
        zero = memoryview(np.zeros(w + 1)).cast("B")
        for f_out, digest in outs:
            f_out.seek(header)
            f_out.write(zero)
            digest.update(zero)
        r0 = 0
        for density, sat, sat2 in strips:
            n = density.shape[0]
            if sat.shape != (n, w + 1) or sat2.shape != (n, w + 1):
                raise ValueError(f"table strips must be ({n}, {w + 1}), got {sat.shape}, {sat2.shape}")
            dst.write(density.astype(np.float32, copy=False), 1, window=Window(0, r0, w, n))
            for (f_out, digest), table in zip(outs, (sat, sat2), strict=True):
                data = memoryview(np.ascontiguousarray(table, dtype=np.float64)).cast("B")
                f_out.write(data)
                digest.update(data)
            r0 += n
        if r0 != h:
            raise ValueError(f"strips cover {r0} rows of a {h}-row grid")
        dst.update_tags(**prior_tags(model), **build_tags(uuid.uuid4().hex, (d.hexdigest() for d in hashes)))
