"""Exact Euclidean distance transform in metres on grids with (possibly non-square) cells.

Felzenszwalb & Huttenlocher's separable algorithm (Theory of Computing 8, 2012): a pass down
each column finds the row offset of the nearest target in that column, then a pass along each
row takes the lower envelope of parabolas ``(dx*(c - q))^2 + (dy*g[q])^2``. Both passes are
linear in the number of cells and run in parallel with numba; the result is exact (not the
paper's two-pass chamfer approximation) and needs one int32 work array beside the output (uint16
under a cap of fewer than 65,535 rows).
"""

from __future__ import annotations

import numba as nb
import numpy as np

_NONE = np.iinfo(np.int32).max
"""Column offset meaning "no target in this column" in the int32 work array."""
_NONE16 = np.iinfo(np.uint16).max
"""The same in the uint16 work array of a capped transform, whose offsets beyond the cap mean "none" too."""

_COL_BLOCK = 256
"""Columns per parallel task in the column pass: rows are walked in order, so memory stays sequential."""


@nb.njit(cache=True, parallel=True)
def _column_offsets(mask: np.ndarray, g: np.ndarray, limit: int, none: int) -> None:
    """g[r, c] = |r - r*| for the nearest target row r* in column c, or ``none`` when the column has
    none within ``limit`` rows."""
    h, w = mask.shape
    n_blocks = (w + _COL_BLOCK - 1) // _COL_BLOCK
    for b in nb.prange(n_blocks):
        c0 = b * _COL_BLOCK
        c1 = min(c0 + _COL_BLOCK, w)
        last = np.full(c1 - c0, -1, dtype=np.int64)
        for r in range(h):
            for c in range(c0, c1):
                if mask[r, c]:
                    last[c - c0] = r
                g[r, c] = none if last[c - c0] < 0 or r - last[c - c0] > limit else r - last[c - c0]
        last[:] = -1
        for r in range(h - 1, -1, -1):
            for c in range(c0, c1):
                if mask[r, c]:
                    last[c - c0] = r
                if last[c - c0] >= 0 and last[c - c0] - r <= limit and last[c - c0] - r < g[r, c]:
                    g[r, c] = last[c - c0] - r


@nb.njit(cache=True, parallel=True)
def _row_envelopes(g: np.ndarray, none: int, dx: float, dy: float, cap: float, r0: int, c0: int, out: np.ndarray) -> None:
    """out[r, c] = min_q sqrt((dx*(c0+c-q))^2 + (dy*g[r0+r,q])^2), capped at ``cap`` (inf: no cap): the
    window of ``out``'s shape at row r0, column c0 of the distances, every column q of g not ``none`` a candidate."""
    w = g.shape[1]
    for r in nb.prange(out.shape[0]):
        gr = g[r0 + r]
        f = np.empty(w, dtype=np.float64)  # squared column distance, metres^2
        v = np.empty(w, dtype=np.int64)  # columns of the parabolas in the envelope
        z = np.empty(w + 1, dtype=np.float64)  # envelope breakpoints, metres
        k = -1
        for q in range(w):
            if gr[q] == none:
                continue
            f[q] = (dy * gr[q]) ** 2
            pq = dx * q
            while k >= 0:
                pv = dx * v[k]
                s = ((f[q] + pq * pq) - (f[v[k]] + pv * pv)) / (2.0 * (pq - pv))
                if s <= z[k]:
                    k -= 1
                else:
                    break
            k += 1
            v[k] = q
            z[k] = -np.inf if k == 0 else s
            z[k + 1] = np.inf
        if k < 0:
            for c in range(out.shape[1]):
                out[r, c] = cap
            continue
        j = 0
        for c in range(out.shape[1]):
            pc = dx * (c0 + c)
            while z[j + 1] < pc:
                j += 1
            d = np.sqrt((pc - dx * v[j]) ** 2 + f[v[j]])
            out[r, c] = d if d < cap else cap


def distance_m(
    mask: np.ndarray,
    dx: float,
    dy: float,
    max_distance: float | None = None,
    dtype: type = np.float64,
    window: tuple[int, int, int, int] | None = None,
) -> np.ndarray:
    """Euclidean distance in metres from each cell centre to the nearest True cell centre.

    ``mask``: 2-D boolean (True = target, distance 0). ``dx``, ``dy``: cell width and height in
    metres. ``max_distance`` (metres) caps the result; with no True cell at all every cell gets
    ``max_distance`` (or ``inf`` when it is None). ``dtype``: float64, or float32 to halve memory on
    very large grids (about 7 significant digits). ``window`` (row, column, height, width): return only
    that part of the distances, still measured to every True cell of ``mask`` (a padded mask's inner
    grid, without a full-size output and a copy).
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"distance_m: mask must be 2-D, got shape {mask.shape}")
    if mask.dtype != np.bool_:
        raise ValueError(f"distance_m: mask must be boolean, got dtype {mask.dtype}")
    for name, value in (("dx", dx), ("dy", dy)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"distance_m: {name} must be a positive cell size in metres, got {value}")
    if max_distance is not None and not max_distance >= 0:
        raise ValueError(f"distance_m: max_distance must be >= 0 metres or None, got {max_distance}")
    if np.dtype(dtype) not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ValueError(f"distance_m: dtype must be float32 or float64, got {dtype}")
    cap = np.inf if max_distance is None else float(max_distance)
    r0, c0, h, w = (0, 0, *mask.shape) if window is None else window
    if not (min(r0, c0, h, w) >= 0 and r0 + h <= mask.shape[0] and c0 + w <= mask.shape[1]):
        raise ValueError(f"distance_m: window {window} is not inside the mask's {mask.shape}")
    out = np.empty((h, w), dtype=dtype)
    if out.size == 0 or mask.size == 0:
        return out
    # A column whose nearest target is more than cap/dy rows away is at least the cap from the cell, so
    # it is dropped like a column without targets: under a cap of fewer than 65,535 rows the offsets fit
    # uint16, half the work array (the result is the uncapped one capped, bit for bit: tested).
    rows = cap / dy
    if rows < _NONE16 - 1:
        g, limit, none = np.empty(mask.shape, dtype=np.uint16), int(np.ceil(rows)), _NONE16
    else:
        g, limit, none = np.empty(mask.shape, dtype=np.int32), _NONE - 1, _NONE
    _column_offsets(np.ascontiguousarray(mask), g, limit, none)
    _row_envelopes(g, none, float(dx), float(dy), cap, r0, c0, out)
    return out
