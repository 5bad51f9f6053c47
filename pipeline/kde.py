"""Kernel density of past points: on the grid (the hybrid's spatial feature) and scikit-learn's
KernelDensity with its bandwidth chosen by spatial block cross-validation (the baseline)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from sklearn.model_selection import GridSearchCV, GroupKFold
from sklearn.neighbors import KernelDensity

from pipeline.grid import Grid

FLOOR_SHARE = 0.01
"""The grid KDE is mixed with this share of the uniform density so its log is finite everywhere."""
TRUNCATE = 4.0
"""Gaussian kernel truncated at this many bandwidths."""


def cell_counts(grid: Grid, points: np.ndarray) -> np.ndarray:
    """Points per cell (H, W); points off the grid are left out."""
    u, v = grid.to_pixel(points[:, 0], points[:, 1])
    ok = (u >= 0) & (u < grid.width) & (v >= 0) & (v < grid.height)
    flat = v[ok].astype(np.intp) * grid.width + u[ok].astype(np.intp)
    return np.bincount(flat, minlength=grid.height * grid.width).reshape(grid.shape).astype(np.float64)


def _centre_weight(sigma_px: float) -> float:
    """Weight a unit point puts on its own cell under scipy's truncated, normalised Gaussian filter."""
    radius = int(TRUNCATE * sigma_px + 0.5)
    impulse = np.zeros(2 * radius + 1)
    impulse[radius] = 1.0
    return float(ndimage.gaussian_filter1d(impulse, sigma_px, mode="constant", truncate=TRUNCATE)[radius] ** 2)


def grid_kde(grid: Grid, points: np.ndarray, bandwidth: float) -> tuple[np.ndarray, float]:
    """Gaussian KDE (density per m², points snapped to cell centres) on the grid, and the density
    each point adds at its own cell (for leave-one-out values). ``bandwidth`` in metres."""
    if not bandwidth > 0:
        raise ValueError(f"KDE bandwidth must be > 0 metres, got {bandwidth}")
    counts = cell_counts(grid, points)
    n = counts.sum()
    if n == 0:
        raise ValueError("grid_kde: no points on the grid")
    sigma = bandwidth / grid.dx
    dens = ndimage.gaussian_filter(counts, sigma, mode="constant", truncate=TRUNCATE) / (n * grid.cell_area)
    return dens, _centre_weight(sigma) / (n * grid.cell_area)


def log_kde_feature(grid: Grid, points: np.ndarray, bandwidth: float) -> tuple[np.ndarray, np.ndarray]:
    """log of the floored grid KDE on the grid (log per m²) and its leave-one-out value at each point.

    The leave-one-out value removes the point's own kernel, so the hybrid's exponent is fitted on
    how well the *other* points predict each one (otherwise it rewards bandwidth → 0).
    """
    dens, self_w = grid_kde(grid, points, bandwidth)
    n = len(points)
    floor = FLOOR_SHARE / (grid.width * grid.height * grid.cell_area)
    u, v = grid.to_pixel(points[:, 0], points[:, 1])
    ok = (u >= 0) & (u < grid.width) & (v >= 0) & (v < grid.height)
    at = np.zeros(n)
    at[ok] = dens[v[ok].astype(np.intp), u[ok].astype(np.intp)]
    loo = np.clip((n * at - n * self_w) / max(n - 1, 1), 0.0, None)
    return np.log((1 - FLOOR_SHARE) * dens + floor), np.log((1 - FLOOR_SHARE) * loo + floor)


def block_ids(points: np.ndarray, origin: tuple[float, float], block_size: float) -> np.ndarray:
    """Integer id of the square block (side ``block_size`` metres from ``origin``) holding each point."""
    bx = np.floor((points[:, 0] - origin[0]) / block_size).astype(np.int64)
    by = np.floor((points[:, 1] - origin[1]) / block_size).astype(np.int64)
    return bx * 1_000_003 + by


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
