"""Penalised inhomogeneous-Poisson log-likelihood of points on sufficient statistics, and its fit.

For points x_1..x_n and r(x) = Π_t r_t(x), the normalised-density log-likelihood is
ℓ(θ) = Σ_i log r(x_i) − n log Σ_c A_c r(c), the Poisson process likelihood with the intercept
profiled out. Parameters per term (:class:`TermParams`): log r of each free level of a discrete
term (reference level fixed at 0, structural zeros fixed), (log rmd, mv) for the road form, γ for
the hybrid's KDE term. The penalty is a Gaussian prior: ½ Σ θ²/σ² on the discrete terms'
log-likelihoods (σ = ``penalty_sd``) plus ½ Σ (Δ log r)²/τ² between adjacent bins of a binned term
(τ = ``smooth_sd``). The fit minimises −(ℓ − penalty) with scipy's L-BFGS-B (bounds: rmd > 0,
mv in (0, 1], γ >= 0);
standard errors come from the inverse of the observed information, the Hessian of −(ℓ − penalty),
by central differences of the analytic gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy import optimize
from threadpoolctl import threadpool_limits

from pipeline.learn.forms import BASIS_FORMS, difference_penalty
from pipeline.learn.kde import KDE_EPS
from pipeline.learn.sufficient import DISCRETE_FORMS, CellStats, PointStats, Term
from pipeline.prior.likelihood import road_likelihood

MV_MIN = 1e-6
"""Lower bound of mv in the fit (the form needs mv > 0)."""
RMD_BOUNDS_M = (1e-2, 1e7)


@dataclass
class TermParams:
    """How one term's parameters enter log r. ``fixed`` holds log r of every discrete level
    (reference 0, structural zeros −inf or log of the softened value), overwritten at ``free``."""

    term: Term
    free: np.ndarray  # discrete: free level indices
    fixed: np.ndarray  # discrete: log r per level, plus log(nodata) last
    x0: np.ndarray
    bounds: list[tuple[float | None, float | None]]
    bin_value: np.ndarray | None = None  # continuous: area-weighted mean value per fine bin (cells)
    alpha: float = 0.01  # KDE term: fixed share of the uniform density mixed into the KDE
    has_area: np.ndarray | None = None  # discrete: levels with area on the grid
    pen: np.ndarray | None = None  # basis forms: λ·P, the quadratic penalty ½ θᵀ(λP)θ

    def __post_init__(self) -> None:
        self._basis: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def basis(self, value: np.ndarray) -> np.ndarray:
        """Basis forms: B at raw feature values (cached per array: the fit asks for the same
        distinct point rows and fine-bin values at every evaluation)."""
        hit = self._basis.get(id(value))
        if hit is not None and hit[0] is value:
            return hit[1]
        b = self.term.basis(value)
        self._basis[id(value)] = (value, b)
        return b

    @property
    def size(self) -> int:
        return len(self.x0)

    def lut(self, theta: np.ndarray) -> np.ndarray:
        """Discrete: log r per level with log(nodata) last, so index −1 (no data) picks it."""
        out = self.fixed.copy()
        out[self.free] = theta
        return out

    def logr(self, theta: np.ndarray, index: np.ndarray, value: np.ndarray) -> np.ndarray:
        """log r per row (points, or fine bins) from level indices and exact values."""
        t = self.term
        if t.form in DISCRETE_FORMS:
            return self.lut(theta)[index]
        lognd = self.lut_nodata
        if t.form in BASIS_FORMS:
            return np.where(index >= 0, self.basis(value) @ theta, lognd)
        if t.form == "road":
            r = road_likelihood(value, np.exp(theta[0]), theta[1])
            with np.errstate(divide="ignore"):
                return np.where(index >= 0, np.log(r), lognd)
        return np.where(index >= 0, kde_logr(np.nan_to_num(value), theta[0], self.alpha), lognd)

    def cell_lut(self, theta: np.ndarray) -> np.ndarray:
        """log r per level (fine bin for continuous terms) with log(nodata) last."""
        if self.term.form in DISCRETE_FORMS:
            return self.lut(theta)
        if self.term.form in BASIS_FORMS:
            return np.append(self.basis(self.bin_value) @ theta, self.lut_nodata)
        n = len(self.bin_value)
        return np.append(self.logr(theta, np.zeros(n, np.int64), self.bin_value), self.lut_nodata)

    def design(self) -> np.ndarray | None:
        """J (n_levels + 1, size) with :meth:`cell_lut` = const + J·θ (no data last) for a term linear
        in θ (every form but the road form: None)."""
        t = self.term
        if t.form in DISCRETE_FORMS:
            j = np.zeros((t.n_levels + 1, self.size))
            j[self.free, np.arange(self.size)] = 1.0
            return j
        if t.form in BASIS_FORMS:
            return np.vstack([self.basis(self.bin_value), np.zeros((1, self.size))])
        if t.form == "kde":
            return np.append(kde_logr(np.nan_to_num(self.bin_value), 1.0, self.alpha), 0.0)[:, None]
        return None

    @property
    def lut_nodata(self) -> float:
        return float(np.log(self.term.nodata)) if self.term.nodata > 0 else -np.inf

    def grad(self, theta: np.ndarray, index: np.ndarray, value: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """Σ_i weight_i ∂ log r_i / ∂θ over rows (distinct point rows)."""
        t = self.term
        ok = index >= 0
        if t.form in DISCRETE_FORMS:
            return self.grad_levels(theta, np.bincount(index[ok], weights=weight[ok], minlength=t.n_levels))
        if t.form in BASIS_FORMS:
            return self.basis(value).T @ np.where(ok, weight, 0.0)
        return self._grad_values(theta, value[ok], weight[ok])

    def grad_levels(self, theta: np.ndarray, per_level: np.ndarray) -> np.ndarray:
        """As :meth:`grad` from the weights summed per level (fine bin for continuous terms)."""
        if self.term.form in DISCRETE_FORMS:
            return per_level[self.free]
        return self._grad_values(theta, self.bin_value, per_level)

    def _grad_values(self, theta: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
        if self.term.form in BASIS_FORMS:
            return self.basis(d).T @ w
        if self.term.form == "road":
            rmd, mv = np.exp(theta[0]), theta[1]
            z = d / rmd - 1.0
            g = np.exp(-0.5 * z * z)
            r = (1.0 - mv) * g + mv
            d_logrmd = (1.0 - mv) * g * z * d / rmd / r
            d_mv = (1.0 - g) / r
            return np.array([np.dot(w, d_logrmd), np.dot(w, d_mv)])
        return np.array([np.dot(w, kde_logr(d, 1.0, self.alpha))])


def term_params(
    term: Term, level_area: np.ndarray, soften: float | None, start: dict | None = None, bin_value: np.ndarray | None = None
) -> TermParams:
    """Parameters of one term. Discrete levels with no area are fixed at log r = 0 (unidentified).

    ``soften``: structural zeros get this fixed likelihood instead of 0. ``start``: initial values
    (``{"logr": array per level}`` or ``{"rmd":, "mv":}`` or ``{"gamma":, "alpha":}``, α fixed).
    """
    start = start or {}
    if term.form in DISCRETE_FORMS:
        n = term.n_levels
        fixed = np.zeros(n + 1)
        zeros = np.array(sorted(term.zeros), dtype=np.int64)
        fixed[zeros] = np.log(soften) if soften else -np.inf
        fixed[n] = np.log(term.nodata) if term.nodata > 0 else -np.inf
        free = np.array(
            [k for k in range(n) if k != term.reference and k not in term.zeros and level_area[k] > 0], dtype=np.int64
        )
        x0 = np.asarray(start.get("logr", np.zeros(n)), dtype=np.float64)[free]
        x0 = np.where(np.isfinite(x0), x0, 0.0)
        return TermParams(term, free, fixed, x0, [(None, None)] * len(free), has_area=np.asarray(level_area) > 0)
    if term.form in BASIS_FORMS:
        pen = term.lam * difference_penalty(term.form, term.n_knots)
        x0 = np.zeros(pen.shape[0])
        # monotone forms: non-negative hinge weights; the others are free (the spline is penalised)
        b = [(0.0, None)] * len(x0) if term.form in ("increasing", "decreasing") else [(None, None)] * len(x0)
        return TermParams(term, np.zeros(0, np.int64), np.zeros(0), x0, b, bin_value, pen=pen)
    if term.form == "road":
        rmd = float(start.get("rmd", 100.0))
        mv = float(np.clip(start.get("mv", 0.5), MV_MIN, 1.0))
        b = [tuple(np.log(RMD_BOUNDS_M)), (MV_MIN, 1.0)]
        return TermParams(term, np.zeros(0, np.int64), np.zeros(0), np.array([np.log(rmd), mv]), b, bin_value)
    # γ >= 0: more past points nearby never makes a place less likely. Without the bound, a fit on
    # held-out-block values learns "targets are where the other blocks' points are not" (γ < 0).
    alpha = float(start.get("alpha", 0.01))
    if not 0 < alpha <= 1:
        raise ValueError(f"the KDE term's uniform share must be in (0, 1], got {alpha}")
    x0 = np.array([max(float(start.get("gamma", 0.5)), 0.0)])
    return TermParams(term, np.zeros(0, np.int64), np.zeros(0), x0, [(0.0, None)], bin_value, alpha)


def kde_logr(value: np.ndarray, gamma: float, alpha: float) -> np.ndarray:
    """The hybrid's spatial term: log r = γ·log(α + (1−α)·k), k = exp(value) − KDE_EPS the KDE of
    past points over the uniform density. α, the share of the uniform density mixed in, bounds
    what a target far from every past one costs; γ >= 0 says how sharply targets follow past ones."""
    k = np.exp(value) - KDE_EPS
    return gamma * np.log(alpha + (1.0 - alpha) * k)


@dataclass
class Objective:
    """−(ℓ − penalty) and its gradient over the concatenated parameters of ``params``.

    ``active`` picks the terms in the model (the others are ignored: r_t = 1), which gives the
    marginal (naive) fits on the same statistics.
    """

    cells: CellStats
    points: PointStats
    params: list[TermParams]
    active: list[int]
    penalty_sd: float
    smooth_sd: float

    def __post_init__(self) -> None:
        sizes = [self.params[k].size for k in self.active]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        w = self.points.weights
        self.n = float(w.sum())  # the weighted likelihood: Σ w_i log r(x_i) − (Σ w_i) log Z
        # The points enter only through each term's distinct (level, value) rows and their summed weights.
        self._rows = [_distinct_rows(self.points.index[:, k], self.points.value[:, k], w) for k in self.active]
        self._cidx = np.ascontiguousarray(self.cells.index[:, self.active], dtype=np.int64)
        sizes = [self.params[k].term.n_levels + 1 for k in self.active]
        self._lut_off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self._pairs = [(a, b) for a in range(len(sizes)) for b in range(a + 1, len(sizes))]
        self._pair_off = np.concatenate([[0], np.cumsum([sizes[a] * sizes[b] for a, b in self._pairs])]).astype(np.int64)
        self._pen_hess: np.ndarray | None = None

    @property
    def x0(self) -> np.ndarray:
        return np.concatenate([self.params[k].x0 for k in self.active]) if self.active else np.zeros(0)

    @property
    def bounds(self) -> list:
        return [b for k in self.active for b in self.params[k].bounds]

    def split(self, x: np.ndarray) -> list[np.ndarray]:
        return [x[self.offsets[j] : self.offsets[j + 1]] for j in range(len(self.active))]

    def points_sum(self, x: np.ndarray) -> float:
        """Σ_i log r(x_i) from the distinct rows."""
        total = 0.0
        for th, k, (idx, val, cnt) in zip(self.split(x), self.active, self._rows, strict=True):
            total += float(cnt @ self.params[k].logr(th, idx, val))
        return total

    def log_z(self, x: np.ndarray) -> tuple[float, list[np.ndarray]]:
        """log Σ_c A_c r_c (m²), and per active term the share A_c r_c / Z summed per level."""
        luts = np.concatenate([self.params[k].cell_lut(th) for th, k in zip(self.split(x), self.active, strict=True)])
        log_z, shares = _cell_pass(self._cidx, self.cells.area, luts, self._lut_off)
        return log_z, [shares[self._lut_off[j] : self._lut_off[j + 1] - 1] for j in range(len(self.active))]

    def loglik(self, x: np.ndarray) -> float:
        """ℓ(θ): Σ log p(x_i) with p per m² (nats)."""
        return self.points_sum(x) - self.n * self.log_z(x)[0]

    def penalty(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        val, grad = 0.0, np.zeros_like(x)
        for j, (th, k) in enumerate(zip(self.split(x), self.active, strict=True)):
            p = self.params[k]
            sl = slice(self.offsets[j], self.offsets[j + 1])
            if p.pen is not None:  # basis forms: the spline's difference penalty (zero for the others)
                val += 0.5 * float(th @ p.pen @ th)
                grad[sl] += p.pen @ th
                continue
            if p.term.form not in DISCRETE_FORMS:  # road and KDE parameters are bounded, not penalised
                continue
            val += 0.5 * float(th @ th) / self.penalty_sd**2
            grad[sl] += th / self.penalty_sd**2
            if p.term.form == "binned" and self.smooth_sd > 0:
                # differences between consecutive bins that have area and are not structural
                # zeros: an empty bin (fixed, unidentified) must not pull its neighbours to 1
                lut = p.lut(th)[:-1]
                used = np.flatnonzero(np.isfinite(lut) & p.has_area)
                diff = np.diff(lut[used])
                val += 0.5 * float(diff @ diff) / self.smooth_sd**2
                g_lut = np.zeros(lut.shape[0])
                np.add.at(g_lut, used[:-1], -diff / self.smooth_sd**2)
                np.add.at(g_lut, used[1:], diff / self.smooth_sd**2)
                grad[sl] += g_lut[p.free]
        return val, grad

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """(−(ℓ − penalty), gradient), both divided by n for conditioning."""
        log_z, wc = self.log_z(x)
        ll = self.points_sum(x) - self.n * log_z
        g = np.zeros_like(x)
        for j, (th, k, (idx, val, cnt)) in enumerate(zip(self.split(x), self.active, self._rows, strict=True)):
            p = self.params[k]
            g[self.offsets[j] : self.offsets[j + 1]] = p.grad(th, idx, val, cnt) - self.n * p.grad_levels(th, wc[j])
        pen, gpen = self.penalty(x)
        return (-(ll - pen)) / self.n, (-(g - gpen)) / self.n

    @property
    def linear(self) -> bool:
        """Every active term is linear in θ (log r per level = const + J·θ; all forms but the road
        form), so :meth:`hess` is exact and the fit uses Newton's method."""
        return all(self.params[k].term.form != "road" for k in self.active)

    def penalty_hessian(self) -> np.ndarray:
        """Hessian of the penalty (constant: it is quadratic in θ), column by column from its gradient."""
        if self._pen_hess is None:
            k = int(self.offsets[-1])
            g0 = self.penalty(np.zeros(k))[1]
            self._pen_hess = np.column_stack([self.penalty(e)[1] - g0 for e in np.eye(k)]) if k else np.zeros((0, 0))
        return self._pen_hess

    def hess(self, x: np.ndarray) -> np.ndarray:
        """Exact Hessian of −(ℓ − penalty) / n for linear terms (:attr:`linear`): ∇² log Z is the
        covariance of the design rows J over the combinations weighted by their share of Z, made from
        each term's and each pair of terms' level shares (one cell pass), plus the penalty's."""
        luts = np.concatenate([self.params[k].cell_lut(th) for th, k in zip(self.split(x), self.active, strict=True)])
        _, shares, pairs = _pair_pass(self._cidx, self.cells.area, luts, self._lut_off, self._pair_off)
        designs = [self.params[k].design() for k in self.active]
        h = np.zeros((x.shape[0], x.shape[0]))
        mu = np.zeros(x.shape[0])
        sl = [slice(self.offsets[j], self.offsets[j + 1]) for j in range(len(self.active))]
        for j, d in enumerate(designs):
            s = shares[self._lut_off[j] : self._lut_off[j + 1]]
            mu[sl[j]] = d.T @ s
            h[sl[j], sl[j]] = d.T @ (s[:, None] * d)
        for q, (a, b) in enumerate(self._pairs):
            s_ab = pairs[self._pair_off[q] : self._pair_off[q + 1]].reshape(designs[a].shape[0], designs[b].shape[0])
            h[sl[a], sl[b]] = designs[a].T @ s_ab @ designs[b]
            h[sl[b], sl[a]] = h[sl[a], sl[b]].T
        return h - np.outer(mu, mu) + self.penalty_hessian() / self.n

    def hessian(self, x: np.ndarray) -> np.ndarray:
        """Observed information: Hessian of −(ℓ − penalty) (not divided by n): exact for linear
        terms (:meth:`hess`), else central differences of the analytic gradient, one-sided at a bound."""
        if self.linear:
            return self.hess(x) * self.n
        k = x.shape[0]
        h = np.empty((k, k))
        for j, (lo, hi) in enumerate(self.bounds):
            step = 1e-5 * max(1.0, abs(x[j]))
            up = x.copy()
            dn = x.copy()
            up[j] += step
            dn[j] -= step
            if hi is not None and up[j] > hi:
                up[j] = x[j]
            if lo is not None and dn[j] < lo:
                dn[j] = x[j]
            h[:, j] = (self(up)[1] - self(dn)[1]) * self.n / (up[j] - dn[j])
        return 0.5 * (h + h.T)


