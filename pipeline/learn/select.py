"""Choosing features by spatial block cross-validation: backward elimination.

Starting from every feature of an estimator, each step refits the model without one feature at a
time and scores it by the pooled held-out log density of spatial block folds (each point scored by
the model fitted without its fold's blocks, :func:`cross_fitted`). The feature whose removal scores
best is dropped while that beats the current set; the search stops when every removal scores lower.
Features whose template has structural zeros (a water mask) are never candidates: they say where
targets cannot be, not how a covariate acts, and dropping one would change which points are scored.

The selection is fitted without the defensive mixture and tempering (those calibrate a chosen
model); the chosen features are then fitted with the estimator's own settings. Nested inside an
outer spatial block CV (:func:`pipeline.learn.evaluate.with_model`), the held-out gain measures the
whole procedure, not the set it picked on all the data.
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, clone
from sklearn.utils.validation import check_is_fitted
from tqdm import tqdm

from pipeline.learn.estimator import PriorEstimator, cross_fitted, with_features
from pipeline.learn.kde import block_folds
from pipeline.learn.sufficient import check_points
from pipeline.learn.window import BlockWindow
from pipeline.prior import TerrainPrior


class BackwardSelection(BaseEstimator):
    """Backward elimination of a :class:`PriorEstimator`'s features by spatial block CV.

    Parameters
    ----------
    estimator : the unfitted estimator with every candidate feature (``feature_names`` or its defaults).
    spatial_block : block side of the selection's folds, metres.
    n_folds : number of folds (whole blocks each; fewer when fewer blocks hold points).
    progress : show a tqdm bar over the candidate fits.
    window : the observation window of the points (:class:`pipeline.learn.window.BlockWindow`), given to
        every fit (None: the estimator's own); each cross-fit also leaves its fold's blocks out.

    Fitted attributes: ``features_`` (the kept feature names, in the estimator's order), ``fixed_``
    (features never dropped: those with structural zeros), ``path_`` (one dict per step: ``features``,
    ``score`` and ``candidates``, the score without each candidate; scores are held-out mean log
    densities in nats per point, density per m²), ``score_`` (the kept set's), ``estimator_`` (the
    kept features fitted on all points with the estimator's settings).
    """

    def __init__(self, estimator: PriorEstimator | None = None, spatial_block: float = 2000.0, n_folds: int = 5,
                 progress: bool = False, window: BlockWindow | None = None) -> None:
        self.estimator = estimator
        self.spatial_block = spatial_block
        self.n_folds = n_folds
        self.progress = progress
        self.window = window

    def fit(self, X: np.ndarray, y: None = None, sample_weight: np.ndarray | None = None) -> BackwardSelection:
        """Select on points X (N, 2, metres in the grid's CRS), weighted by ``sample_weight`` (N,) if given."""
        if self.estimator is None:
            raise ValueError("estimator: BackwardSelection needs a PriorEstimator")
        if not (self.spatial_block > 0 and self.n_folds >= 2):
            raise ValueError(f"spatial_block must be > 0 and n_folds >= 2, got {self.spatial_block}, {self.n_folds}")
        pts = check_points(X)
        sw = None if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
        estimator = self.estimator if self.window is None else clone(self.estimator).set_params(window=self.window)
        base = clone(estimator).set_params(defensive=None, temper=None)
        full = clone(base).fit(pts, sample_weight=sw)
        names = [t.feature for t in full.terms_]
        self.fixed_ = tuple(t.feature for t in full.terms_ if t.zeros)
        fold = block_folds(pts, full.features.grid.bounds[:2], self.spatial_block, self.n_folds)
        if fold.max() < 1:
            raise ValueError(f"spatial_block: the points fill fewer than 2 blocks of {self.spatial_block:g} m")
        w = np.ones(len(pts)) if sw is None else sw
        first = cross_fitted(base, pts, fold, sw, self.spatial_block)
        usable = np.isfinite(first)  # off the grid or on a structural zero under every candidate alike

        def score(features: list[str], ld: np.ndarray | None = None) -> float:
            if ld is None:
                ld = cross_fitted(with_features(base, features), pts, fold, sw, self.spatial_block)
            return float(w[usable] @ ld[usable] / w[usable].sum())

        kept, current = list(names), score(names, first)
        self.path_ = []
        with tqdm(desc="backward selection", unit="fit", disable=not self.progress) as bar:
            while True:
                candidates = [f for f in kept if f not in self.fixed_]
                if len(candidates) <= 1:  # keep one covariate: without any the model is the uniform prior
                    self.path_.append({"features": list(kept), "score": current, "candidates": {}})
                    break
                scores = {}
                for f in candidates:
                    scores[f] = score([k for k in kept if k != f])
                    bar.update()
                self.path_.append({"features": list(kept), "score": current, "candidates": scores})
                best = max(scores, key=scores.__getitem__)
                if not scores[best] > current:
                    break
                kept.remove(best)
                current = scores[best]
        self.features_, self.score_ = tuple(kept), current
        self.estimator_ = with_features(estimator, self.features_).fit(pts, sample_weight=sw)
        return self

    @property
    def prior_(self) -> TerrainPrior:
        """The prior of the kept features (density per m²)."""
        check_is_fitted(self)
        return self.estimator_.prior_

    def score_samples(self, X: np.ndarray) -> np.ndarray:
        """log p(x) per point of X (N, 2, metres) under the kept features' fit."""
        check_is_fitted(self)
        return self.estimator_.score_samples(X)

    def score(self, X: np.ndarray, y: None = None) -> float:
        """Mean log density per point of X (nats, density per m²); see :meth:`PriorEstimator.score`."""
        check_is_fitted(self)
        return self.estimator_.score(X)
