"""The one writer of GeoTIFFs on a grid and of the prior set: ``prior.tif`` (a Cloud-Optimized GeoTIFF,
float32 density per m^2, the model as tags) with ``prior.sat.npy`` / ``prior.sat2.npy`` and its QGIS
style ``prior.qml`` beside it, committed together.

The density and tables arrive in row strips, so a prior larger than memory is written as it is
computed (the tiled build) and an in-memory one is written the same way.

One build binds the files: ``prior.tif`` carries a random build id (tag ``PRIOR_BUILD``) and the
SHA-1 of each table's data (tags ``SAT_SHA1``, ``SAT2_SHA1``); the tables stay plain ``.npy`` files.
The GeoTIFF is renamed into place last, and the old one is removed just before the tables are, so an
interrupted rebuild leaves no ``prior.tif`` (absent) rather than an old one beside new tables, and
:meth:`pipeline.prior.terrain.TerrainPrior.read` refuses any set whose tables do not match the tags.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import uuid
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.io import DatasetWriter
from rasterio.windows import Window

from common.atomic import atomic_paths, scratch_dir
from pipeline.gis.grid import Grid
from pipeline.prior.style import prior_qml, style_path

BLOCK = 256
"""GeoTIFF tile edge in cells."""
UNITS = "probability density per square metre"
"""The ``UNITS`` tag of a prior GeoTIFF."""
STYLE_SAMPLE_EDGE = 1024
"""The prior's style is fitted to every k-th row and column, k chosen so at most this many of each."""
BUILD_TAG = "PRIOR_BUILD"
"""The tag holding a prior's build id (32 hex digits, random per build)."""
WRITE_CACHE_BYTES = 64 << 20
"""GDAL's block cache while a GeoTIFF is written (bytes): the default, 5% of RAM, would hold most of
a large grid's blocks again beside the arrays they are written from."""
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


@contextlib.contextmanager
def cog_writer(path: str | Path, grid: Grid, dtype: str, resampling: str = "AVERAGE", **options) -> Iterator[DatasetWriter]:
    """Yield a one-band GeoTIFF on ``grid`` open for writing (bands, tags); when the block succeeds,
    copy it to ``path`` as a Cloud-Optimized GeoTIFF: deflate, BLOCK x BLOCK tiles, overviews made
    with GDAL's ``resampling`` (AVERAGE for densities, NEAREST for category codes). ``options``: extra
    profile keys (e.g. ``nodata``). The uncompressed source lives in a scratch folder beside ``path``."""
    path = Path(path)
    with scratch_dir(path) as scratch, rasterio.Env(GDAL_CACHEMAX=WRITE_CACHE_BYTES):
        plain = scratch / "plain.tif"
        # the COG copy compresses; its uncompressed source is cheaper to write
        with rasterio.open(plain, "w", **geotiff_profile(grid, dtype, None, BIGTIFF="IF_SAFER", **options)) as dst:
            yield dst
        rasterio.shutil.copy(
            plain, path, driver="COG", COMPRESS="DEFLATE", BLOCKSIZE=BLOCK,
            OVERVIEW_RESAMPLING=resampling, NUM_THREADS="ALL_CPUS", BIGTIFF="IF_SAFER",
        )


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


def _write_and_hash(f_out, digest, table: np.ndarray) -> None:
    data = memoryview(np.ascontiguousarray(table, dtype=np.float64)).cast("B")
    f_out.write(data)
    digest.update(data)


def write_prior(
    path: str | Path,
    grid: Grid,
    model: dict,
    strips: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> Path:
    """Write the prior set of ``path`` atomically from ``strips``: successive (density, sat, sat2) row
    bands from the top, density (n, W) per m^2 (written as float32), tables (n, W+1) float64 — the rows
    below the zero top row of the padded (H+1, W+1) summed-area tables. The strips' buffers may be reused
    between strips. The GeoTIFF is a COG with overviews; its QGIS style (:func:`pipeline.prior.style.prior_qml`
    of a decimated sample of the density) goes beside it. Returns the GeoTIFF path."""
    path = Path(path)
    h, w = grid.shape
    step = max(1, -(-max(h, w) // STYLE_SAMPLE_EDGE))
    sample = []
    # Tables and style first, GeoTIFF last: a complete prior.tif implies a complete set.
    with atomic_paths(*sat_paths(path), style_path(path), path) as (t_sat, t_sat2, t_qml, t_tif):
        header = np.lib.format.open_memmap(t_sat, mode="w+", dtype=np.float64, shape=(h + 1, w + 1)).offset
        np.lib.format.open_memmap(t_sat2, mode="w+", dtype=np.float64, shape=(h + 1, w + 1))
        with (cog_writer(t_tif, grid, "float32") as dst, open(t_sat, "r+b") as f_sat, open(t_sat2, "r+b") as f_sat2):
            hashes = (table_hash(), table_hash())
            outs = ((f_sat, hashes[0]), (f_sat2, hashes[1]))
            zero = memoryview(np.zeros(w + 1)).cast("B")
            for f_out, digest in outs:
                f_out.seek(header)
                f_out.write(zero)
                digest.update(zero)
            r0 = 0
            # each table's write and digest on a thread of its own beside the GeoTIFF's strip (file
            # writes, hashlib and GDAL release the GIL); done before the next strip reuses the buffers
            with ThreadPoolExecutor(max_workers=2) as pool:
                for density, sat, sat2 in strips:
                    n = density.shape[0]
                    if sat.shape != (n, w + 1) or sat2.shape != (n, w + 1):
                        raise ValueError(f"table strips must be ({n}, {w + 1}), got {sat.shape}, {sat2.shape}")
                    tables = [pool.submit(_write_and_hash, f_out, digest, table)
                              for (f_out, digest), table in zip(outs, (sat, sat2), strict=True)]
                    dst.write(density.astype(np.float32, copy=False), 1, window=Window(0, r0, w, n))
                    sample.append(np.array(density[(-r0) % step :: step, ::step], dtype=np.float32))  # a copy: buffers are reused
                    for done in tables:
                        done.result()
                    r0 += n
            if r0 != h:
                raise ValueError(f"strips cover {r0} rows of a {h}-row grid")
            dst.update_tags(**prior_tags(model), **build_tags(uuid.uuid4().hex, (d.hexdigest() for d in hashes)))
        t_qml.write_text(prior_qml(np.concatenate(sample)), encoding="utf-8")
        # The renames follow one by one: without the old prior.tif, a kill between them leaves no prior
        # (and tables that read refuses) instead of an old GeoTIFF beside new tables.
        path.unlink(missing_ok=True)
    return path
