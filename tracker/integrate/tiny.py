"""Gaussians much smaller than a cell, in closed form: ∫ G r = Σ of the (at most four) cells' values
weighted by the Gaussian's mass in each.

As A → 0 the integral tends to r(a); at a cell edge or corner the cells around the mean share the
mass, and those shares are bivariate normal orthant probabilities. A Gaussian whose larger σ is at
most :data:`TINY` cells, centred within half a cell of its nearest grid corner, has all but Φ(-8.5)
≈ 1e-17 of its mass on the 2 × 2 cells around that corner, so

    ∫ G r = Σ_{quadrants q} r(cell q) · P(q),   P(u < cu, v < cv) = Φ₂((cu - uc)/σ_u, (cv - vc)/σ_v; ρ)

(and the reflections for the other three), ρ the u-v correlation. This is exact for every scale below
:data:`TINY` (to 1e-300 m² and beyond: no variance is squared, so nothing underflows) and every
eccentricity the checker accepts. Φ₂ comes from Sheppard's formula,

    Φ₂(x, y; ρ) = Φ(x) Φ(y) + 1/(2π) ∫_0^{arcsin ρ} exp(-(x² + y² - 2xy sin θ) / (2 cos² θ)) dθ,

by Gauss-Legendre on panels that halve their distance to π/2, so correlations near ±1 (thin tilted
Gaussians) cost a few more panels, never an unbounded number (at most :data:`_MAX_PANELS`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["FEW", "READ_SPAN", "TINY", "bvn_cdf", "few_cell_integrals", "is_few_cells", "is_tiny", "tiny_integrals"]

TINY = 0.05
"""Largest σ (cells, along the Gaussian's major axis) integrated in closed form: 8.5 σ < 0.5 cell, so
the 2 × 2 cells around the nearest corner hold all of the mass that float64 can see."""

FEW = 2.0
"""Largest σ (cells, major axis) that the terraces hand to :func:`few_cell_integrals`: a Gaussian this
small spans too few cells for concentric terraces to follow a field that jumps from cell to cell (4 %
off for r² at σ = 1 cell on a rough field), and its ±8.5 σ window is at most 35 × 35 cells."""
_WINDOW = 8.5  # σ each side: Φ(-8.5) ≈ 1e-17 of the mass lies beyond
READ_SPAN = _WINDOW
"""Both kernels read only cells within ``READ_SPAN`` σ (per axis) plus 2 cells of a Gaussian's mean."""

_GL_X, _GL_W = np.polynomial.legendre.leggauss(12)
_MAX_PANELS = 64  # the last panel ends 2^-63 rad from π/2: what lies beyond is below 1e-19


@nb.njit(cache=True, inline="always")
def _phi(x):
    """Φ(x), the standard normal CDF."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


@nb.njit(cache=True)
def bvn_cdf(x, y, rho):
    """P(X <= x, Y <= y) for standard normals with correlation ``rho`` in [-1, 1] (exact to ~1e-15)."""
    x = min(max(x, -40.0), 40.0)
    y = min(max(y, -40.0), 40.0)
    a = abs(rho)
    if a == 0.0:
        return _phi(x) * _phi(y)
    sign = 1.0 if rho > 0.0 else -1.0
    hs = 0.5 * (x * x + y * y)
    xy = sign * x * y
    # θ from 0 to arcsin|ρ| (the sign of ρ goes into xy); δ = π/2 - θ runs from π/2 down to acos|ρ|.
    end = math.acos(min(a, 1.0))
    total = 0.0
    hi = 0.5 * math.pi
    for _ in range(_MAX_PANELS):
        lo = max(0.5 * hi, end)
        mid = 0.5 * (hi + lo)
        half = 0.5 * (hi - lo)
        part = 0.0
        for i in range(_GL_X.shape[0]):
            d = mid + half * _GL_X[i]
            c = math.sin(d)  # cos θ
            s = math.cos(d)  # sin θ
            part += _GL_W[i] * math.exp((s * xy - hs) / (c * c))
        total += half * part
        if lo <= end:
            break
        hi = lo
    return _phi(x) * _phi(y) + sign * total / (2.0 * math.pi)


@nb.njit(cache=True)
def _corr(cuu, cuv, cvv):
    """(σ_u, σ_v, ρ) without multiplying variances (no underflow at 1e-300)."""
    su = math.sqrt(cuu)
    sv = math.sqrt(cvv)
    return su, sv, min(max(cuv / su / sv, -1.0), 1.0)


@nb.njit(cache=True)
def is_tiny(cuu, cuv, cvv):
    """True for Gaussians (pixel units) whose larger σ is at most :data:`TINY` cells."""
    out = np.empty(cuu.shape[0], dtype=np.bool_)
    for n in range(cuu.shape[0]):
        # The larger eigenvalue is at most cuu + cvv and at least half of it: a cheap, safe test.
        out[n] = cuu[n] + cvv[n] <= TINY * TINY
    return out


@nb.njit(cache=True, inline="always")
def _cell(field, i, j, r0, c0):
    """The value of the grid's cell at column i, row j from a field holding the cells from row r0,
    column c0 on; 0 beyond the field (off the grid, when the field holds every cell read)."""
    i -= c0
    j -= r0
    if 0 <= i < field.shape[1] and 0 <= j < field.shape[0]:
        return field[j, i]
    return 0.0


@nb.njit(cache=True)
def tiny_integrals(field, r0, c0, uc, vc, cuu, cuv, cvv):
    """∫ G r for Gaussians that pass :func:`is_tiny`: the mass-weighted values of the 2 × 2 cells
    around each mean's nearest corner (pixel units in, the field's units out). ``field`` holds the
    grid's cells from row ``r0``, column ``c0`` on (0, 0: the whole grid), at least those read."""
    out = np.empty(uc.shape[0])
    for n in range(uc.shape[0]):
        su, sv, rho = _corr(cuu[n], cuv[n], cvv[n])
        cu = math.floor(uc[n] + 0.5)
        cv = math.floor(vc[n] + 0.5)
        x = (cu - uc[n]) / su
        y = (cv - vc[n]) / sv
        i = int(cu)
        j = int(cv)
        # Each quadrant by its own orthant probability (reflections), so small shares keep their accuracy.
        out[n] = (
            _cell(field, i - 1, j - 1, r0, c0) * bvn_cdf(x, y, rho)
            + _cell(field, i, j - 1, r0, c0) * bvn_cdf(-x, y, -rho)
            + _cell(field, i - 1, j, r0, c0) * bvn_cdf(x, -y, -rho)
            + _cell(field, i, j, r0, c0) * bvn_cdf(-x, -y, rho)
        )
    return out


