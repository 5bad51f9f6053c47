"""Integrals of 2-D Gaussians against a terrain prior: ∫ G(y; a_n, A_n) r(y) dy per m², or ∫ G r² dy per m⁴.

:func:`integrate` is the public entry: it validates the Gaussians (one pass of
:func:`tracker.types.reports.check_gaussians`) and calls :func:`integrate_checked`, the path for arrays
already checked (a :class:`~tracker.types.reports.Reports` batch, or Gaussian products of checked
Gaussians), which the association and the metrics call many times per batch. By default both use the
prior's Gaussian pyramid (:mod:`tracker.integrate.scalespace`, ~30 look-ups per integral) and the
terraces (:mod:`tracker.integrate.terraces`) for the Gaussians the pyramid is not made for;
``method="terraces"`` uses the terraces throughout. :mod:`tracker.integrate.reference` is the slow,
independent dense reference. Anything the tracker or the metrics call to integrate is an
:class:`Integrator`.
"""

from __future__ import annotations

import warnings
from typing import Literal, Protocol

import numpy as np

from pipeline.prior import TerrainPrior
from tracker.integrate import scalespace
from tracker.integrate.lazy import lazy_pyramid, window_groups
from tracker.integrate.reference import covered_mass, reference_integrate
from tracker.integrate.terraces import (
    MASS,
    MAX_STRIPS,
    N_STRIPS,
    N_TERRACES,
    SHEAR,
    integrate_terraces,
    near_grid,
    pixel_gaussians,
)
from tracker.integrate.tiny import (
    READ_SPAN,
    TINY,
    few_cell_integrals,
    is_few_cells,
    is_tiny,
    tiny_integrals,
)
from tracker.types.reports import MAX_CONDITION, check_gaussians

__all__ = [
    "MAX_CONDITION",
    "MAX_STRIPS",
    "METHODS",
    "NEAR_RHO",
    "NEAR_SPREAD",
    "TINY",
    "Integrator",
    "covered_mass",
    "cell_integrals",
    "integrate",
    "integrate_checked",
    "reference_integrate",
]

METHODS = ("scalespace", "terraces")
"""The integrators :func:`integrate` offers (its ``method``)."""
NEAR_RHO = 0.5
"""Mahalanobis distance from the grid beyond which ``method="scalespace"`` leaves a Gaussian to the terraces."""
NEAR_SPREAD = 4.0
"""2π√det A over the grid's area beyond which ``method="scalespace"`` leaves a Gaussian to the terraces."""


class Integrator(Protocol):
    """What the association (:class:`tracker.association.greedy.Tracker`) and the metrics
    (:mod:`tracker.study.metrics`) need from an integrator.

    Called with ``means`` (N, 2) metres in the prior's CRS and ``covs`` (N, 2, 2) m² that are already
    checked (finite, symmetric positive definite: see :func:`integrate_checked`); returns (N,) float64
    ∫ G(y; a_n, A_n) r(y) dy per m², or ∫ G r² dy per m⁴ when ``squared``. Examples:
    :func:`integrate_checked`, ``functools.partial(integrate_checked, method="terraces")``,
    :func:`reference_integrate`, :class:`tracker.study.experiment.CachedIntegrator`.
    """

    def __call__(self, prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, squared: bool = False) -> np.ndarray: ...


def integrate(
    prior: TerrainPrior,
    means: np.ndarray,
    covs: np.ndarray,
    squared: bool = False,
    *,
    method: Literal["scalespace", "terraces"] = "scalespace",
    n_terraces: int = N_TERRACES,
    n_strips: int = N_STRIPS,
    mass: float = MASS,
    shear: float = SHEAR,
    scheme: Literal["adaptive", "paper"] = "adaptive",
) -> np.ndarray:
    """∫ G(y; a_n, A_n) r(y) dy per m² (or ∫ G r² dy per m⁴ when ``squared``) for N 2-D Gaussians.

    ``means`` (N, 2) metres in the prior's CRS, ``covs`` (N, 2, 2) m². The prior is zero off its
    grid, so Gaussians partly or wholly off the grid are fine. Validates the Gaussians, then
    :func:`integrate_checked` (see it for ``method`` and the terrace settings). Raises ``ValueError``
    naming the indices of non-finite means or of covariances that are not symmetric positive definite.
    """
    means, covs = check_gaussians(means, covs, "integrate")
    if means.shape[1] != 2:
        raise ValueError(f"integrate: Gaussians must be 2-D, got dimension {means.shape[1]}")
    return _integrate(prior, means, covs, squared, method, n_terraces, n_strips, mass, shear, scheme)


