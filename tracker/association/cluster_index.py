"""A persistent uniform grid over the batch chain's cluster posteriors (means b_D in m, relative to the
chain's origin), updated with only the clusters a Gibbs round changed.

It answers a coarse question: which clusters could gate a report? A pair gates when
d² = rᵀ(B_D + V_i)⁻¹r ≤ γ, which implies |r|² ≤ γ λmax(B_D + V_i) ≤ γ (λmax(B_D) + λmax(V_i)).
:meth:`ClusterIndex.candidates` returns every cluster that passes this Euclidean bound (a superset of
the gated ones); the exact test stays with the gater (:func:`tracker.gating.gate.gate_unchecked`),
so the gated pairs are the same as gating against all live clusters, at a cost that does not grow
with the number of clusters.

A cluster sits in the cell of its mean, clamped to the grid (a matrix-weighted mean may leave the
reports' bounding box; clamping is monotone, so the cell ranges of queries stay correct). Cells hold
doubly linked lists, so a move costs O(1).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_SLACK = 1e-6
"""Relative slack on the coarse radius: rounding must never drop a gated cluster."""


def lambda_max(c: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of symmetric 2×2 matrices (n,2,2), in their units (m²)."""
    a, b, d = c[:, 0, 0], 0.5 * (c[:, 0, 1] + c[:, 1, 0]), c[:, 1, 1]
    return 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)


