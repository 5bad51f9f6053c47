"""Gaussian-terrace integration of 2-D Gaussians against a terrain prior (paper 1, appendix A).

``integrate(prior, means, covs)`` returns ∫ G(y; a_n, A_n) r(y) dy for a batch of Gaussians, in
per m² (G is a density per m², r a density per m²); ``squared=True`` returns ∫ G r² dy in per m⁴.
The cost per Gaussian is ``n_terraces × n_strips`` summed-area-table rectangles whatever its spread.

The Gaussian is replaced by a stack of concentric elliptical terraces (its constant-density
contours at Mahalanobis radii ρ_1 < … < ρ_K): a step function, constant on each ring. Writing
R(ρ) = ∫_{ellipse ρ} r dy, the stack gives Σ_k c_k R(ρ_k) (each ellipse's sum enters with its
terrace height minus the next one's: "inner ellipse subtracted, times the terrace height").
Each ellipse sum R(ρ) is the sum of ``n_strips`` vertical strips read from the summed-area table
with fractional edges; each strip is the rectangle with the strip's exact ellipse area (the
strip-vs-ellipse area correction) centred on the strip's area centroid, so a prior that is
linear across the ellipse is integrated exactly.

Where this differs from the paper (the accuracy study in docs/terrace.md says why): the paper's
terraces hold equal mass shares up to 99 % of the mass. Equal shares make the outer terraces very
wide, and the 1 % left over is large next to a 0.1 % goal: a grid edge or a lake 1σ from the
mean is then missed by 1-4 %. Here the radii are equally spaced in ρ up to the ellipse holding
``mass`` (default 1 - 1e-6) and the heights are the trapezoid rule of the layer-cake identity

    ∫ G r dy = ∫_0^∞ R(ρ) ρ e^{-ρ²/2} dρ / (2π √det A),

scaled so that a constant prior gives exactly the covered mass. The rest (1 - ``mass``) is
corrected for by the tail mass times the mean density of the outermost ring. With
``n_terraces`` and ``mass`` set to the paper's values (``radii="equal-mass"``), the paper's scheme is
reproduced for comparison.
"""

from __future__ import annotations

from typing import Literal

import numba as nb
import numpy as np

from pipeline.prior import TerrainPrior, sat_rect
from tracker.reports import check_gaussians

N_TERRACES = 16
"""Default number of terraces (ellipses), from the accuracy study in docs/terrace.md."""
N_STRIPS = 8
"""Default (minimum) number of vertical strips per ellipse."""
SHEAR = 2.0
"""Default strips per unit of shear κ (see :func:`n_strips_for`)."""
MASS = 1.0 - 1e-6
"""Default Gaussian mass inside the outermost ellipse."""


def terrace_rule(
    n_terraces: int, mass: float, radii: Literal["equal-width", "equal-mass"] = "equal-width"
) -> tuple[np.ndarray, np.ndarray]:
    """Mahalanobis radii ρ_k (K,) and coefficients c_k (K,) with ∫ G r ≈ Σ_k c_k R(ρ_k) / √det A.

    R(ρ) is the prior mass inside the ellipse of radius ρ; a constant prior r0 gives
    Σ_k c_k π ρ_k² r0 = ``mass`` · r0 before the tail correction, and r0 after it.
    ``equal-width``: trapezoid rule on equally spaced radii; ``equal-mass``: the paper's terraces,
    each holding ``mass / n_terraces``, with heights from their mass.
    """
    if not (isinstance(n_terraces, int | np.integer) and n_terraces >= 2):
        raise ValueError(f"n_terraces must be an integer >= 2, got {n_terraces!r}")
    if not 0.0 < mass < 1.0:
        raise ValueError(f"mass must be in (0, 1), got {mass!r}")
    k = np.arange(1, n_terraces + 1)
    if radii == "equal-width":
        rho_max = np.sqrt(-2.0 * np.log1p(-mass))
        rho = rho_max * k / n_terraces
        w = rho * np.exp(-0.5 * rho * rho)
        w[-1] *= 0.5
        coef = w * mass / np.sum(w * np.pi * rho * rho)
    elif radii == "equal-mass":
        rho = np.sqrt(-2.0 * np.log1p(-mass * k / n_terraces))
        area = np.pi * rho * rho
        height = (mass / n_terraces) / np.diff(area, prepend=0.0)
        coef = height - np.append(height[1:], 0.0)
    else:
        raise ValueError(f"radii must be 'equal-width' or 'equal-mass', got {radii!r}")
    # The tail (1 - mass) at the mean density of the outermost ring, R(ρ_K) - R(ρ_{K-1}).
    tail = (1.0 - mass) / (np.pi * (rho[-1] ** 2 - rho[-2] ** 2))
    coef[-1] += tail
    coef[-2] -= tail
    return rho, coef



def pixel_gaussians(prior: TerrainPrior, means: np.ndarray, covs: np.ndarray):
    """Means and covariances in fractional pixel coordinates (u = column, v = row, rows grow southward).

    Returns (uc, vc, cuu, cuv, cvv) as (N,) arrays; the y flip makes the u-v covariance the
    negative of the x-y covariance divided by the cell sizes.
    """
    g = prior.grid
    uc, vc = g.to_pixel(means[:, 0], means[:, 1])
    cuu = covs[:, 0, 0] / (g.dx * g.dx)
    cvv = covs[:, 1, 1] / (g.dy * g.dy)
    cuv = -0.5 * (covs[:, 0, 1] + covs[:, 1, 0]) / (g.dx * g.dy)
    return uc, vc, cuu, cuv, cvv