@nb.njit(cache=True, inline="always")
def _slot(i, t, lut_off):
    """Flat look-up slot of level index ``i`` of term ``t`` (no data, i = −1: the term's last slot)."""
    return lut_off[t] + i if i >= 0 else lut_off[t + 1] - 1


@nb.njit(cache=True)
def _weights(index, area, luts, lut_off):
    """A_c·exp(log r_c − top) per combination c (log r_c = Σ_t lut_t[index_ct]), their sum and top = max_c log r_c."""
    m, n_terms = index.shape
    w = np.empty(m)
    top = -np.inf
    for c in range(m):
        s = 0.0
        for t in range(n_terms):
            s += luts[_slot(index[c, t], t, lut_off)]
        w[c] = s
        top = max(top, s)
    z = 0.0
    for c in range(m):
        w[c] = area[c] * np.exp(w[c] - top)
        z += w[c]
    return w, z, top


@nb.njit(cache=True)
def _cell_pass(index, area, luts, lut_off):
    """log Z = log Σ_c A_c exp(Σ_t lut_t[index_ct]) and each level's share of Z (flat, per term
    at ``lut_off``; no data is each term's last slot, picked by index −1)."""
    w, z, top = _weights(index, area, luts, lut_off)
    shares = np.zeros(luts.shape[0])
    for c in range(index.shape[0]):
        for t in range(index.shape[1]):
            shares[_slot(index[c, t], t, lut_off)] += w[c] / z
    return np.log(z) + top, shares


