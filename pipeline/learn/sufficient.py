"""Sufficient statistics of the inhomogeneous-Poisson fit: one pass over the grid, then no cells.

The log-likelihood of points x_1..x_n under p(x) = r(x) / ∫ r depends on the grid only through
∫ r = Σ_c A_c r(c), the sum over *combinations* c of the terms' levels (categories, bins, fine
bins of a continuous feature) of their area A_c (m²) times the likelihood there. :func:`cell_stats`
makes that table in one chunked pass; :func:`point_stats` gives each point's levels and its exact
continuous values. Continuous terms (the road form, a log-KDE exponent) use fine bins of width
``Term.bin_width`` (feature units) and keep the area-weighted mean value of each bin inside each
combination, so the only approximation is r evaluated at that mean within one fine bin.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from pipeline.features.stack import FeatureStack
from pipeline.gis.grid import NODATA_CODE
from pipeline.learn.forms import BASIS_FORMS, basis, from_scale, knots, to_scale
from pipeline.learn.window import BlockWindow, cell_blocks

TermForm = Literal["categorical", "binned", "road", "kde", "linear", "increasing", "decreasing", "spline"]
DISCRETE_FORMS = ("categorical", "binned")
CONTINUOUS_FORMS = ("road", "kde", *BASIS_FORMS)
NODATA_INDEX = -1
"""Level index of a no-data cell or point (its likelihood is the fixed ``Term.nodata``)."""

_DENSE_KEYS = 1 << 24
"""Largest combination-key space counted with a dense bincount; larger spaces use np.unique."""


@dataclass(frozen=True)
class Term:
    """One feature's factor r_i(F_i(x)) as the fit sees it.

    ``categorical``: one level per code in ``codes`` (names in ``levels``). ``binned``: one level per
    left edge in ``edges`` (feature units, last bin open, values below the first edge in bin 0).
    ``road``: paper 1's form in (rmd, mv). ``kde``: the hybrid's spatial term (see
    :func:`pipeline.learn.poisson.kde_logr`) of value log(k + KDE_EPS), k a KDE over the uniform density. ``zeros`` are level
    indices fixed at r = 0 (structural zeros); ``reference`` is the level fixed at r = 1.
    ``bin_width`` (feature units) is the fine bin of continuous forms; ``lo`` their lowest value.
    Basis forms (:mod:`pipeline.learn.forms`: linear, increasing, decreasing, spline) bin on their
    ``scale`` g(v) (``lo`` and ``bin_width`` in units of g), with ``n_knots`` knot intervals and,
    for the spline, the difference-penalty weight ``lam``; ``clamp_lo`` .. ``clamp_hi`` (units of g)
    is the range the basis is evaluated in (values beyond it take the value at its end: Maxent's
    clamping, set by the fit to the training points' range).
    """

    feature: str
    form: TermForm
    levels: tuple[str, ...] = ()
    codes: tuple[int, ...] = ()
    edges: tuple[float, ...] = ()
    zeros: frozenset[int] = field(default_factory=frozenset)
    reference: int = 0
    nodata: float = 1.0
    bin_width: float = 1.0
    lo: float = 0.0
    n_fine: int = 1
    scale: str = "linear"
    n_knots: int = 8
    lam: float = 0.0
    clamp_lo: float = -np.inf
    clamp_hi: float = np.inf

    @property
    def kappa(self) -> np.ndarray:
        """Basis forms: the knots on the scale g over the fine bins' range."""
        return knots(self.lo, self.lo + self.n_fine * self.bin_width, self.n_knots)

    def basis(self, values: np.ndarray) -> np.ndarray:
        """Basis forms: B (n, K) at raw feature values ``values`` (n,), their scale g clamped to
        [``clamp_lo``, ``clamp_hi``]; rows of NaN values are 0."""
        return basis(self.form, np.clip(to_scale(self.scale, values), self.clamp_lo, self.clamp_hi), self.kappa)

    @property
    def n_levels(self) -> int:
        """Number of level indices (fine bins for continuous forms)."""
        return len(self.levels) if self.form in DISCRETE_FORMS else self.n_fine

    def index(self, values: np.ndarray) -> np.ndarray:
        """Level index (int64) of feature values; ``NODATA_INDEX`` for no data."""
        if self.form == "categorical":
            # a look-up table over the code range: one gather per cell
            lo = min(min(self.codes), NODATA_CODE)
            lut = np.full(max(self.codes) - lo + 1, -2, dtype=np.int64)
            lut[np.asarray(self.codes) - lo] = np.arange(len(self.codes))
            lut[NODATA_CODE - lo] = NODATA_INDEX
            v = np.asarray(values, dtype=np.int64) - lo
            inside = (v >= 0) & (v < len(lut))
            idx = lut[np.where(inside, v, 0)]
            idx[~inside] = -2
            if np.any(idx == -2):
                bad = np.unique(np.asarray(values)[idx == -2])
                raise ValueError(f"feature {self.feature!r}: codes {bad[:10].tolist()} are not in the term's {list(self.codes)}")
            return idx
        x = np.asarray(values, dtype=np.float64)
        if self.form in BASIS_FORMS:
            x = to_scale(self.scale, x)
        nan = np.isnan(x)
        xs = np.where(nan, self.lo, x)
        if self.form == "binned":
            idx = np.clip(np.searchsorted(self.edges, xs, side="right") - 1, 0, len(self.edges) - 1)
        else:
            idx = np.clip(np.floor((xs - self.lo) / self.bin_width), 0, self.n_fine - 1).astype(np.int64)
        return np.where(nan, NODATA_INDEX, idx)


def with_range(term: Term, values: np.ndarray) -> Term:
    """A continuous term whose fine bins cover the finite ``values``."""
    if term.form not in CONTINUOUS_FORMS:
        return term
    finite = values[np.isfinite(values)]
    if term.form in BASIS_FORMS:
        finite = to_scale(term.scale, finite)
    if finite.size == 0:
        raise ValueError(f"feature {term.feature!r}: no finite values on the grid")
    lo, hi = float(finite.min()), float(finite.max())
    if term.form in BASIS_FORMS:  # ``n_fine`` equal bins over [lo, hi] of the scale g
        return Term(**{**term.__dict__, "lo": lo, "bin_width": (hi - lo) / term.n_fine if hi > lo else 1.0})
    n_fine = max(1, int(np.floor((hi - lo) / term.bin_width)) + 1)
    return Term(**{**term.__dict__, "lo": lo, "n_fine": n_fine})


@dataclass
class CellStats:
    """Area of each combination of term levels present on the grid.

    ``index`` (m, T) level index per term (``NODATA_INDEX`` for no data); ``value`` (m, T) the
    area-weighted mean feature value in the combination for continuous terms (NaN for discrete);
    ``area`` (m,) in m²; ``n_cells`` the grid's cell count. With ``block_size`` (metres) each
    combination is split by block (``block`` (m,) its :func:`pipeline.learn.kde.block_ids`), so the
    statistics of an observation window are a selection of rows (:meth:`within`).
    """

    terms: tuple[Term, ...]
    index: np.ndarray
    value: np.ndarray
    area: np.ndarray
    cell_area: float
    n_cells: int
    block: np.ndarray | None = None
    block_size: float | None = None

    def within(self, window: BlockWindow | None) -> CellStats:
        """The statistics of the cells inside ``window`` (None: all of them)."""
        if window is None or not window.unobserved:
            return self
        if self.block is None or self.block_size != window.size:
            raise ValueError(f"window: blocks of {window.size:g} m need cell statistics split by such blocks "
                             f"(these are split by {self.block_size})")
        keep = ~np.isin(self.block, np.fromiter(window.unobserved, np.int64))
        return replace(self, index=self.index[keep], value=self.value[keep], area=self.area[keep], block=self.block[keep])

    @property
    def total_area(self) -> float:
        """Grid area in m²."""
        return float(self.area.sum())

    def bin_value(self, t: int) -> np.ndarray:
        """Continuous term ``t``: area-weighted mean value per fine bin over all combinations."""
        idx = self.index[:, t]
        ok = idx >= 0
        n = self.terms[t].n_levels
        s = np.bincount(idx[ok], weights=(self.area * self.value[:, t])[ok], minlength=n)
        a = np.bincount(idx[ok], weights=self.area[ok], minlength=n)
        term = self.terms[t]
        lo = term.lo + term.bin_width * (np.arange(n) + 0.5)
        if term.form in BASIS_FORMS:
            lo = from_scale(term.scale, lo)
        return np.where(a > 0, s / np.where(a > 0, a, 1.0), lo)

    def level_area(self, t: int) -> np.ndarray:
        """Area (m²) of each level of term ``t`` (no data excluded)."""
        idx = self.index[:, t]
        ok = idx >= 0
        return np.bincount(idx[ok], weights=self.area[ok], minlength=self.terms[t].n_levels)


@dataclass
class PointStats:
    """Each point's level index and exact value per term; ``inside`` marks points on the grid;
    ``weight`` each point's weight (None: all 1; see :func:`check_weights`)."""

    terms: tuple[Term, ...]
    index: np.ndarray
    value: np.ndarray
    inside: np.ndarray
    weight: np.ndarray | None = None

    @property
    def weights(self) -> np.ndarray:
        """Per-point weights (ones when none were given)."""
        return np.ones(len(self.inside)) if self.weight is None else self.weight

    def subset(self, mask: np.ndarray) -> PointStats:
        w = None if self.weight is None else self.weight[mask]
        return PointStats(self.terms, self.index[mask], self.value[mask], self.inside[mask], w)


def _radix(terms: tuple[Term, ...]) -> np.ndarray:
    """Mixed-radix strides of the combination key; slot 0 of each digit is no data."""
    sizes = np.array([t.n_levels + 1 for t in terms], dtype=np.int64)
    if np.prod(sizes.astype(np.float64)) >= 2.0**62:
        raise ValueError(f"too many level combinations ({sizes.tolist()}); use wider fine bins")
    return np.concatenate([[1], np.cumprod(sizes[:-1])]).astype(np.int64), sizes


def cell_stats(stack: FeatureStack, terms: tuple[Term, ...], rows_per_chunk: int | None = None,
               block_size: float | None = None) -> CellStats:
    """One pass over the grid: area per combination of the terms' levels (see the module doc), and
    per block of ``block_size`` metres too when it is given.

    Continuous terms must already have their range set (:func:`with_range`).
    """
    terms = tuple(terms)
    if not terms:
        raise ValueError("cell_stats needs at least one term")
    strides, sizes = _radix(terms)
    space = int(np.prod(sizes))
    h, w = stack.grid.shape
    n_by = 1
    if block_size is not None:  # the block is the key's top digit: bx * n_by + by
        g = stack.grid
        n_by = int(np.floor((g.bounds[3] - g.bounds[1]) / block_size)) + 1
        n_blocks = (int(np.floor((g.bounds[2] - g.bounds[0]) / block_size)) + 1) * n_by
        if space * float(n_blocks) >= 2.0**62:
            raise ValueError(f"too many level combinations times {n_blocks} blocks; use wider fine bins or larger blocks")
        space_blocks = space * n_blocks
    rows = rows_per_chunk or max(1, (1 << 22) // w)
    cont = [k for k, t in enumerate(terms) if t.form in CONTINUOUS_FORMS]
    keyspace = space if block_size is None else space_blocks
    dense = keyspace <= _DENSE_KEYS
    if dense:
        counts = np.zeros(keyspace, dtype=np.int64)
        sums = np.zeros((len(cont), keyspace), dtype=np.float64)
    else:
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    arrays = [stack[t.feature].values for t in terms]
    for r0 in range(0, h, rows):
        key = np.zeros(min(rows, h - r0) * w, dtype=np.int64)
        chunks = [a[r0 : r0 + rows].ravel() for a in arrays]
        for k, t in enumerate(terms):
            key += (t.index(chunks[k]) + 1) * strides[k]
        if block_size is not None:
            b = cell_blocks(stack.grid, block_size, r0, min(rows, h - r0))
            key += (b // 1_000_003 * n_by + b % 1_000_003) * space
        vals = [np.nan_to_num(chunks[k].astype(np.float64)) for k in cont]
        if dense:
            counts += np.bincount(key, minlength=keyspace)
            for j, v in enumerate(vals):
                sums[j] += np.bincount(key, weights=v, minlength=keyspace)
        else:
            u, inv = np.unique(key, return_inverse=True)
            parts.append((u, np.bincount(inv), np.array([np.bincount(inv, weights=v) for v in vals]).reshape(len(cont), -1)))
    if dense:
        keys = np.flatnonzero(counts)
        n = counts[keys]
        s = sums[:, keys]
    else:
        allk = np.concatenate([p[0] for p in parts])
        keys, inv = np.unique(allk, return_inverse=True)
        n = np.bincount(inv, weights=np.concatenate([p[1] for p in parts])).astype(np.int64)
        s = np.array([np.bincount(inv, weights=np.concatenate([p[2][j] for p in parts])) for j in range(len(cont))]).reshape(len(cont), -1)
    block = None
    if block_size is not None:
        compact, keys = keys // space, keys % space
        block = compact // n_by * 1_000_003 + compact % n_by
    index = ((keys[:, None] // strides[None, :]) % sizes[None, :] - 1).astype(np.int64)
    value = np.full(index.shape, np.nan)
    for j, k in enumerate(cont):
        value[:, k] = np.where(index[:, k] >= 0, s[j] / n, np.nan)
    return CellStats(terms, index, value, n * stack.grid.cell_area, stack.grid.cell_area, h * w, block,
                     None if block_size is None else float(block_size))


_PASSES: dict[int, tuple[weakref.ref, dict[tuple[tuple[Term, ...], float | None], tuple[tuple[np.ndarray, ...], CellStats]]]] = {}
"""Grid passes per live stack (by id, dropped when the stack is collected): (terms, block size) -> (arrays read, stats)."""


def cached_cell_stats(stack: FeatureStack, terms: tuple[Term, ...], block_size: float | None = None) -> CellStats:
    """:func:`cell_stats`, run once per stack, terms and ``block_size``: a refit on the same stack (CV folds, clones,
    other points) reuses the pass. A feature replaced in the stack (another array) runs it again;
    arrays changed in place are not detected."""
    terms = tuple(terms)
    key = id(stack)
    entry = _PASSES.get(key)
    if entry is None or entry[0]() is not stack:
        entry = (weakref.ref(stack, lambda _, k=key: _PASSES.pop(k, None)), {})
        _PASSES[key] = entry
    arrays = tuple(stack[t.feature].values for t in terms)
    hit = entry[1].get((terms, block_size))
    if hit is not None and all(a is b for a, b in zip(hit[0], arrays, strict=True)):
        return hit[1]
    cells = cell_stats(stack, terms, block_size=block_size)
    entry[1][(terms, block_size)] = (arrays, cells)
    return cells


def check_points(points: np.ndarray) -> np.ndarray:
    """Points as a float (N, 2) array of x, y metres; ValueError naming bad shapes or indices."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be an (N, 2) array of x, y metres, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
        raise ValueError(f"points have non-finite coordinates at indices {bad[:10].tolist()}")
    return pts


def check_weights(weights: np.ndarray | None, n: int, what: str = "sample_weight") -> np.ndarray | None:
    """Per-point weights as float (n,), or None; ValueError naming ``what`` and the first bad rows
    for a wrong length or NaN, infinite, zero or negative weights (a point that should not count is
    left out of the points, not given weight 0)."""
    if weights is None:
        return None
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise ValueError(f"{what}: expected one weight per point ({n}), got shape {w.shape}")
    for bad, name in ((np.isnan(w), "NaN"), (np.isinf(w), "infinite"), (w == 0, "zero"), (w < 0, "negative")):
        if bad.any():
            rows = np.flatnonzero(bad)
            raise ValueError(f"{what}: {rows.size} {name} weights (rows {rows[:10].tolist()}); weights must be finite and > 0")
    return w


def point_stats(stack: FeatureStack, terms: tuple[Term, ...], points: np.ndarray,
                weights: np.ndarray | None = None) -> PointStats:
    """Level index and exact value per term of points (N, 2) in metres in the grid's CRS, with
    their ``weights`` (validated by :func:`check_weights`)."""
    pts = check_points(points)
    weights = check_weights(weights, len(pts))
    inside = stack.grid.contains(pts[:, 0], pts[:, 1])
    sampled = stack.sample(pts[:, 0], pts[:, 1])
    index = np.empty((pts.shape[0], len(terms)), dtype=np.int64)
    value = np.full(index.shape, np.nan)
    for k, t in enumerate(terms):
        x = sampled[t.feature]
        index[:, k] = t.index(x)
        if t.form in CONTINUOUS_FORMS:
            value[:, k] = x
    return PointStats(tuple(terms), index, value, inside, weights)