def n_strips_for(cuu: np.ndarray, cuv: np.ndarray, cvv: np.ndarray, n_strips: int, shear: float) -> np.ndarray:
    """Strips per ellipse: ``n_strips``, raised for sheared ellipses so each strip's drift stays small.

    A vertical strip of a tilted ellipse is a parallelogram; the rectangle standing in for it is
    off by the parallelogram's vertical drift across the strip, which relative to the strip's
    height is about κ/S with κ = |ρ_uv|/√(1-ρ_uv²) (ρ_uv the correlation). S = ⌈shear·κ⌉ keeps
    that near 1/shear. κ depends on orientation and eccentricity only (at most (e - 1/e)/2 for an
    e:1 ellipse), never on the spread, so the cost stays flat in the spread.
    """
    if not (isinstance(n_strips, int | np.integer) and n_strips >= 1):
        raise ValueError(f"n_strips must be an integer >= 1, got {n_strips!r}")
    if not shear >= 0:
        raise ValueError(f"shear must be >= 0, got {shear!r}")
    kappa = np.abs(cuv) / np.sqrt(cuu * cvv - cuv * cuv)
    return np.maximum(n_strips, np.ceil(shear * kappa)).astype(np.int64)


@nb.njit(cache=True, inline="always")
def _strip_geometry(n: int, t: np.ndarray, tbar: np.ndarray, eta: np.ndarray) -> None:
    """Strips of the unit circle cut at u = sin θ_i, θ equally spaced over [-π/2, π/2].

    Fills edges t[:n+1], area centroids tbar[:n] and half-heights eta[:n] of the rectangles with
    each strip's exact area. Equal angles put the narrow strips where the boundary is steep.
    """
    s0 = -1.0
    a0 = -0.5 * np.pi  # θ + sinθ cosθ: the area of the unit circle left of u = sin θ, times 2
    m0 = 0.0  # -2/3 cos³θ: the first moment in u of that area
    t[0] = -1.0
    for i in range(n):
        th1 = -0.5 * np.pi + np.pi * (i + 1) / n
        s1, c1 = (1.0, 0.0) if i == n - 1 else (np.sin(th1), np.cos(th1))
        a1 = th1 + s1 * c1
        m1 = -2.0 / 3.0 * c1 * c1 * c1
        t[i + 1] = s1
        tbar[i] = (m1 - m0) / (a1 - a0)
        eta[i] = (a1 - a0) / (2.0 * (s1 - s0))
        s0, a0, m0 = s1, a1, m1


@nb.njit(cache=True, parallel=True)
def _terrace_kernel(sat, uc, vc, cuu, cuv, cvv, strips, rho, coef, out):
    h = float(sat.shape[0] - 1)
    w = float(sat.shape[1] - 1)
    rho_max = rho[rho.shape[0] - 1]
    s_max = strips.max() if strips.shape[0] else 1
    for n in nb.prange(uc.shape[0]):
        su = np.sqrt(cuu[n])
        sd = np.sqrt(cuu[n] * cvv[n] - cuv[n] * cuv[n])
        # Skip Gaussians whose outermost ellipse misses the grid (the prior is zero there).
        eu = rho_max * su
        ev = rho_max * np.sqrt(cvv[n])
        if uc[n] + eu <= 0.0 or uc[n] - eu >= w or vc[n] + ev <= 0.0 or vc[n] - ev >= h:
            out[n] = 0.0
            continue
        ns = strips[n]
        t = np.empty(s_max + 1)
        tbar = np.empty(s_max)
        eta = np.empty(s_max)
        _strip_geometry(ns, t, tbar, eta)
        slope = cuv[n] / cuu[n]
        half = sd / su  # half-height of the unit ellipse at its centre column
        acc = 0.0
        for k in range(rho.shape[0]):
            width = rho[k] * su
            shift = slope * width
            height = rho[k] * half
            total = 0.0
            u0 = uc[n] - width
            for i in range(ns):
                u1 = uc[n] + width * t[i + 1]
                vm = vc[n] + shift * tbar[i]
                hh = height * eta[i]
                total += sat_rect(sat, u0, u1, vm - hh, vm + hh)
                u0 = u1
            acc += coef[k] * total
        out[n] = acc / sd


def integrate(
    prior: TerrainPrior,
    means: np.ndarray,
    covs: np.ndarray,
    squared: bool = False,
    *,
    n_terraces: int = N_TERRACES,
    n_strips: int = N_STRIPS,
    mass: float = MASS,
    shear: float = SHEAR,
    radii: Literal["equal-width", "equal-mass"] = "equal-width",
) -> np.ndarray:
    """∫ G(y; a_n, A_n) r(y) dy per m² (or ∫ G r² dy per m⁴ when ``squared``) for N 2-D Gaussians.

    ``means`` (N, 2) metres in the prior's CRS, ``covs`` (N, 2, 2) m². The prior is zero off its
    grid, so Gaussians partly or wholly off the grid are fine. Raises ``ValueError`` naming the
    indices of non-finite means or covariances that are not symmetric positive definite.
    ``shear = 0`` fixes the strips at ``n_strips`` (the paper's scheme).
    """
    means, covs = check_gaussians(means, covs, "integrate")
    if means.shape[1] != 2:
        raise ValueError(f"integrate: Gaussians must be 2-D, got dimension {means.shape[1]}")
    rho, coef = terrace_rule(n_terraces, mass, radii)
    uc, vc, cuu, cuv, cvv = pixel_gaussians(prior, means, covs)
    strips = n_strips_for(cuu, cuv, cvv, n_strips, shear)
    out = np.empty(means.shape[0])
    sat = np.asarray(prior.sat2 if squared else prior.sat)
    _terrace_kernel(sat, uc, vc, cuu, cuv, cvv, strips, rho, coef, out)
    # The kernel works in pixels: Σ mass / √det(pixel²) is per pixel area; divide by its m².
    return out / prior.grid.cell_area
