"""A persistent uniform grid over the batch chain's cluster posteriors (means b_D in m, relative to the
chain's origin), updated with only the clusters a Gibbs round changed.

It answers which clusters gate a report. A pair gates when d² = rᵀ(B_D + V_i)⁻¹r ≤ γ, which implies
|r|² ≤ γ λmax(B_D + V_i) ≤ γ (λmax(B_D) + λmax(V_i)). :meth:`ClusterIndex.gated` visits the cells
within that Euclidean bound and applies the gater's own exact test
(:func:`tracker.gating.exact.sym_d2_logdet`, the arithmetic of :func:`tracker.gating.gate.gate_unchecked`)
in the same pass, so the gated pairs are those of gating against all live clusters, at a cost that
does not grow with the number of clusters. Each report's pairs come out sorted by cluster id.

A cluster sits in the cell of its mean, clamped to the grid (a matrix-weighted mean may leave the
reports' bounding box; clamping is monotone, so the cell ranges of queries stay correct). Cells hold
doubly linked lists, so a move costs O(1).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tracker.association.cell_lists import relink, unlink
from tracker.gating.exact import sym_d2_logdet

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
        self.cov = np.zeros((capacity, 3))  # B00, B01, B11 (m²) for the exact test
        self.lam = np.zeros(capacity)
        self.lam_max = np.zeros(1)  # max λmax(B) ever inserted: a stale (larger) value is only slower

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
            ids = np.asarray(ids, np.int64)
            self.cov[ids] = covs[:, [0, 0, 1], [0, 1, 1]]
            _place(self.head, self.nxt, self.prv, self.cell_of, self.mean, self.lam, self.lam_max,
                   ids, np.ascontiguousarray(means), lambda_max(covs), self.lo, self.cell, self.dims)

    def remove(self, ids: np.ndarray) -> None:
        """Take clusters ``ids`` out (they became empty)."""
        if ids.size:
            _remove(self.head, self.nxt, self.prv, self.cell_of, np.asarray(ids, np.int64))

    def gated(self, zc: np.ndarray, V: np.ndarray, lam_v: np.ndarray, skip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gated pairs of reports (``zc`` (m,2) m, ``V`` (m,2,2) m², ``lam_v`` (m,) λmax(V_i) m²) with the
        live clusters: d² of z_i − b_D under B_D + V_i ≤ γ, leaving out cluster ``skip[i]`` of report i.
        Returns CSR ``ptr`` (m+1,) and cluster ids (ptr[-1],), each report's ids ascending."""
        return _gated(self.head, self.nxt, self.mean, self.cov, self.lam, self.lam_max[0], np.ascontiguousarray(zc),
                      np.ascontiguousarray(V), np.ascontiguousarray(lam_v), np.asarray(skip, np.int64), self.gamma,
                      self.lo, self.cell, self.dims)


@njit(cache=True)
def _cell(x: float, y: float, lo, cell: float, dims) -> int:
    ix = min(max(int(math.floor((x - lo[0]) / cell)), 0), dims[0] - 1)
    iy = min(max(int(math.floor((y - lo[1]) / cell)), 0), dims[1] - 1)
    return iy * dims[0] + ix


@njit(cache=True)
def _remove(head, nxt, prv, cell_of, ids) -> None:
    for t in range(ids.size):
        unlink(head, nxt, prv, cell_of, ids[t])


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
        relink(head, nxt, prv, cell_of, c, k)


@njit(cache=True)
def _gated(head, nxt, mean, cov, lam, lam_max, zc, V, lam_v, skip, gamma, lo, cell, dims):
    m = zc.shape[0]
    ptr = np.zeros(m + 1, np.int64)
    out = np.empty(max(4 * m, 16), np.int64)
    n = 0
    for i in range(m):
        x, y = zc[i, 0], zc[i, 1]
        v00, v01, v11 = V[i, 0, 0], V[i, 0, 1], V[i, 1, 1]
        reach = math.sqrt(gamma * (lam_max + lam_v[i])) * (1.0 + _SLACK)
        x0 = min(max(int(math.floor((x - reach - lo[0]) / cell)), 0), dims[0] - 1)
        x1 = min(max(int(math.floor((x + reach - lo[0]) / cell)), 0), dims[0] - 1)
        y0 = min(max(int(math.floor((y - reach - lo[1]) / cell)), 0), dims[1] - 1)
        y1 = min(max(int(math.floor((y + reach - lo[1]) / cell)), 0), dims[1] - 1)
        for iy in range(y0, y1 + 1):
            for ix in range(x0, x1 + 1):
                c = head[iy * dims[0] + ix]
                while c >= 0:
                    dx, dy = x - mean[c, 0], y - mean[c, 1]
                    if c != skip[i] and dx * dx + dy * dy <= gamma * (lam[c] + lam_v[i]) * (1.0 + _SLACK) + 1e-12:
                        d2, _ = sym_d2_logdet(cov[c, 0] + v00, cov[c, 1] + v01, 0.0, cov[c, 2] + v11, 0.0, 0.0,
                                              dx, dy, 0.0, 2, False)
                        if d2 <= gamma:
                            if n == out.size:
                                grown = np.empty(2 * n, np.int64)
                                grown[:n] = out
                                out = grown
                            out[n] = c
                            n += 1
                    c = nxt[c]
        for a in range(ptr[i] + 1, n):  # insertion sort: a report gates a few clusters
            v = out[a]
            b = a - 1
            while b >= ptr[i] and out[b] > v:
                out[b + 1] = out[b]
                b -= 1
            out[b + 1] = v
        ptr[i + 1] = n
    return ptr, out[:n]
