"""A mixture of learned priors, its weights chosen on held-out blocks (stacking).

p(x) = Σ_k w_k p_k(x), w on the simplex, each p_k a :class:`pipeline.learn.estimator.PriorEstimator`
(a density per m² on the same grid). The weights maximise the log-likelihood of **cross-fitted**
densities: the training points are dealt into spatial blocks, each component is fitted without a
fold's blocks and scored on them, so w rewards what transfers to unseen blocks, not what a component
memorised (stacking of predictive densities; Yao, Vehtari, Simpson & Gelman, Bayesian Analysis 2018).
The components are then refitted on all points. A mixture keeps every component's mass: where one
component's covariates say nothing (a town model on farmland), the others still hold the density.
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp
from sklearn.base import BaseEstimator, clone
from sklearn.utils.validation import check_is_fitted

from pipeline.learn.estimator import PriorEstimator, cross_fitted
from pipeline.learn.kde import block_folds
from pipeline.learn.sufficient import check_points
from pipeline.learn.window import BlockWindow
from pipeline.prior import TerrainPrior

EM_TOL = 1e-10
"""EM stops when max_k ∂ℓ/∂w_k − 1, an upper bound on how far the mean log-likelihood per point is
below its maximum (nats), falls under this."""
EM_MAX_ITER = 10_000


def simplex_weights(logp: np.ndarray, sample_weight: np.ndarray | None = None) -> np.ndarray:
    """w on the simplex maximising Σ_i s_i log Σ_k w_k exp(logp[i, k]) (EM; the objective is concave
    in w; EM runs until its duality gap is under :data:`EM_TOL`). ``logp`` (N, K) log densities; rows where every
    component is −inf are ValueError."""
    logp = np.asarray(logp, dtype=np.float64)
    n, k = logp.shape
    s = np.ones(n) if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
    if not np.isfinite(logp.max(axis=1)).all():
        raise ValueError("simplex_weights: some points have zero density under every component")
    w = np.full(k, 1.0 / k)
    for _ in range(EM_MAX_ITER):
        with np.errstate(divide="ignore"):
            mix = logsumexp(logp + np.log(w), axis=1)
        grad = s @ np.exp(logp - mix[:, None]) / s.sum()  # ∂/∂w_k of the mean log-likelihood; Σ w_k grad_k = 1
        if grad.max() - 1.0 < EM_TOL:  # the Frank-Wolfe gap: it bounds the distance to the maximum
            break
        w = w * grad
    return w / w.sum()


class MixturePrior(BaseEstimator):
    """A mixture of priors fitted to the same points, its weights chosen by spatial block cross-fitting.

    Parameters
    ----------
    estimators : the components, unfitted :class:`PriorEstimator` on one feature stack (e.g. the same
        features with different covariates: one for towns, one for farmland).
    spatial_block : block side (metres) of the cross-fitting folds.
    n_folds : number of cross-fitting folds (whole blocks each).
    window : the observation window of the points (:class:`pipeline.learn.window.BlockWindow`), given to
        every component (None: each component's own); each cross-fit also leaves its fold's blocks out.

    Fitted attributes: ``weights_`` (K,), ``estimators_`` (the components refitted on all points),
    ``cv_loglik_`` the cross-fitted mean log density per point at ``weights_`` (nats, density per m²).
    """

    def __init__(self, estimators: tuple[PriorEstimator, ...] = (), spatial_block: float = 2000.0, n_folds: int = 4,
                 window: BlockWindow | None = None) -> None:
        self.estimators = estimators
        self.spatial_block = spatial_block
        self.n_folds = n_folds
        self.window = window

    def fit(self, X: np.ndarray, y: None = None, sample_weight: np.ndarray | None = None) -> MixturePrior:
        """Cross-fit every component on the blocks of X (N, 2, metres in the grid's CRS), choose the
        weights on the held-out densities, refit the components on all of X."""
        if len(self.estimators) < 2:
            raise ValueError(f"estimators: a mixture needs at least 2 components, got {len(self.estimators)}")
        if not (self.spatial_block > 0 and self.n_folds >= 2):
            raise ValueError(f"spatial_block must be > 0 and n_folds >= 2, got {self.spatial_block}, {self.n_folds}")
        pts = check_points(X)
        sw = None if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
        grid = self.estimators[0].features.grid
        fold = block_folds(pts, grid.bounds[:2], self.spatial_block, self.n_folds)
        if fold.max() < 1:
            raise ValueError(f"spatial_block: the points fill fewer than 2 blocks of {self.spatial_block:g} m")
        components = [est if self.window is None else clone(est).set_params(window=self.window) for est in self.estimators]
        logp = np.column_stack([cross_fitted(est, pts, fold, sw, self.spatial_block) for est in components])
        usable = np.isfinite(logp.max(axis=1))  # points no component reaches (off the grid, water) carry no information on w
        self.weights_ = simplex_weights(logp[usable], None if sw is None else sw[usable])
        with np.errstate(divide="ignore"):
            mix = logsumexp(logp[usable] + np.log(self.weights_), axis=1)
        self.cv_loglik_ = float(mix.mean() if sw is None else sw[usable] @ mix / sw[usable].sum())
        self.estimators_ = [clone(est).fit(pts, sample_weight=sw) for est in components]
        return self

    @property
    def prior_(self) -> TerrainPrior:
        """Σ w_k r_k on the training grid (density per m²)."""
        check_is_fitted(self)
        priors = [e.prior_ for e in self.estimators_]
        density = sum(w * np.asarray(p.density, dtype=np.float64) for w, p in zip(self.weights_, priors, strict=True))
        meta = {"mixture_weights": [float(w) for w in self.weights_]}
        return TerrainPrior.from_array(density, priors[0].grid, meta)

    def score_samples(self, X: np.ndarray) -> np.ndarray:
        """log p(x) per point of X (N, 2, metres): log Σ_k w_k p_k(x); −inf where every component is zero."""
        check_is_fitted(self)
        logp = np.column_stack([e.score_samples(X) for e in self.estimators_])
        with np.errstate(divide="ignore"):
            return logsumexp(logp + np.log(self.weights_), axis=1)

    def score(self, X: np.ndarray, y: None = None) -> float:
        """Mean log density per point of X (nats, density per m²) over points of positive density."""
        ld = self.score_samples(X)
        ok = np.isfinite(ld)
        if not ok.any():
            raise ValueError("score: every point has zero density under the mixture")
        return float(ld[ok].mean())
