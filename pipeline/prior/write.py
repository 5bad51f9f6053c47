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
import io
import json
import mmap
import os
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
DEFLATE_LEVEL = 4
"""DEFLATE level of the COGs (GDAL's default is 6): on a 10,000² density 1.3 s against 1.9-2.6 s for the
copy, for 5 % more bytes (72.9 against 69.2 MiB); level 1 is 0.35 s faster still but 23 % larger."""
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
    # COG_TMP_COMPRESSION: GDAL keeps the overviews it computes in a temporary file, ZSTD-compressed by
    # default, and reads each level back to make the next and to copy it: uncompressed, the copy of a
    # 10,000² density takes ~1.5 s less, and the COG is the same bytes (tested)
    with scratch_dir(path) as scratch, rasterio.Env(GDAL_CACHEMAX=WRITE_CACHE_BYTES, COG_TMP_COMPRESSION="NONE"):
        plain = scratch / "plain.tif"
        # the COG copy compresses; its uncompressed source is cheaper to write
        with rasterio.open(plain, "w", **geotiff_profile(grid, dtype, None, BIGTIFF="IF_SAFER", **options)) as dst:
            yield dst
        rasterio.shutil.copy(
            plain, path, driver="COG", COMPRESS="DEFLATE", LEVEL=DEFLATE_LEVEL, BLOCKSIZE=BLOCK,
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


DIRECT_CHUNK = 8 << 20
"""Bytes per write of a table file with ``O_DIRECT`` (a multiple of any file system's block size)."""
_DIRECT_ALIGN = 4096
"""Alignment of direct writes (offset, length, buffer); the last chunk is padded to it, then truncated."""


class TableFile:
    """A summed-area table's ``.npy`` file written front to back, its data hashed on the way.

    Where the file system takes ``O_DIRECT`` (Linux), the bytes go to the file through two aligned
    staging buffers (one written on a thread while the next is filled), bypassing the page cache: a 10,000² table is 0.8 GB, and on a virtual machine whose
    host backs guest memory lazily, fresh page-cache pages cost ~2 s of system time per GB (a direct
    write of the same bytes ~0.1 s). Elsewhere (tmpfs on older kernels, macOS, Windows) it writes through
    the page cache. The file holds the same bytes either way (tested).
    """

    def __init__(self, path: Path, header: bytes) -> None:
        self.path, self.digest, self._size = path, table_hash(), len(header)
        self._fd, self._used, self._written, self._pending = None, 0, 0, None
        if hasattr(os, "O_DIRECT"):
            self._fd = _open_direct(path, header)
        self.direct = self._fd is not None
        """Whether the file is written with O_DIRECT."""
        if self._fd is None:
            self._buffers = None
            self._file = open(path, "wb")  # noqa: SIM115 (closed in close())
            self._file.write(header)
        else:
            # two page-aligned buffers: one is filled (and the data hashed) while the other is written
            self._buffers = [mmap.mmap(-1, DIRECT_CHUNK), mmap.mmap(-1, DIRECT_CHUNK)]
            self._io = ThreadPoolExecutor(max_workers=1)
            self._buffers[0][: len(header)] = header
            self._used = len(header)

    def write(self, table: np.ndarray) -> None:
        """Append ``table``'s float64 bytes (C order) and hash them."""
        data = memoryview(np.ascontiguousarray(table, dtype=np.float64)).cast("B")
        self.digest.update(data)
        self._size += data.nbytes
        if self._buffers is None:
            self._file.write(data)
            return
        while data.nbytes:
            n = min(data.nbytes, DIRECT_CHUNK - self._used)
            self._buffers[0][self._used : self._used + n] = data[:n]
            self._used, data = self._used + n, data[n:]
            if self._used == DIRECT_CHUNK:
                self._flush(DIRECT_CHUNK)

    def _flush(self, length: int) -> None:
        """Start writing the first ``length`` bytes of the buffer being filled and fill the other one,
        once its own write has finished."""
        self._wait()
        self._pending = self._io.submit(_write_all, self._fd, memoryview(self._buffers[0])[:length], self._written)
        self._written += length
        self._buffers.reverse()
        self._used = 0

    def _wait(self) -> None:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            pending.result()

    def close(self) -> None:
        """Write what is staged (padded to the alignment, then truncated to the file's size) and close."""
        if self._buffers is None:
            self._file.close()
            return
        try:
            if self._used:
                self._flush(-(-self._used // _DIRECT_ALIGN) * _DIRECT_ALIGN)
            self._wait()
            os.ftruncate(self._fd, self._size)
        finally:
            self._io.shutdown(wait=True)  # a write still running (after an error) ends before the buffers go
            os.close(self._fd)
            for buffer in self._buffers:
                buffer.close()


def _open_direct(path: Path, header: bytes) -> int | None:
    """``path`` opened for direct writes, or None where the file system refuses them: at the open, or
    (some accept the flag and fail the write) at a first aligned write of the header."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_DIRECT, 0o644)
    except OSError:
        return None
    probe = mmap.mmap(-1, _DIRECT_ALIGN)
    try:
        probe[: len(header)] = header
        _write_all(fd, memoryview(probe), 0)  # rewritten by the first chunk
        return fd
    except OSError:
        os.close(fd)
        return None
    finally:
        probe.close()


def _write_all(fd: int, data: memoryview, offset: int) -> None:
    """All of ``data`` to ``fd`` at ``offset`` (a direct write may be short)."""
    done = 0
    while done < data.nbytes:
        done += os.pwrite(fd, data[done:], offset + done)


def _npy_header(shape: tuple[int, int]) -> bytes:
    """The ``.npy`` header of a C-order float64 array of ``shape`` (what ``np.save`` writes before the data)."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buffer.getvalue()


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
        header = _npy_header((h + 1, w + 1))
        with cog_writer(t_tif, grid, "float32") as dst, contextlib.ExitStack() as files:
            outs = [TableFile(t, header) for t in (t_sat, t_sat2)]
            for out in outs:
                files.callback(out.close)
                out.write(np.zeros((1, w + 1)))
            r0 = 0
            # each table's write and digest on a thread of its own beside the GeoTIFF's strip (file
            # writes, hashlib and GDAL release the GIL); done before the next strip reuses the buffers
            with ThreadPoolExecutor(max_workers=2) as pool:
                for density, sat, sat2 in strips:
                    n = density.shape[0]
                    if sat.shape != (n, w + 1) or sat2.shape != (n, w + 1):
                        raise ValueError(f"table strips must be ({n}, {w + 1}), got {sat.shape}, {sat2.shape}")
                    tables = [pool.submit(out.write, table) for out, table in zip(outs, (sat, sat2), strict=True)]
                    dst.write(density.astype(np.float32, copy=False), 1, window=Window(0, r0, w, n))
                    sample.append(np.array(density[(-r0) % step :: step, ::step], dtype=np.float32))  # a copy: buffers are reused
                    for done in tables:
                        done.result()
                    r0 += n
            if r0 != h:
                raise ValueError(f"strips cover {r0} rows of a {h}-row grid")
            dst.update_tags(**prior_tags(model), **build_tags(uuid.uuid4().hex, (out.digest.hexdigest() for out in outs)))
        t_qml.write_text(prior_qml(np.concatenate(sample)), encoding="utf-8")
        # The renames follow one by one: without the old prior.tif, a kill between them leaves no prior
        # (and tables that read refuses) instead of an old GeoTIFF beside new tables.
        path.unlink(missing_ok=True)
    return path