class ClusterIndex:
    """Grid of cluster means over the box ``lo``..``hi`` (m) with square cells of ``cell`` m, for cluster
    ids 0..capacity−1. ``gamma`` is the gate on d²."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, cell: float, capacity: int, gamma: float) -> None:
        self.lo = np.asarray(lo, float)
        self.cell = float(cell)
        self.dims = np.maximum(np.ceil((np.asarray(hi, float) - self.lo) / self.cell).astype(np.int64), 1)
        self.gamma = float(gamma)
        self.head = np.full(int(self.dims[0] * self.dims[1]), -1, np.int64)
        self.nxt = np.full(capacity, -1, np.int64)
        self.prv = np.full(capacity, -1, np.int64)
        self.cell_of = np.full(capacity, -1, np.int64)
        self.mean = np.zeros((capacity, 2))
        self.lam = np.zeros(capacity)
        self.lam_max = np.zeros(1)  # max λmax(B) ever inserted: a stale (larger) value is only slower
        self.stamp = np.zeros(capacity, np.int64)
        self.round = np.zeros(1, np.int64)

    @classmethod
    def for_reports(cls, zc: np.ndarray, lam_v: np.ndarray, capacity: int, gamma: float) -> ClusterIndex:
        """An empty index over the reports' box (``zc`` (K,2) m), cells about one typical gate radius
        sqrt(γ · 2 · median λmax(V)) wide, at most about 4 cells per cluster id."""
        if zc.shape[0] == 0:
            return cls(np.zeros(2), np.ones(2), 1.0, capacity, gamma)
        lo, hi = zc.min(axis=0), zc.max(axis=0)
        cell = math.sqrt(gamma * 2.0 * float(np.median(lam_v)))
        area = float(np.prod(np.maximum(hi - lo, 1e-9)))
        cell = max(cell, math.sqrt(area / (4.0 * capacity + 16.0)), 1e-9)
        return cls(lo, hi + cell * 1e-9, cell, capacity, gamma)

    def update(self, ids: np.ndarray, means: np.ndarray, covs: np.ndarray) -> None:
        """(Re)place clusters ``ids`` with posterior means (n,2) m and covariances (n,2,2) m²."""
        if ids.size:
            _place(self.head, self.nxt, self.prv, self.cell_of, self.mean, self.lam, self.lam_max,
                   np.asarray(ids, np.int64), np.ascontiguousarray(means), lambda_max(covs),
                   self.lo, self.cell, self.dims)

    def remove(self, ids: np.ndarray) -> None:
        """Take clusters ``ids`` out (they became empty)."""
        if ids.size:
            _remove(self.head, self.nxt, self.prv, self.cell_of, np.asarray(ids, np.int64))

    def candidates(self, zc: np.ndarray, lam_v: np.ndarray) -> np.ndarray:
        """Sorted ids of the clusters with |b_D − z_i|² ≤ γ (λmax(B_D) + λmax(V_i)) for some report i
        (``zc`` (m,2) m, ``lam_v`` (m,) λmax(V_i) m²): a superset of the clusters that gate them."""
        self.round[0] += 1
        out = _candidates(self.head, self.nxt, self.mean, self.lam, self.lam_max[0], self.stamp, self.round[0],
                          np.ascontiguousarray(zc), np.ascontiguousarray(lam_v), self.gamma, self.lo, self.cell,
                          self.dims)
        out.sort()
        return out


@njit(cache=True)
def _cell(x: float, y: float, lo, cell: float, dims) -> int:
    ix = min(max(int(math.floor((x - lo[0]) / cell)), 0), dims[0] - 1)
    iy = min(max(int(math.floor((y - lo[1]) / cell)), 0), dims[1] - 1)
    return iy * dims[0] + ix


@njit(cache=True)
def _unlink(head, nxt, prv, cell_of, c: int) -> None:
    k = cell_of[c]
    if k < 0:
        return
    if prv[c] >= 0:
        nxt[prv[c]] = nxt[c]
    else:
        head[k] = nxt[c]
    if nxt[c] >= 0:
        prv[nxt[c]] = prv[c]
    nxt[c] = -1
    prv[c] = -1
    cell_of[c] = -1


@njit(cache=True)
def _remove(head, nxt, prv, cell_of, ids) -> None:
    for t in range(ids.size):
        _unlink(head, nxt, prv, cell_of, ids[t])


@njit(cache=True)
def _place(head, nxt, prv, cell_of, mean, lam, lam_max, ids, means, lams, lo, cell, dims) -> None:
    for t in range(ids.size):
        c = ids[t]
        mean[c, 0] = means[t, 0]
        mean[c, 1] = means[t, 1]
        lam[c] = lams[t]
        if lams[t] > lam_max[0]:
            lam_max[0] = lams[t]
        k = _cell(means[t, 0], means[t, 1], lo, cell, dims)
        if cell_of[c] == k:
            continue
        _unlink(head, nxt, prv, cell_of, c)
        nxt[c] = head[k]
        prv[c] = -1
        if head[k] >= 0:
            prv[head[k]] = c
        head[k] = c
        cell_of[c] = k


@njit(cache=True)
def _candidates(head, nxt, mean, lam, lam_max, stamp, rnd, zc, lam_v, gamma, lo, cell, dims):
    out = np.empty(64, np.int64)
    n = 0
    for i in range(zc.shape[0]):
        x, y = zc[i, 0], zc[i, 1]
        reach = math.sqrt(gamma * (lam_max + lam_v[i])) * (1.0 + _SLACK)
        x0 = min(max(int(math.floor((x - reach - lo[0]) / cell)), 0), dims[0] - 1)
        x1 = min(max(int(math.floor((x + reach - lo[0]) / cell)), 0), dims[0] - 1)
        y0 = min(max(int(math.floor((y - reach - lo[1]) / cell)), 0), dims[1] - 1)
        y1 = min(max(int(math.floor((y + reach - lo[1]) / cell)), 0), dims[1] - 1)
        for iy in range(y0, y1 + 1):
            for ix in range(x0, x1 + 1):
                c = head[iy * dims[0] + ix]
                while c >= 0:
                    if stamp[c] != rnd:
                        dx, dy = mean[c, 0] - x, mean[c, 1] - y
                        if dx * dx + dy * dy <= gamma * (lam[c] + lam_v[i]) * (1.0 + _SLACK) + 1e-12:
                            stamp[c] = rnd
                            if n == out.size:
                                grown = np.empty(2 * n, np.int64)
                                grown[:n] = out
                                out = grown
                            out[n] = c
                            n += 1
                    c = nxt[c]
    return out[:n]