@nb.njit(cache=True)
def is_few_cells(cuu, cuv, cvv):
    """True for Gaussians (pixel units) whose larger σ is at most :data:`FEW` cells."""
    out = np.empty(cuu.shape[0], dtype=np.bool_)
    for n in range(cuu.shape[0]):
        half = 0.5 * (cuu[n] - cvv[n])
        out[n] = 0.5 * (cuu[n] + cvv[n]) + math.sqrt(half * half + cuv[n] * cuv[n]) <= FEW * FEW
    return out


@nb.njit(cache=True)
def few_cell_integrals(field, r0, c0, uc, vc, cuu, cuv, cvv):
    """∫ G r, exactly, for Gaussians of a few cells (:func:`is_few_cells`): Σ over the cells of the ±8.5 σ
    window of r(cell) times the Gaussian's mass in it, each mass a rectangle of Φ₂ (its four corners).
    ``field``, ``r0``, ``c0`` as in :func:`tiny_integrals`."""
    out = np.empty(uc.shape[0])
    for n in range(uc.shape[0]):
        su, sv, rho = _corr(cuu[n], cuv[n], cvv[n])
        i0 = int(math.floor(uc[n] - _WINDOW * su))
        i1 = int(math.floor(uc[n] + _WINDOW * su))
        j0 = int(math.floor(vc[n] - _WINDOW * sv))
        j1 = int(math.floor(vc[n] + _WINDOW * sv))
        # Φ₂ at the window's cell corners, then each cell's mass by inclusion-exclusion.
        corners = np.empty((j1 - j0 + 2, i1 - i0 + 2))
        for b in range(j1 - j0 + 2):
            y = (j0 + b - vc[n]) / sv
            for a in range(i1 - i0 + 2):
                corners[b, a] = bvn_cdf((i0 + a - uc[n]) / su, y, rho)
        total = 0.0
        for b in range(j1 - j0 + 1):
            for a in range(i1 - i0 + 1):
                value = _cell(field, i0 + a, j0 + b, r0, c0)
                if value != 0.0:
                    # A cell's mass is >= 0; the four-corner difference can round to -1e-27 far in a tail.
                    mass = corners[b + 1, a + 1] - corners[b, a + 1] - corners[b + 1, a] + corners[b, a]
                    total += value * max(mass, 0.0)
        out[n] = total
    return out
