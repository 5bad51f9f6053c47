"""Reference integrals of Gaussians against a terrain prior: exact per-cell masses, summed densely.

Slow but independent of the terrace code (it never touches the summed-area tables): for each
Gaussian and each grid column within ``n_sigma`` standard deviations, the mass of every cell is

    P(cell) = ∫_{column} g_u(u) [Φ((v_bottom - m(u)) / s) - Φ((v_top - m(u)) / s)] du,

with g_u the marginal density in the column coordinate, m(u) and s the conditional mean and
standard deviation of the row coordinate. The inner integral over rows is exact (the normal
CDF); the outer one is Gauss-Legendre on sub-intervals aligned with the column edges and no
wider than a quarter of the Gaussian's smallest standard deviation, which makes the cell masses
accurate to about 1e-12. The integral is then Σ_cells P(cell)·r(cell) (or r(cell)²).

Units: means in metres (grid CRS), covariances in m²; the result is per m² (``squared=False``:
∫ G(y; a, A) r(y) dy) or per m⁴ (``squared=True``: ∫ G r² dy).
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from pipeline.prior import TerrainPrior
from tracker.integrate.terraces import pixel_gaussians
from tracker.types.reports import check_gaussians

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(10)


def _cell_masses(
    uc: float, vc: float, cuu: float, cuv: float, cvv: float, shape: tuple[int, int], n_sigma: float
) -> tuple[slice, slice, np.ndarray] | None:
    """Gaussian mass of each cell in the window of the grid within ``n_sigma`` of the mean."""
    h, w = shape
    su, sv = np.sqrt(cuu), np.sqrt(cvv)
    c0, c1 = max(int(np.floor(uc - n_sigma * su)), 0), min(int(np.ceil(uc + n_sigma * su)), w)
    r0, r1 = max(int(np.floor(vc - n_sigma * sv)), 0), min(int(np.ceil(vc + n_sigma * sv)), h)
    if c0 >= c1 or r0 >= r1:
        return None
    det = cuu * cvv - cuv * cuv
    sigma_min = np.sqrt(det / (0.5 * (cuu + cvv) + np.sqrt(0.25 * (cuu - cvv) ** 2 + cuv * cuv)))
    n_sub = max(int(np.ceil(4.0 / sigma_min)), 1)  # sub-intervals per column: width <= sigma_min / 4
    slope, s = cuv / cuu, np.sqrt(det / cuu)  # conditional row mean slope and standard deviation
    masses = np.zeros((r1 - r0, c1 - c0))
    # Blocks of columns keep the (nodes x rows) arrays small; rows limited to the conditional band.
    block = max(1, 200_000 // (n_sub * _GL_NODES.size * max(1, min(r1 - r0, int(2 * n_sigma * s) + 2))))
    for b0 in range(c0, c1, block):
        b1 = min(b0 + block, c1)
        edges = b0 + np.arange((b1 - b0) * n_sub + 1) / n_sub
        lo, hi = edges[:-1, None], edges[1:, None]
        u = (0.5 * (lo + hi) + 0.5 * (hi - lo) * _GL_NODES).ravel()
        wts = (0.5 * (hi - lo) * _GL_WEIGHTS).ravel()
        col = np.repeat(b0 + np.arange((b1 - b0) * n_sub) // n_sub, _GL_NODES.size) - c0
        du = u - uc
        g_u = np.exp(-0.5 * du * du / cuu) / np.sqrt(2.0 * np.pi * cuu)
        m = vc + slope * du
        j0 = max(int(np.floor(m.min() - n_sigma * s)), r0)
        j1 = min(int(np.ceil(m.max() + n_sigma * s)), r1)
        if j0 >= j1:
            continue
        rows = np.arange(j0, j1 + 1, dtype=np.float64)
        cdf = ndtr((rows[None, :] - m[:, None]) / s)
        per_node = np.diff(cdf, axis=1) * (g_u * wts)[:, None]  # (nodes, rows)
        np.add.at(masses[j0 - r0 : j1 - r0].T, col, per_node)
    return slice(r0, r1), slice(c0, c1), masses


def reference_integrate(
    prior: TerrainPrior,
    means: np.ndarray,
    covs: np.ndarray,
    squared: bool = False,
    n_sigma: float = 8.0,
) -> np.ndarray:
    """∫ G(y; a_n, A_n) r(y) dy (per m²), or of r² (per m⁴), for each of N 2-D Gaussians, by dense per-cell masses."""
    means, covs = check_gaussians(means, covs, "reference_integrate")
    if means.shape[1] != 2:
        raise ValueError(f"reference_integrate: Gaussians must be 2-D, got dimension {means.shape[1]}")
    field = prior.density * prior.density if squared else prior.density
    out = np.zeros(means.shape[0])
    for n, params in enumerate(zip(*pixel_gaussians(prior, means, covs), strict=True)):
        window = _cell_masses(*params, prior.grid.shape, n_sigma)
        if window is not None:
            rows, cols, masses = window
            out[n] = float(np.sum(masses * field[rows, cols]))
    return out


def covered_mass(prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, n_sigma: float = 8.0) -> np.ndarray:
    """Gaussian probability mass falling on the grid, for each of N Gaussians (dimensionless)."""
    means, covs = check_gaussians(means, covs, "covered_mass")
    out = np.zeros(means.shape[0])
    for n, params in enumerate(zip(*pixel_gaussians(prior, means, covs), strict=True)):
        window = _cell_masses(*params, prior.grid.shape, n_sigma)
        if window is not None:
            out[n] = float(window[2].sum())
    return out