def integrate_checked(
    prior: TerrainPrior,
    means: np.ndarray,
    covs: np.ndarray,
    squared: bool = False,
    *,
    method: Literal["scalespace", "terraces"] = "scalespace",
    n_terraces: int = N_TERRACES,
    n_strips: int = N_STRIPS,
    mass: float = MASS,
    shear: float = SHEAR,
    scheme: Literal["adaptive", "paper"] = "adaptive",
) -> np.ndarray:
    """:func:`integrate` for Gaussians already checked: float64 ``means`` (N, 2) m and ``covs``
    (N, 2, 2) m² that passed :func:`~tracker.types.reports.check_gaussians` (those of a
    :class:`~tracker.types.reports.Reports`, or their Gaussian products); it does not check them again.

    ``method="scalespace"`` (default) integrates with the prior's Gaussian pyramid
    (:mod:`tracker.integrate.scalespace`) the Gaussians that have most of their mass on the grid and sends
    the rest (centres more than ``NEAR_RHO`` σ off the grid, spreads wider than the grid, thinner
    than ~500:1) to the terraces; ``method="terraces"`` uses the terraces for all. On grids of more
    than ``scalespace.MAX_CELLS`` cells the pyramid is built lazily, per tile where the Gaussians fall,
    in a bounded cache (:mod:`tracker.integrate.lazy`), with the same integrals.
    Terrace settings: ``shear = 0`` keeps every ellipse at ``n_strips`` strips; ``scheme="paper"``
    uses the paper's equal-mass terraces (with ``mass = 0.99`` its stop). Raises ``ValueError`` for
    settings out of range.
    """
    return _integrate(prior, means, covs, squared, method, n_terraces, n_strips, mass, shear, scheme)


def _integrate(prior, means, covs, squared, method, n_terraces, n_strips, mass, shear, scheme) -> np.ndarray:
    """The dispatch behind :func:`integrate` and :func:`integrate_checked` (warnings point at their caller)."""
    if not (isinstance(n_terraces, int | np.integer) and n_terraces >= 2):
        raise ValueError(f"integrate: n_terraces must be an integer >= 2, got {n_terraces!r}")
    if not (isinstance(n_strips, int | np.integer) and n_strips >= 1):
        raise ValueError(f"integrate: n_strips must be an integer >= 1, got {n_strips!r}")
    if not 0.0 < mass < 1.0:
        raise ValueError(f"integrate: mass must be in (0, 1), got {mass!r}")
    if not shear >= 0.0:
        raise ValueError(f"integrate: shear must be >= 0, got {shear!r}")
    if scheme not in ("adaptive", "paper"):
        raise ValueError(f"integrate: scheme must be 'adaptive' or 'paper', got {scheme!r}")
    if method not in METHODS:
        raise ValueError(f"integrate: method must be one of {METHODS}, got {method!r}")
    if method == "scalespace" and 0 < means.shape[0] < scalespace.SMALL_BATCH:
        if prior.grid.height * prior.grid.width <= scalespace.MAX_CELLS:
            small = scalespace.integrate_small(prior, means, covs, squared, NEAR_RHO, NEAR_SPREAD)
        else:
            small = lazy_pyramid(prior, squared).integrate_small(prior, means, covs, NEAR_RHO, NEAR_SPREAD)
        if small is not None:  # the same values as below, in one compiled call
            return small
    uc, vc, cuu, cuv, cvv = pixel_gaussians(prior, means, covs)
    result = np.empty(means.shape[0])
    # Gaussians under TINY cells (both methods): the closed form, the cells' values weighted by their masses.
    tiny = is_tiny(cuu, cuv, cvv)
    rest = np.flatnonzero(~tiny)
    if rest.size < means.shape[0]:
        idx = np.flatnonzero(tiny)
        result[idx] = cell_integrals(prior, tiny_integrals, squared, *(a[idx] for a in (uc, vc, cuu, cuv, cvv)))
        uc, vc, cuu, cuv, cvv = (a[rest] for a in (uc, vc, cuu, cuv, cvv))
    _integrate_rest(prior, uc, vc, cuu, cuv, cvv, squared, method, n_terraces, n_strips, mass, shear, scheme, result, rest)
    bad = np.flatnonzero(~np.isfinite(result))
    if bad.size:
        # Finite, checked Gaussians give finite integrals of a finite prior: the prior's tables are not.
        table = "sat2 (r²)" if squared else "sat (r)"
        raise ValueError(
            f"integrate: non-finite integrals at indices {bad[:10].tolist()}: the prior's density or "
            f"summed-area table {table} holds NaN or inf values; rebuild the prior"
        )
    return result


