"""A 2-D ``.npy`` scratch file written in windows by many processes and summed without loading it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

_SUM_LEAF = 1 << 22
"""Elements per leaf of the pairwise global sum read from the scratch file (32 MiB of float64)."""


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
