"""The observation window of a fit: the grid without the square blocks where points were not looked for.

A Poisson-process fit of points observed in a window W maximises Σ_i log λ(x_i) − ∫_W λ: cells outside
W carry no information, neither for nor against targets. Spatial block CV holds whole blocks out, so a
fold's models are fitted with those blocks outside the window: counting them as searched and empty
would teach every model that the held-out blocks' terrain holds no targets, and the held-out score
would measure that bias. The fitted model is still a density over the whole grid.

Blocks are the squares of :func:`pipeline.learn.kde.block_ids` (side ``size`` metres from the grid's
lower-left corner).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from pipeline.gis.grid import Grid
from pipeline.learn.kde import block_ids


@dataclass(frozen=True)
class BlockWindow:
    """The grid less the blocks ``unobserved`` (ids of :func:`block_ids` for blocks of ``size`` metres)."""

    size: float
    unobserved: frozenset[int] = frozenset()

    def __post_init__(self) -> None:
        if not (isinstance(self.size, int | float) and self.size > 0):
            raise ValueError(f"window: block size must be > 0 metres, got {self.size!r}")
        object.__setattr__(self, "unobserved", frozenset(int(b) for b in self.unobserved))

    def without(self, blocks: Iterable[int]) -> BlockWindow:
        """This window less ``blocks`` (more unobserved blocks)."""
        return BlockWindow(self.size, self.unobserved | frozenset(int(b) for b in blocks))

    def without_points(self, grid: Grid, points: np.ndarray) -> BlockWindow:
        """This window less the blocks holding ``points`` (N, 2, metres): what a fold that holds them out leaves."""
        return self.without(np.unique(block_ids(points, grid.bounds[:2], self.size)))

    def observed(self, grid: Grid, points: np.ndarray) -> np.ndarray:
        """Per point (N, 2, metres): is it inside the window (not in an unobserved block)?"""
        return ~np.isin(block_ids(points, grid.bounds[:2], self.size), np.fromiter(self.unobserved, np.int64))


def cell_blocks(grid: Grid, size: float, row0: int = 0, rows: int | None = None) -> np.ndarray:
    """Block id (:func:`block_ids`, blocks of ``size`` metres) of every cell of rows ``row0``..``row0 + rows``, raveled."""
    xs, ys = grid.axes()
    x, y = np.meshgrid(xs, ys[row0 : row0 + (grid.height if rows is None else rows)])
    return block_ids(np.column_stack([x.ravel(), y.ravel()]), grid.bounds[:2], size)