def _integrate_rest(prior, uc, vc, cuu, cuv, cvv, squared, method, n_terraces, n_strips, mass, shear, scheme, out, where):
    """The pyramid and the terraces for the Gaussians (pixel units) that are not tiny; results to ``out[where]``."""
    result = np.empty(uc.shape[0])
    rest = np.arange(uc.shape[0])
    if method == "scalespace" and rest.size:
        h, w = prior.grid.shape
        handled = near_grid(uc, vc, cuu, cuv, cvv, float(w), float(h), NEAR_RHO, NEAR_SPREAD)
        near = None if handled.all() else np.flatnonzero(handled)
        px = (uc, vc, cuu, cuv, cvv) if near is None else tuple(a[near] for a in (uc, vc, cuu, cuv, cvv))
        if prior.grid.height * prior.grid.width > scalespace.MAX_CELLS:
            try:
                values, counts = lazy_pyramid(prior, squared).integrate_pixels(*px)  # the same numbers, per tile
            except MemoryError as exc:  # wide Gaussians: the tiles below one tile outgrow the cache
                warnings.warn(f"integrate: {exc}; using the terraces for this batch", stacklevel=4)
                values, counts = np.zeros(px[0].shape[0]), np.zeros(px[0].shape[0], np.int64)
        else:
            values, counts = scalespace.integrate_pixels(prior, *px, squared)
        if near is None:
            result, handled = values, counts > 0
        else:
            result[near] = values
            handled[near] = counts > 0
        rest = np.flatnonzero(~handled)
    if rest.size:
        # Gaussians of a few cells: exact per-cell masses, which terraces cannot follow on a rough field.
        few = rest[is_few_cells(cuu[rest], cuv[rest], cvv[rest])]
        if few.size:
            result[few] = cell_integrals(prior, few_cell_integrals, squared, *(a[few] for a in (uc, vc, cuu, cuv, cvv)))
            rest = np.setdiff1d(rest, few, assume_unique=True)
    if rest.size:
        result[rest] = integrate_terraces(
            prior, *(a[rest] for a in (uc, vc, cuu, cuv, cvv)), squared, n_terraces, n_strips, mass, shear, scheme
        )
    out[where] = result


def cell_integrals(prior: TerrainPrior, kernel, squared: bool, uc, vc, cuu, cuv, cvv) -> np.ndarray:
    """``kernel`` (:func:`~tracker.integrate.tiny.tiny_integrals` or
    :func:`~tracker.integrate.tiny.few_cell_integrals`) on the prior's cells (r, or r² when ``squared``).
    A windowed density (a prior larger than memory) is read per file block of the Gaussians' means, each
    window covering every cell its Gaussians read, so the integrals are the in-memory ones."""
    density = prior.density
    if isinstance(density, np.ndarray):
        field = np.asarray(density, dtype=np.float64)
        return kernel(field * field if squared else field, 0, 0, uc, vc, cuu, cuv, cvv)
    out = np.empty(uc.shape[0])
    reach_u, reach_v = np.sqrt(cuu) * READ_SPAN + 2.0, np.sqrt(cvv) * READ_SPAN + 2.0
    order, group, bounds = window_groups(uc, vc, reach_u, reach_v, prior.grid.shape, WINDOW_BLOCK)
    groups = np.split(order, np.flatnonzero(np.diff(group)) + 1) if order.size else []
    for members, (r0, r1, c0, c1) in zip(groups, bounds.tolist(), strict=True):
        field = density[r0:r1, c0:c1]
        out[members] = kernel(field * field if squared else field, r0, c0, *(a[members] for a in (uc, vc, cuu, cuv, cvv)))
    return out


WINDOW_BLOCK = 256
"""Cells per side of the blocks of means whose cells :func:`cell_integrals` reads in one window."""
