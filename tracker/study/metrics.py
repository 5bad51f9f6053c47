"""Scoring an association-estimation result: the paper's Score (eq. 18), |N̂_D − N_D|, GOSPA, OSPA
and association purity.

A *mixture component* is either a terrain component c⁻¹·G(a, A, x)·r(x) with c = ∫G(a, A, y) r(y) dy
(UT, TT and the perfect-association reference) or a plain Gaussian G(a, A, x) (UU: the uniform prior
taken over all space, as in the paper). Score² = ∫(EstimateMixture − PerfectMixture)² dx is a
quadratic form wᵀKw over the union of both mixtures' components, with weights +1/N̂ for the estimate
and −1/N_D for the reference, and K_ij = ∫ f_i f_j dx. Each K_ij is one Gaussian product:

    G(a_i; a_j, A_i + A_j) · ∫ G(m, M, x) r(x)^p dx / (c_i^{t_i} c_j^{t_j}),   p = t_i + t_j,

with t = 1 for a terrain component, 0 for a plain Gaussian; p = 2 uses the terrace integral against
r², p = 1 against r, p = 0 is analytic. Components with identical report sets cancel exactly, so a
perfect association scores exactly 0. Units: Score is per metre (Score² per m²).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from pipeline.prior import TerrainPrior
from tracker.integrate import Integrator, integrate_checked
from tracker.types.reports import check_gaussians, gaussian_product


class ScoreGram:
    """The Gram matrix K_ij = ∫ f_i f_j dx of a set of mixture components, for scoring many mixtures
    built from the same components (e.g. every τ and variant of one data set) at the cost of one
    batch of terrace integrals.

    ``means`` (n, 2) metres, ``covs`` (n, 2, 2) m², ``terrain`` (n,) bool. Pairs whose analytic upper
    bound G(a_i; a_j, A_i+A_j)·max(r)^p / (c_i^{t_i} c_j^{t_j}) is below ``tol``·min(K_ii, K_jj) are set
    to 0; ``skipped_bound`` (n, n) keeps those bounds so callers can bound the error of a score.
    Attributes: ``K`` (n, n) per m², ``log_c`` (n,) log normalisers (0 for plain Gaussians).
    The components are checked once here; ``integrator`` (an :class:`~tracker.integrate.Integrator`,
    given them and their products) defaults to :func:`tracker.integrate.integrate_checked`. ``needed``
    (n, n) bool, optional: the pairs some scored mixture will use (others are not computed, and
    :meth:`score` refuses weights that would need them).
    """

    def __init__(
        self,
        prior: TerrainPrior,
        means: np.ndarray,
        covs: np.ndarray,
        terrain: np.ndarray,
        tol: float = 1e-9,
        integrator: Integrator | None = None,
        needed: np.ndarray | None = None,
    ) -> None:
        self._integrator = integrator or integrate_checked
        means = np.asarray(means, dtype=np.float64)
        covs = np.asarray(covs, dtype=np.float64)
        terrain = np.asarray(terrain, dtype=bool)
        n = means.shape[0]
        if covs.shape != (n, 2, 2) or terrain.shape != (n,) or means.shape != (n, 2):
            raise ValueError(f"ScoreGram: need means (n, 2), covs (n, 2, 2), terrain (n,); got {means.shape}, {covs.shape}, {terrain.shape}")
        means, covs = check_gaussians(means, covs, "ScoreGram")
        self.n = n
        self.log_c = np.zeros(n)
        if terrain.any():
            c = self._integrate(prior, means[terrain], covs[terrain], False)
            bad = np.flatnonzero(~(c > 0))
            if bad.size:
                idx = np.flatnonzero(terrain)[bad]
                raise ValueError(f"ScoreGram: components {idx[:10].tolist()} have no prior mass (∫G·r = 0); they cannot be normalised")
            self.log_c[terrain] = np.log(c)
        if needed is None:
            self.needed = np.ones((n, n), dtype=bool)
        else:
            self.needed = np.asarray(needed, dtype=bool) | np.eye(n, dtype=bool)
            if self.needed.shape != (n, n):
                raise ValueError(f"ScoreGram: needed must be ({n}, {n}), got {self.needed.shape}")
            self.needed = self.needed | self.needed.T
        # Needed pairs of the upper triangle, diagonal included.
        iu, ju = np.nonzero(np.triu(self.needed))
        m, M, log_g = gaussian_product(means[ju], covs[ju], means[iu], covs[iu])
        p = terrain[iu].astype(int) + terrain[ju].astype(int)
        log_rmax = np.log(prior.max_density)
        log_bound = log_g + p * log_rmax - self.log_c[iu] - self.log_c[ju]
        diag = iu == ju
        values = np.zeros(iu.size)
        values[diag] = self._pair_values(prior, m[diag], M[diag], log_g[diag], p[diag], iu[diag], ju[diag])
        k_diag = np.empty(n)
        k_diag[iu[diag]] = values[diag]
        keep = ~diag & (log_bound >= np.log(tol) + np.log(np.minimum(k_diag[iu], k_diag[ju])))
        values[keep] = self._pair_values(prior, m[keep], M[keep], log_g[keep], p[keep], iu[keep], ju[keep])
        self.K = np.zeros((n, n))
        self.K[iu, ju] = values
        self.K[ju, iu] = values
        skipped = np.where(~diag & ~keep, np.exp(log_bound), 0.0)
        self.skipped_bound = np.zeros((n, n))
        self.skipped_bound[iu, ju] = skipped
        self.skipped_bound[ju, iu] = skipped

    def _integrate(self, prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, squared: bool) -> np.ndarray:
        return np.asarray(self._integrator(prior, means, covs, squared=squared), dtype=np.float64)

    def _pair_values(self, prior, m, M, log_g, p, i, j) -> np.ndarray:
        out = np.exp(log_g - self.log_c[i] - self.log_c[j])
        for power in (1, 2):
            sel = p == power
            if sel.any():
                out[sel] *= self._integrate(prior, m[sel], M[sel], power == 2)
        return out

    def score(self, weights: np.ndarray) -> tuple[float, float]:
        """(sqrt(wᵀKw), an upper bound on |Score² error| from skipped pairs), with ``weights`` (n,).

        wᵀKw is clipped at 0: terrace integrals are approximate, so K need not be exactly PSD.
        """
        w = np.asarray(weights, dtype=np.float64)
        support = np.flatnonzero(w)
        if not self.needed[np.ix_(support, support)].all():
            raise ValueError("ScoreGram.score: the weights use component pairs outside `needed`")
        s2 = float(w @ self.K @ w)
        return float(np.sqrt(max(s2, 0.0))), float(np.abs(w) @ self.skipped_bound @ np.abs(w))


def posterior_means(
    prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, step: float = 0.05, integrator: Integrator | None = None
) -> np.ndarray:
    """Means (n, 2) in metres of the terrain posteriors c⁻¹G(a, A, x)r(x), c(a) = ∫G(a, A, y)r(y)dy.

    Stein's identity ∇_a G = A⁻¹(x − a)G gives E[x] = a + A ∇_a ln c(a); the gradient is a central
    difference of the integral with steps ``step`` standard deviations along x and y. The Gaussians
    are checked once here; ``integrator`` defaults to :func:`tracker.integrate.integrate_checked`.
    """
    means = np.asarray(means, dtype=np.float64)
    covs = np.asarray(covs, dtype=np.float64)
    n = means.shape[0]
    if not n:
        return means.reshape(0, 2).copy()
    means, covs = check_gaussians(means, covs, "posterior_means")
    integrate = integrator or integrate_checked
    h = step * np.sqrt(np.stack([covs[:, 0, 0], covs[:, 1, 1]], axis=1))  # (n, 2) metres
    shifts = np.concatenate([means + [1, 0] * h, means - [1, 0] * h, means + [0, 1] * h, means - [0, 1] * h])
    c = np.asarray(integrate(prior, shifts, np.tile(covs, (4, 1, 1)), squared=False), dtype=np.float64).reshape(4, n)
    if not (c > 0).all():
        bad = np.flatnonzero(~(c > 0).all(axis=0))
        raise ValueError(f"posterior_means: components {bad[:10].tolist()} have no prior mass nearby")
    grad = np.stack([np.log(c[0] / c[1]) / (2 * h[:, 0]), np.log(c[2] / c[3]) / (2 * h[:, 1])], axis=1)
    return means + np.einsum("nij,nj->ni", covs, grad)


def mixture_weights(n_components: int, members: np.ndarray, sign: float = 1.0) -> np.ndarray:
    """Equal weights sign/len(members) on the ``members`` indices of ``n_components`` (zero elsewhere)."""
    w = np.zeros(n_components)
    members = np.asarray(members, dtype=np.intp)
    if members.size:
        np.add.at(w, members, sign / members.size)
    return w


def score(
    prior: TerrainPrior,
    est_means: np.ndarray,
    est_covs: np.ndarray,
    est_terrain: bool,
    ref_means: np.ndarray,
    ref_covs: np.ndarray,
    ref_terrain: bool = True,
    integrator: Integrator | None = None,
) -> float:
    """The paper's Score (eq. 18, per metre) of an estimate against the perfect-association reference;
    each is an equally weighted mixture of its components (terrain or plain Gaussian, see module doc)."""
    n_e, n_r = len(est_means), len(ref_means)
    means = np.concatenate([np.reshape(est_means, (n_e, 2)), np.reshape(ref_means, (n_r, 2))])
    covs = np.concatenate([np.reshape(est_covs, (n_e, 2, 2)), np.reshape(ref_covs, (n_r, 2, 2))])
    terrain = np.array([est_terrain] * n_e + [ref_terrain] * n_r, dtype=bool)
    n = n_e + n_r
    w = mixture_weights(n, np.arange(n_e)) + mixture_weights(n, np.arange(n_e, n), -1.0)
    # Identical components (same density) are merged so their weights cancel exactly, as the
    # experiment's report-set keys do; otherwise Score² of equal mixtures is rounding noise.
    keys = np.column_stack([means, covs.reshape(n, 4), terrain])
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    merged = np.zeros(first.size)
    np.add.at(merged, inverse.ravel(), w)
    gram = ScoreGram(prior, means[first], covs[first], terrain[first], integrator=integrator)
    return gram.score(merged)[0]


def _check_points(points: np.ndarray, what: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2:
        raise ValueError(f"{what}: points must be (N, d), got shape {points.shape}")
    return points


def _capped_costs(x: np.ndarray, y: np.ndarray, c: float, p: float) -> np.ndarray:
    d = np.sqrt(((x[:, None, :] - y[None, :, :]) ** 2).sum(axis=-1))
    return np.minimum(d, c) ** p


def gospa(estimates: np.ndarray, truth: np.ndarray, c: float, p: float = 2.0) -> dict[str, float]:
    """GOSPA with α = 2 (Rahmathullah, García-Fernández, Svensson 2017) between point sets in metres:
    min over assignments of Σ_assigned d^p + c^p/2·(#missed + #false), to the power 1/p.

    Returns ``gospa`` (m) and its parts: ``localisation`` (Σ d^p over assigned pairs with d < c),
    ``missed`` and ``false`` counts.
    """
    x = _check_points(estimates, "gospa estimates")
    y = _check_points(truth, "gospa truth")
    if not (c > 0 and p >= 1):
        raise ValueError(f"gospa needs c > 0 and p >= 1, got c={c}, p={p}")
    loc, assigned = 0.0, 0
    if x.shape[0] and y.shape[0]:
        cost = _capped_costs(x, y, c, p)
        rows, cols = linear_sum_assignment(cost)
        # A pair at distance >= c costs as much as one miss plus one false target: count it that way.
        real = cost[rows, cols] < c**p
        loc = float(cost[rows, cols][real].sum())
        assigned = int(real.sum())
    missed = y.shape[0] - assigned
    false = x.shape[0] - assigned
    total = loc + 0.5 * c**p * (missed + false)
    return {"gospa": total ** (1.0 / p), "localisation": loc, "missed": float(missed), "false": float(false)}


def ospa(estimates: np.ndarray, truth: np.ndarray, c: float, p: float = 2.0) -> float:
    """OSPA (Schuhmacher, Vo, Vo 2008) in metres: with m <= n the smaller and larger set sizes,
    ((min_π Σ_{i<=m} min(d, c)^p + c^p (n − m)) / n)^(1/p); 0 for two empty sets."""
    x = _check_points(estimates, "ospa estimates")
    y = _check_points(truth, "ospa truth")
    if not (c > 0 and p >= 1):
        raise ValueError(f"ospa needs c > 0 and p >= 1, got c={c}, p={p}")
    m, n = sorted((x.shape[0], y.shape[0]))
    if n == 0:
        return 0.0
    total = c**p * (n - m)
    if m:
        cost = _capped_costs(x, y, c, p)
        rows, cols = linear_sum_assignment(cost)
        total += float(cost[rows, cols].sum())
    return float((total / n) ** (1.0 / p))


def purity(assignment: np.ndarray, truth: np.ndarray) -> float:
    """Association purity: the share of reports that belong to their hypothesis's majority true target,
    Σ_q max_j #{k : assignment_k = q, truth_k = j} / K. 1 when no hypothesis mixes targets."""
    assignment = np.asarray(assignment, dtype=np.int64)
    truth = np.asarray(truth, dtype=np.int64)
    if assignment.shape != truth.shape or assignment.ndim != 1:
        raise ValueError(f"purity: assignment and truth must be equal-length 1-D arrays, got {assignment.shape}, {truth.shape}")
    if not assignment.size:
        return 1.0
    pairs, counts = np.unique(np.stack([assignment - assignment.min(), truth]), axis=1, return_counts=True)
    best = np.zeros(pairs[0].max() + 1, dtype=np.int64)
    np.maximum.at(best, pairs[0], counts)
    return float(best.sum() / assignment.size)

