"""A prior's density read from its GeoTIFF window by window, for priors larger than memory.

:meth:`pipeline.prior.TerrainPrior.read` keeps the density of a grid above :data:`WINDOWED_CELLS` cells as a
:class:`WindowedDensity` instead of one float64 array (a 50,000² prior would be 20 GB): its summed-area
tables are memory-mapped as always, and the density's cells are read where they are needed (the tracker's
lazy pyramid tiles, its few-cell integrals, point look-ups). Values are the file's float32 cells as float64,
the same numbers an in-memory read holds.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import rasterio
from rasterio.windows import Window

from pipeline.prior.write import BLOCK

__all__ = ["WINDOWED_CELLS", "WindowedDensity"]

WINDOWED_CELLS = 25_000_000
"""Grids of more cells than this are read windowed by default (200 MB as a float64 array)."""


class WindowedDensity:
    """Read-only (H, W) float64 view of band 1 of a GeoTIFF, read on demand (thread-safe, picklable:
    a worker reopens the file from its path).

    ``d[r0:r1, c0:c1]`` reads that window; ``d[rows, cols]`` with integer arrays reads the cells' blocks;
    ``np.asarray(d)`` reads everything (what small-prior code paths get). ``max`` is the largest cell value,
    set by the reader's checking pass."""

    ndim = 2
    dtype = np.dtype(np.float64)

    def __init__(self, path: str | Path, shape: tuple[int, int], max_value: float) -> None:
        self.path = str(path)
        self.shape = (int(shape[0]), int(shape[1]))
        self.max = float(max_value)
        self._local = threading.local()

    def __getstate__(self) -> dict:
        return {"path": self.path, "shape": self.shape, "max": self.max}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"], state["shape"], state["max"])

    def _src(self):
        src = getattr(self._local, "src", None)
        if src is None:  # one open handle per thread: a GDAL dataset is not safe across threads
            src = self._local.src = rasterio.open(self.path)
        return src

    def window(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Cells [r0, r1) x [c0, c1) (clipped to the grid; an empty window gives an empty array), float64."""
        h, w = self.shape
        r0, r1, c0, c1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if r1 <= r0 or c1 <= c0:
            return np.zeros((max(r1 - r0, 0), max(c1 - c0, 0)))
        return self._src().read(1, window=Window(c0, r0, c1 - c0, r1 - r0)).astype(np.float64)

    def __getitem__(self, key):
        if isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, slice) for k in key):
            (r0, r1, rs), (c0, c1, cs) = (k.indices(n) for k, n in zip(key, self.shape, strict=True))
            out = self.window(r0, max(r1, r0), c0, max(c1, c0))
            return out if rs == cs == 1 else out[::rs, ::cs]
        if isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, np.ndarray) and k.dtype.kind in "iu" for k in key):
            return self._cells(*np.broadcast_arrays(*key))
        return np.asarray(self)[key]

    def _cells(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Values at integer (rows, cols), read one file block at a time."""
        out = np.empty(rows.shape)
        flat_r, flat_c, flat = rows.ravel(), cols.ravel(), out.reshape(-1)
        if (flat_r < 0).any() or (flat_r >= self.shape[0]).any() or (flat_c < 0).any() or (flat_c >= self.shape[1]).any():
            raise IndexError(f"{self.path}: cell index outside the {self.shape} grid")
        blocks = (flat_r // BLOCK) * (-(-self.shape[1] // BLOCK)) + flat_c // BLOCK
        order = np.argsort(blocks, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(blocks[order]) != 0])
        for group in np.split(order, starts[1:]):
            br, bc = flat_r[group[0]] // BLOCK * BLOCK, flat_c[group[0]] // BLOCK * BLOCK
            block = self.window(br, br + BLOCK, bc, bc + BLOCK)
            flat[group] = block[flat_r[group] - br, flat_c[group] - bc]
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self.window(0, self.shape[0], 0, self.shape[1])
        return out if dtype is None else out.astype(dtype, copy=False)

    def strips(self, rows: int = BLOCK):
        """(r0, values) for consecutive bands of ``rows`` rows, top to bottom."""
        for r0 in range(0, self.shape[0], rows):
            yield r0, self.window(r0, r0 + rows, 0, self.shape[1])
