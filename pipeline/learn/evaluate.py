"""Spatial block cross-validation of learned priors against the uniform prior, the naive fit and KDE.

Points are grouped into square blocks (``block_size`` metres); folds hold out whole blocks
(scikit-learn's GroupKFold), so a held-out point's neighbours are held out with it and a model
cannot win by memorising the training points around it. Scores are mean log densities per
held-out point in nats (densities per m²); gains are over the uniform prior on the grid.

The folds run through scikit-learn's ``cross_validate``: :class:`FoldModels` fits every compared
model on a training fold, one scorer per model scores it on the held-out fold.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy.special import ndtr
from sklearn.base import BaseEstimator, clone
from sklearn.model_selection import GroupKFold, cross_validate
from sklearn.neighbors import KernelDensity
from tqdm import tqdm

from pipeline.features.stack import FeatureStack
from pipeline.learn.estimator import PriorEstimator
from pipeline.learn.kde import block_ids, fit_kde_cv
from pipeline.learn.mixture import MixturePrior
from pipeline.learn.select import BackwardSelection
from pipeline.learn.sufficient import check_points
from pipeline.learn.window import BlockWindow

MODELS = ("uniform", "naive", "terrain", "kde", "hybrid")
TIE_NATS = 1e-4
"""Gains per point closer than this are a tie (the same model up to the optimiser's tolerance)."""


@dataclass
class CVResult:
    """Per-fold mean held-out log density (nats per point) of each model, and what was held out."""

    models: tuple[str, ...]
    scores: np.ndarray  # (folds, models)
    n_test: np.ndarray  # (folds,)
    bandwidths: np.ndarray  # (folds,) KDE bandwidth chosen by inner block CV, metres
    block_size: float
    n_points: int
    n_excluded: int
    extra: dict = field(default_factory=dict)

    def gains(self) -> np.ndarray:
        """(folds, models) nats per point over the uniform prior."""
        return self.scores - self.scores[:, [self.models.index("uniform")]]

    def summary(self) -> dict:
        """Per model: mean, fold sd, min and max of the gain over uniform; hybrid's fold wins."""
        g = self.gains()
        out: dict = {
            "folds": int(len(self.n_test)),
            "block_size_m": self.block_size,
            "n_points": self.n_points,
            "n_excluded": self.n_excluded,
            "n_test_per_fold": self.n_test.tolist(),
            "n_blocks_per_fold": [len(b) for b in self.extra["test_blocks"]] if "test_blocks" in self.extra else None,
            "kde_bandwidth_m": self.bandwidths.tolist(),
            "uniform_nats": float(self.scores[:, self.models.index("uniform")].mean()),
            # True: each fold's fits left its held-out blocks out of their observation window (pipeline.learn.window)
            "held_out_blocks_unobserved": any(w is not None for w in self.extra.get("windows", ())),
            "gain_nats": {},
        }
        # weight folds by their held-out points for the pooled mean; report the fold spread unweighted
        w = self.n_test / self.n_test.sum()
        for j, m in enumerate(self.models):
            out["gain_nats"][m] = {
                "pooled": float(w @ g[:, j]),
                "mean": float(g[:, j].mean()),
                "sd": float(g[:, j].std(ddof=1)) if len(g) > 1 else 0.0,
                "min": float(g[:, j].min()),
                "max": float(g[:, j].max()),
                "per_fold": g[:, j].tolist(),
            }
        worst = int(np.argmin(g[:, [self.models.index(m) for m in self.models if m != "uniform"]].max(axis=1)))
        out["worst_fold"] = worst
        if "hybrid" in self.models:
            h = self.models.index("hybrid")
            # within TIE_NATS per point the two are the same model (e.g. a hybrid whose γ is 0)
            out["hybrid_fold_wins"] = {
                m: int((g[:, h] > g[:, j] + TIE_NATS).sum()) for j, m in enumerate(self.models) if m != "hybrid"
            }
            out["hybrid_fold_ties"] = {
                m: int((np.abs(g[:, h] - g[:, j]) <= TIE_NATS).sum()) for j, m in enumerate(self.models) if m != "hybrid"
            }
        return out


def with_model(cv: CVResult, name: str, estimator: BaseEstimator, points: np.ndarray,
               sample_weight: np.ndarray | None = None,
               describe: tuple[str, Callable[[BaseEstimator], object]] | None = None) -> CVResult:
    """``cv`` with a ``name`` column: ``estimator`` (unfitted; anything with ``fit(X, sample_weight=)`` and
    ``score_samples``) fitted on each fold's training points (the other folds' held-out points, so the
    same folds as every other model) and scored on the fold (nats per point, density per m²);
    ``describe = (key, fn)``: ``fn(fitted)`` per fold in ``extra[key]``. A procedure that chooses on its training
    points (a mixture's weights, a feature selection) is thereby nested in the outer CV. When ``cv`` fitted its
    folds in observation windows (``extra["windows"]``), ``estimator``'s ``window`` is set to each fold's."""
    pts = check_points(points)
    index = cv.extra["test_index"]
    windows = cv.extra.get("windows") or [None] * len(index)
    column, described = [], []
    for j, test in enumerate(index):
        train = np.concatenate([i for k, i in enumerate(index) if k != j])
        fitted = clone(estimator)
        if windows[j] is not None:
            fitted.set_params(window=windows[j])
        fitted = fitted.fit(pts[train], sample_weight=None if sample_weight is None else np.asarray(sample_weight)[train])
        ld = fitted.score_samples(pts[test])
        if not np.all(np.isfinite(ld)):
            raise ValueError(f"with_model: {name} gives zero density to {int((~np.isfinite(ld)).sum())} held-out points")
        column.append(float(ld.mean()))
        if describe is not None:
            described.append(describe[1](fitted))
    extra = {**cv.extra, describe[0]: described} if describe is not None else cv.extra
    return dataclasses.replace(cv, models=(*cv.models, name), scores=np.column_stack([cv.scores, column]), extra=extra)


def with_mixture(cv: CVResult, mixture: MixturePrior, points: np.ndarray, sample_weight: np.ndarray | None = None) -> CVResult:
    """``cv`` with a "mixture" column (:func:`with_model`; the weights cross-fitted on each training
    fold's own blocks), its weights per fold in ``extra["mixture_weights"]``."""
    return with_model(cv, "mixture", mixture, points, sample_weight, ("mixture_weights", lambda m: m.weights_.tolist()))


def with_selection(cv: CVResult, selection: BackwardSelection, points: np.ndarray,
                   sample_weight: np.ndarray | None = None) -> CVResult:
    """``cv`` with a "selected" column: the backward selection (:class:`BackwardSelection`, unfitted)
    run on each fold's training points and its kept features scored on the fold; the features kept
    per fold in ``extra["selected_features"]``."""
    return with_model(cv, "selected", selection, points, sample_weight, ("selected_features", lambda m: list(m.features_)))


def kde_log_mass(points: np.ndarray, bandwidth: float, bounds: tuple[float, float, float, float]) -> float:
    """log of the mass a Gaussian KDE of ``points`` (bandwidth metres) puts on the grid's rectangle
    (closed form: per point a product of two normal CDF differences); the KDE baseline is divided by
    it so that it is a density on the grid, like every other model it is compared with."""
    xmin, ymin, xmax, ymax = bounds
    px = ndtr((xmax - points[:, 0]) / bandwidth) - ndtr((xmin - points[:, 0]) / bandwidth)
    py = ndtr((ymax - points[:, 1]) / bandwidth) - ndtr((ymin - points[:, 1]) / bandwidth)
    return float(np.log(np.mean(px * py)))


def default_bandwidths(stack: FeatureStack, n: int = 10) -> np.ndarray:
    """Candidate KDE bandwidths (metres): from two cells to a fifth of the grid's shorter side."""
    g = stack.grid
    short = min(g.width * g.dx, g.height * g.dy)
    return np.geomspace(2 * g.dx, max(short / 5, 4 * g.dx), n)


class FoldModels(BaseEstimator):
    """Every model of :func:`block_cv` fitted on one training fold of points (N, 2) in metres.

    ``estimator`` (a :class:`PriorEstimator` carrying the feature stack) is the terrain model;
    "naive" is its ``method="naive"`` twin; "kde" is scikit-learn's KernelDensity with the
    bandwidth among ``bandwidths`` (metres) chosen by block CV inside the training fold (blocks of
    ``block_size`` metres from the grid's corner); "hybrid" adds the spatial term at that bandwidth,
    γ fitted on KDE values from ``n_folds`` block folds of the training points. ``blocks``: ids of the
    blocks (``block_size`` metres) holding the CV's points; those without a training point were held
    out, and the fits leave them out of their observation window (None: the whole grid is the window).
    """

    def __init__(self, estimator: PriorEstimator, models: tuple[str, ...] = MODELS, bandwidths: np.ndarray | None = None,
                 block_size: float = 2000.0, n_folds: int = 5, blocks: tuple[int, ...] | None = None) -> None:
        self.estimator = estimator
        self.models = models
        self.bandwidths = bandwidths
        self.block_size = block_size
        self.n_folds = n_folds
        self.blocks = blocks

    def fit(self, X: np.ndarray, y: None = None, on_fit: Callable[[int], object] | None = None,
            sample_weight: np.ndarray | None = None) -> FoldModels:
        """Fit the models on X (with ``sample_weight``); ``on_fit(1)`` is called when done (a progress bar's update)."""
        stack = self.estimator.features
        self.kde_: KernelDensity | None = None
        self.kde_log_mass_ = 0.0
        if "kde" in self.models or "hybrid" in self.models:
            self.kde_ = fit_kde_cv(X, block_ids(X, stack.grid.bounds[:2], self.block_size), self.bandwidths)
            self.kde_log_mass_ = kde_log_mass(X, float(self.kde_.bandwidth), stack.grid.bounds)
        window = None
        if self.blocks is not None:
            window = BlockWindow(self.block_size, set(self.blocks) - set(block_ids(X, stack.grid.bounds[:2], self.block_size).tolist()))
        self.window_ = window
        params = {"naive": {"method": "naive"}, "terrain": {},
                  "hybrid": {"spatial_bandwidth": float(self.kde_.bandwidth) if self.kde_ else None,
                             "spatial_block": self.block_size, "spatial_folds": self.n_folds}}
        self.fits_ = {m: clone(self.estimator).set_params(window=window, **params[m]).fit(X, sample_weight=sample_weight)
                      for m in self.models if m in params}
        if on_fit is not None:
            on_fit(1)
        return self

    def score_model(self, model: str, X: np.ndarray) -> float:
        """Mean log density (nats per point, density per m²) of ``model`` at held-out points X;
        ValueError when it gives any of them zero density."""
        if model == "uniform":
            g = self.estimator.features.grid
            return float(-np.log(g.width * g.height * g.cell_area))
        ld = self.kde_.score_samples(X) - self.kde_log_mass_ if model == "kde" else self.fits_[model].score_samples(X)
        if not np.all(np.isfinite(ld)):
            raise ValueError(f"block_cv: model {model} gives zero density to {int((~np.isfinite(ld)).sum())} held-out points")
        return float(ld.mean())


def _held_out(est: FoldModels, X: np.ndarray, y: None = None, *, model: str) -> float:
    return est.score_model(model, X)


def block_cv(
    points: np.ndarray,
    estimator: PriorEstimator,
    n_folds: int = 5,
    block_size: float = 2000.0,
    bandwidths: np.ndarray | None = None,
    models: tuple[str, ...] = MODELS,
    progress: bool = True,
    sample_weight: np.ndarray | None = None,
    window: bool = True,
) -> CVResult:
    """Spatial block CV of ``models`` (a subset of :data:`MODELS`) at points (N, 2) in metres on
    ``estimator``'s feature stack.

    ``estimator`` sets the terrain model (template, penalty, zero policy); the models are those of
    :class:`FoldModels`. The hybrid's bandwidth is the KDE baseline's, chosen by block CV
    inside the training folds. (Choosing it instead by the hybrid's own held-out-fold likelihood
    among wider candidates picked wide kernels with large γ that failed on an isolated held-out
    settlement in Swellendam: one partition of the training blocks is a noisy criterion.) Points off the grid, and (with ``on_zero="drop"``) on
    structural zeros, are excluded from every model's test set alike and counted.
    ``sample_weight`` weights the fits (the KDE baseline and the held-out means are unweighted).
    ``window``: each fold's terrain models are fitted in the observation window that leaves out the
    held-out blocks (:mod:`pipeline.learn.window`: unobserved, not searched and empty); False fits them
    on the whole grid, as if the held-out blocks had been searched and held no targets.
    """
    unknown = set(models) - set(MODELS)
    if unknown or "uniform" not in models:
        raise ValueError(f"models must include 'uniform' and be among {MODELS}, got {models}")
    pts = check_points(points)
    stack = estimator.features
    base = clone(estimator).set_params(spatial_bandwidth=None, method="ml")
    usable = base.fit(pts, sample_weight=sample_weight).used_mask_
    pts = pts[usable]
    fit_params = {"on_fit": None}
    if sample_weight is not None:
        fit_params["sample_weight"] = np.asarray(sample_weight, dtype=np.float64)[usable]
    groups = block_ids(pts, stack.grid.bounds[:2], block_size)
    n_blocks = len(np.unique(groups))
    if n_blocks < n_folds:
        raise ValueError(f"block_cv: only {n_blocks} blocks of {block_size:g} m hold points; need >= n_folds = {n_folds}")
    bw_grid = default_bandwidths(stack) if bandwidths is None else np.asarray(bandwidths, dtype=np.float64)
    folds = FoldModels(base, tuple(models), bw_grid, float(block_size), n_folds,
                       tuple(np.unique(groups).tolist()) if window else None)
    with tqdm(total=n_folds, desc="block CV", unit="fold", disable=not progress) as bar:
        cv = cross_validate(folds, pts, groups=groups, cv=GroupKFold(n_splits=n_folds),
                            scoring={m: partial(_held_out, model=m) for m in models}, params={**fit_params, "on_fit": bar.update},
                            return_estimator=True, return_indices=True, error_score="raise")
    kdes = [e.kde_ for e in cv["estimator"]]
    return CVResult(
        tuple(models), np.column_stack([cv[f"test_{m}"] for m in models]),
        np.array([len(te) for te in cv["indices"]["test"]]),
        np.array([k.bandwidth if k is not None else np.nan for k in kdes], dtype=np.float64), float(block_size),
        int(len(points)), int(len(points) - usable.sum()),
        # which points each fold held out (indices into ``points``), so peers can be scored on the same folds
        {"test_index": [np.flatnonzero(usable)[te] for te in cv["indices"]["test"]],
         # which blocks each fold held out: a fold of one town block and a fold of many scattered blocks
         # test different things, and the scores alone do not say which a fold was
         "test_blocks": [np.unique(groups[te]) for te in cv["indices"]["test"]],
         "windows": [e.window_ for e in cv["estimator"]]},
    )