@nb.njit(cache=True)
def _pair_pass(index, area, luts, lut_off, pair_off):
    """As :func:`_cell_pass`, plus each pair of terms' joint level shares (flat, pair q = (a, b),
    a < b, at ``pair_off[q]``, row-major in (level of a, level of b), no data in each last slot)."""
    w, z, top = _weights(index, area, luts, lut_off)
    m, n_terms = index.shape
    shares = np.zeros(luts.shape[0])
    pairs = np.zeros(pair_off[-1])
    for c in range(m):
        wc = w[c] / z
        q = 0
        for a in range(n_terms):
            sa = _slot(index[c, a], a, lut_off)
            shares[sa] += wc
            for b in range(a + 1, n_terms):
                pairs[pair_off[q] + (sa - lut_off[a]) * (lut_off[b + 1] - lut_off[b]) + _slot(index[c, b], b, lut_off) - lut_off[b]] += wc
                q += 1
    return np.log(z) + top, shares, pairs


def _distinct_rows(index: np.ndarray, value: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct (level index, value) rows of one term over the points, with their summed weights."""
    key = np.stack([index.astype(np.float64), np.nan_to_num(value, nan=-np.inf)], axis=1)
    rows, inv = np.unique(key, axis=0, return_inverse=True)
    val = np.where(np.isfinite(rows[:, 1]), rows[:, 1], np.nan)
    return rows[:, 0].astype(np.int64), val, np.bincount(inv.ravel(), weights=weight, minlength=len(rows))


@dataclass
class FitResult:
    x: np.ndarray
    cov: np.ndarray
    loglik: float
    penalty: float
    success: bool
    message: str
    n_iter: int
    at_bound: np.ndarray


def _start_nonlinear(obj: Objective, x0: np.ndarray) -> np.ndarray:
    """Pick the road and KDE terms' starts among a few values (neither form is concave)."""
    x = x0.copy()
    for j, k in enumerate(obj.active):
        form = obj.params[k].term.form
        if form not in ("road", "kde"):
            continue
        o = obj.offsets[j]
        if form == "road":
            d = obj.points.value[:, k]
            d = d[np.isfinite(d) & (d > 0)]
            scale = float(np.median(d)) if d.size else float(np.exp(x[o]))
            grid = [(np.log(rmd), mv) for rmd in scale * np.geomspace(0.125, 4.0, 11) for mv in (0.05, 0.3, 0.8)]
        else:
            grid = [(g,) for g in (0.0, 0.25, 0.5, 1.0, 2.0)]
        grid.append(tuple(x[o : o + obj.params[k].size]))
        size = obj.params[k].size
        best = min(grid, key=lambda c: obj(np.concatenate([x[:o], c, x[o + size :]]))[0])
        x[o : o + size] = best
    return x


def _newton(obj: Objective, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, ftol: float,
            gtol: float = 1e-9, max_iter: int = 200) -> optimize.OptimizeResult:
    """Projected Newton's method (Bertsekas 1982) for a convex objective with box bounds: the exact
    Hessian (:meth:`Objective.hess`) on the coordinates not held at a bound by their gradient, a
    step projected onto the box, Armijo backtracking. Converged when the projected gradient is below
    ``gtol`` or a step gains less than ``ftol`` relative. ~10-30 iterations where L-BFGS-B takes
    ~1000 on the ill-conditioned spline and hinge bases."""
    x = np.clip(x0, lo, hi)
    f, g = obj(x)
    for it in range(1, max_iter + 1):
        held = ((x <= lo + 1e-12) & (g > 0)) | ((x >= hi - 1e-12) & (g < 0))
        free = ~held
        if np.abs(g[free]).max(initial=0.0) < gtol:
            return optimize.OptimizeResult(x=x, fun=f, success=True, message="projected gradient below gtol", nit=it - 1)
        hess = obj.hess(x)
        while True:  # coordinates at a bound whose Newton step leaves the box are held too, and the step re-solved
            d = np.zeros_like(x)
            # least squares: directions the data do not identify (e.g. two hinges between the same
            # two distinct cell values) get no step instead of an arbitrary one
            d[free] = -np.linalg.lstsq(hess[np.ix_(free, free)], g[free], rcond=1e-10)[0]
            out = free & (((x <= lo + 1e-12) & (d < 0)) | ((x >= hi - 1e-12) & (d > 0)))
            if not out.any():
                break
            free &= ~out
        if not g @ d < 0:  # not a descent direction (numerically singular): a projected gradient step
            d = np.where(held, 0.0, -g)
        t = 1.0
        while True:
            xn = np.clip(x + t * d, lo, hi)
            fn, gn = obj(xn)
            if fn <= f + 1e-4 * (g @ (xn - x)) or t < 1e-12:
                break
            t *= 0.5
        if not fn <= f:  # no decrease left at machine precision: converged if the gradient is negligible
            ok = bool(np.abs(g[free]).max(initial=0.0) < 1e-6)
            return optimize.OptimizeResult(x=x, fun=f, success=ok, message="no further decrease", nit=it)
        done = f - fn <= ftol * max(abs(f), abs(fn), 1.0)
        x, f, g = xn, fn, gn
        if done:
            return optimize.OptimizeResult(x=x, fun=f, success=True, message="relative reduction below ftol", nit=it)
    return optimize.OptimizeResult(x=x, fun=f, success=False, message="max_iter reached", nit=max_iter)


def fit(obj: Objective, x0: np.ndarray | None = None, ftol: float = 1e-13, solver: str = "auto") -> FitResult:
    """Minimise −(ℓ − penalty) from ``x0`` (default: the terms' starts, with a search for the road and
    KDE terms) to relative tolerance ``ftol``: projected Newton (:func:`_newton`) when every term is
    linear in θ and ``solver="auto"``, else (or when Newton stalls, or ``solver="lbfgsb"``) L-BFGS-B;
    covariance = inverse observed information."""
    if solver not in ("auto", "lbfgsb"):
        raise ValueError(f"solver must be 'auto' or 'lbfgsb', got {solver!r}")
    if obj.n == 0:
        raise ValueError("no points left to fit (all off the grid or on structural zeros?)")
    x0 = _start_nonlinear(obj, obj.x0) if x0 is None else np.clip(x0, *np.array(
        [(-np.inf if lo is None else lo, np.inf if hi is None else hi) for lo, hi in obj.bounds]).T.reshape(2, -1))
    if x0.size == 0:
        return FitResult(x0, np.zeros((0, 0)), obj.loglik(x0), 0.0, True, "no free parameters", 0, np.zeros(0, bool))
    lo = np.array([b[0] if b[0] is not None else -np.inf for b in obj.bounds])
    hi = np.array([b[1] if b[1] is not None else np.inf for b in obj.bounds])
    # one BLAS thread: the small dense products are slower threaded (x9 under a loaded machine)
    with threadpool_limits(limits=1, user_api="blas"):
        res = _newton(obj, x0, lo, hi, ftol) if obj.linear and solver == "auto" else None
        if res is None or not res.success:  # the road form (not linear in θ), or Newton stalled: L-BFGS-B
            res = optimize.minimize(obj, x0 if res is None else res.x, jac=True, method="L-BFGS-B", bounds=obj.bounds,
                                    options={"maxiter": 2000, "ftol": ftol, "gtol": 1e-9})
    x = res.x
    at_bound = (x <= lo + 1e-9) | (x >= hi - 1e-9)
    h = obj.hessian(x)
    cov = np.full_like(h, np.nan)
    inner = ~at_bound
    if inner.any():
        try:
            cov[np.ix_(inner, inner)] = np.linalg.inv(h[np.ix_(inner, inner)])
        except np.linalg.LinAlgError:
            cov[np.ix_(inner, inner)] = np.linalg.pinv(h[np.ix_(inner, inner)])
    return FitResult(x, cov, obj.loglik(x), obj.penalty(x)[0], bool(res.success), str(res.message), int(res.nit), at_bound)
