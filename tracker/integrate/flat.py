"""Integrals where the prior is flat under the Gaussian (paper 1, section 8: "a hybrid approach", the
prior's cost spent only where it helps).

The prior's grid is cut into tiles of ``TILE`` × ``TILE`` cells holding the least and largest r of
their cells (built once per prior). For a Gaussian G(a, A) take the axis-aligned box a ± K·σ (σ the
marginal standard deviations, K = ``K_SIGMA``), which holds all but T = 4Φ(-K) < 4·10⁻⁹ of its mass.
If the box lies on the grid and r_lo, r_hi bound r over the tiles it touches, then

    r_lo (1 - T) <= ∫ G r <= r_hi + r_max T        (r_max the prior's largest value)

so v̂ = (r_lo + r_hi)/2 is within e = (r_hi - r_lo)/2 + r_max T of the true integral. Where
e <= ``tol`` · v̂ the Gaussian is *flat*: its integral is v̂, with relative error at most ``tol``
against the exact integral (not against an integrator's own approximation of it). Squared (∫ G r²)
uses the tiles' r² bounds. The test costs a few tile look-ups; every other Gaussian goes to the
exact integrator.
"""

from __future__ import annotations

import math
import weakref
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from pipeline.prior import TerrainPrior
from tracker.integrate.terraces import pixel_gaussians

TILE = 8
"""Cells per tile side."""
STRIP_CELLS = 1 << 22
"""Cells of the density read at a time while the tile bounds are made."""
K_SIGMA = 6.0
"""Half-width of the Gaussian's box, in marginal standard deviations."""
TAIL = 4.0 * 0.5 * math.erfc(K_SIGMA / math.sqrt(2.0))
"""Mass of a 2-D Gaussian outside its box: P(|x| > Kσ_x or |y| > Kσ_y) <= 4Φ(-K) ≈ 3.9e-9."""
MAX_TILES = 64
"""Tiles a box may touch (per axis: 8) before the test gives up (wide Gaussians go to the exact integrator)."""
DEFAULT_TOL = 1e-4
"""Default relative error bound of a flat integral."""


class Tiles(NamedTuple):
    """Least (``lo``) and largest (``hi``) prior value of each tile (rows, columns of tiles), the
    prior's largest value ``r_max`` and the grid's shape (rows, columns) in cells."""

    lo: np.ndarray
    hi: np.ndarray
    r_max: float
    shape: tuple[int, int]


_TILES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def tiles(prior: TerrainPrior, squared: bool = False) -> Tiles:
    """The prior's tile bounds of r (or r², ``squared``), once per prior object."""
    cache = _TILES.setdefault(prior, {})
    if squared not in cache:
        h, w = prior.density.shape
        th, tw = -(-h // TILE), -(-w // TILE)
        lo, hi = np.empty((th, tw)), np.empty((th, tw))
        rows = TILE * max(1, STRIP_CELLS // (TILE * max(w, 1)))
        for r0 in range(0, h, rows):  # bands of tile rows: a windowed density is never read whole
            r = np.asarray(prior.density[r0 : r0 + rows, 0:w], dtype=np.float64)
            padded = np.full((-(-r.shape[0] // TILE) * TILE, tw * TILE), np.nan)
            padded[: r.shape[0], :w] = r * r if squared else r
            blocks = padded.reshape(-1, TILE, tw, TILE)
            t0 = r0 // TILE
            lo[t0 : t0 + blocks.shape[0]], hi[t0 : t0 + blocks.shape[0]] = np.nanmin(blocks, axis=(1, 3)), np.nanmax(blocks, axis=(1, 3))
        cache[squared] = Tiles(lo, hi, float(hi.max()) if hi.size else 0.0, (h, w))
    return cache[squared]


@njit(cache=True, parallel=True)
def flat_values(lo, hi, r_max, h, w, uc, vc, cuu, cvv, tol, out):
    """v̂ of each Gaussian (pixel units: centres uc, vc; variances cuu, cvv) into ``out`` where it is
    flat within ``tol``; returns the mask of those (see the module doc)."""
    n = uc.shape[0]
    flat = np.zeros(n, np.bool_)
    for i in prange(n):
        du, dv = K_SIGMA * math.sqrt(cuu[i]), K_SIGMA * math.sqrt(cvv[i])
        u0, u1, v0, v1 = uc[i] - du, uc[i] + du, vc[i] - dv, vc[i] + dv
        if not (u0 >= 0.0 and v0 >= 0.0 and u1 < w and v1 < h):
            continue  # off the grid the prior is 0: not flat
        tu0, tu1 = int(u0) // TILE, int(u1) // TILE
        tv0, tv1 = int(v0) // TILE, int(v1) // TILE
        if (tu1 - tu0 + 1) * (tv1 - tv0 + 1) > MAX_TILES:
            continue
        r_lo, r_hi = np.inf, 0.0
        for tv in range(tv0, tv1 + 1):
            for tu in range(tu0, tu1 + 1):
                r_lo = min(r_lo, lo[tv, tu])
                r_hi = max(r_hi, hi[tv, tu])
        est = 0.5 * (r_lo + r_hi)
        if r_lo > 0.0 and 0.5 * (r_hi - r_lo) + r_max * TAIL <= tol * est:
            out[i] = est
            flat[i] = True
    return flat


class FlatIntegrator:
    """An :class:`~tracker.integrate.Integrator`: flat Gaussians (see the module doc) get v̂, within
    relative error ``tol`` of the exact integral; the others go to ``exact`` (default
    :func:`tracker.integrate.integrate_checked`). Counts ``n_flat`` and ``n_exact`` Gaussians."""

    def __init__(self, tol: float = DEFAULT_TOL, exact=None) -> None:
        if not 0.0 < tol < 1.0:
            raise ValueError(f"FlatIntegrator: tol must be in (0, 1), got {tol!r}")
        if exact is None:
            from tracker.integrate import integrate_checked as exact
        self.tol = float(tol)
        self.exact = exact
        self.n_flat = 0
        self.n_exact = 0

    def __call__(self, prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, squared: bool = False) -> np.ndarray:
        out = np.empty(means.shape[0])
        if not means.shape[0]:
            return out
        tb = tiles(prior, squared)
        uc, vc, cuu, _, cvv = pixel_gaussians(prior, means, covs)
        flat = flat_values(tb.lo, tb.hi, tb.r_max, tb.shape[0], tb.shape[1], uc, vc, cuu, cvv, self.tol, out)
        rest = np.flatnonzero(~flat)
        if rest.size:
            out[rest] = self.exact(prior, means[rest], covs[rest], squared)
        self.n_exact += rest.size
        self.n_flat += means.shape[0] - rest.size
        return out
