"""Kernel density of past points: on the grid (the hybrid's spatial feature) and scikit-learn's
KernelDensity with its bandwidth chosen by spatial block cross-validation (the baseline)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from sklearn.model_selection import GridSearchCV, GroupKFold
from sklearn.neighbors import KernelDensity

from pipeline.gis.grid import Grid

KDE_EPS = 1e-6
"""Added to the KDE ratio k before its log, so the feature is finite where the kernel is truncated."""
TRUNCATE = 4.0
"""Gaussian kernel truncated at this many bandwidths."""


def cell_counts(grid: Grid, points: np.ndarray) -> np.ndarray:
    """Points per cell (H, W); points off the grid are left out."""
    row, col, ok = grid.cell_index(points[:, 0], points[:, 1])
    flat = row[ok] * grid.width + col[ok]
    return np.bincount(flat, minlength=grid.height * grid.width).reshape(grid.shape).astype(np.float64)


def _kernel_1d(sigma_px: float) -> np.ndarray:
    """scipy's truncated, normalised 1-D Gaussian weights for offsets −R..R cells."""
    radius = int(TRUNCATE * sigma_px + 0.5)
    impulse = np.zeros(2 * radius + 1)
    impulse[radius] = 1.0
    return ndimage.gaussian_filter1d(impulse, sigma_px, mode="constant", truncate=TRUNCATE)


def grid_kde(grid: Grid, points: np.ndarray, bandwidth: float) -> np.ndarray:
    """Gaussian KDE (density per m², points snapped to cell centres) on the grid; ``bandwidth`` in metres."""
    if not bandwidth > 0:
        raise ValueError(f"KDE bandwidth must be > 0 metres, got {bandwidth}")
    counts = cell_counts(grid, points)
    n = counts.sum()
    if n == 0:
        raise ValueError("grid_kde: no points on the grid")
    return ndimage.gaussian_filter(counts, bandwidth / grid.dx, mode="constant", truncate=TRUNCATE) / (n * grid.cell_area)


def _own_group_mass(grid: Grid, points: np.ndarray, groups: np.ndarray, bandwidth: float) -> np.ndarray:
    """For each point, Σ over points j of its own group of the grid-kernel weight j puts on its cell."""
    w1 = _kernel_1d(bandwidth / grid.dx)
    radius = len(w1) // 2
    u, v = grid.to_pixel(points[:, 0], points[:, 1])
    col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    out = np.zeros(len(points))
    order = np.argsort(groups, kind="stable")
    bounds = np.flatnonzero(np.diff(groups[order])) + 1
    for members in np.split(order, bounds):
        for start in range(0, len(members), 1024):  # bounded memory for large groups
            rows_ = members[start : start + 1024]
            dc = np.abs(col[rows_][:, None] - col[members][None, :])
            dr = np.abs(row[rows_][:, None] - row[members][None, :])
            near = (dc <= radius) & (dr <= radius)
            wts = np.where(near, w1[np.minimum(dc, radius) + radius] * w1[np.minimum(dr, radius) + radius], 0.0)
            out[rows_] = wts.sum(axis=1)
    return out


def log_kde_feature(
    grid: Grid, points: np.ndarray, bandwidth: float, groups: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """log(k + KDE_EPS) on the grid, k = grid KDE × grid area (the KDE over the uniform density),
    and the same at each point from the points *outside its group* (each point its own group when
    ``groups`` is None: leave-one-out).

    The hybrid's parameters are fitted on those held-out values: how well other points (other
    blocks, under spatial block CV) predict each one; the full KDE at a point's own cell would
    reward the spatial term for the point's own kernel.
    """
    if groups is None:
        groups = np.arange(len(points))
    dens = grid_kde(grid, points, bandwidth)
    n = len(points)
    area = grid.width * grid.height * grid.cell_area
    u, v = grid.to_pixel(points[:, 0], points[:, 1])
    at = dens[v.astype(np.intp), u.astype(np.intp)]
    _, inv, size = np.unique(groups, return_inverse=True, return_counts=True)
    others = n - size[inv]
    own = _own_group_mass(grid, points, groups, bandwidth) / grid.cell_area
    held = np.where(others > 0, np.clip(n * at - own, 0.0, None) / np.maximum(others, 1), 0.0)
    return np.log(dens * area + KDE_EPS), np.log(held * area + KDE_EPS)


def block_ids(points: np.ndarray, origin: tuple[float, float], block_size: float) -> np.ndarray:
    """Integer id of the square block (side ``block_size`` metres from ``origin``) holding each point."""
    bx = np.floor((points[:, 0] - origin[0]) / block_size).astype(np.int64)
    by = np.floor((points[:, 1] - origin[1]) / block_size).astype(np.int64)
    return bx * 1_000_003 + by


def block_folds(points: np.ndarray, origin: tuple[float, float], block_size: float, n_folds: int) -> np.ndarray:
    """Fold id (0..n_folds-1) of each point: whole blocks per fold, as scikit-learn's GroupKFold
    deals them (fewer folds when fewer blocks hold points)."""
    groups = block_ids(points, origin, block_size)
    k = min(n_folds, len(np.unique(groups)))
    fold = np.zeros(len(points), dtype=np.int64)
    if k < 2:
        return fold
    for f, (_, test) in enumerate(GroupKFold(n_splits=k).split(points, groups=groups)):
        fold[test] = f
    return fold


def fit_kde_cv(
    points: np.ndarray, groups: np.ndarray, bandwidths: np.ndarray, n_splits: int = 4
) -> KernelDensity:
    """scikit-learn KernelDensity (Gaussian) with the bandwidth (metres) maximising the held-out
    log-likelihood over block folds (``groups`` = block ids), refitted on all points."""
    n_splits = min(n_splits, len(np.unique(groups)))
    if n_splits < 2:
        raise ValueError("KDE bandwidth CV needs points in at least two blocks")
    search = GridSearchCV(KernelDensity(kernel="gaussian"), {"bandwidth": list(bandwidths)}, cv=GroupKFold(n_splits))
    search.fit(points, groups=groups)
    return search.best_estimator_
