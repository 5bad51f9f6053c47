"""PriorEstimator: per-feature likelihoods fitted to past target locations (scikit-learn style).

Targets are an inhomogeneous Poisson process with intensity λ(x) = exp(β₀ + Σ_t log r_t(F_t(x)));
``method="ml"`` maximises its (penalised) likelihood jointly over all terms on sufficient statistics
(:mod:`pipeline.learn.sufficient`, :mod:`pipeline.learn.poisson`); ``method="naive"`` fits each term alone on
its marginal (for a categorical term: the share of points over the share of area per category),
which is the ML fit only when the features are independent over the grid.

X everywhere is the (N, 2) array of target points, x and y in metres in the grid's CRS, so
scikit-learn's ``model_selection`` (``cross_val_score``, ``GroupKFold`` on spatial blocks, ``GridSearchCV``)
works on it directly. The grid pass of the sufficient statistics is cached per feature stack
(:func:`pipeline.learn.sufficient.cached_cell_stats`), so refits on other points (CV folds, clones) skip it.

Example::

    est = PriorEstimator(features=stack, template=config.model).fit(points_xy_m)
    est.likelihoods_["road_distance"]   # {"rmd": 97.1, "mv": 0.11}
    est.model_.write_toml("model.toml")  # what `terrain-prior build --model` reads
    est.score(test_xy_m)                 # mean log density, nats per point (density per m²)
    cross_val_score(PriorEstimator(features=stack), xy_m, groups=block_ids(xy_m, origin, 2000.0), cv=GroupKFold(5))
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from functools import cached_property

import numpy as np
from sklearn.base import BaseEstimator, clone
from sklearn.utils.validation import check_is_fitted

from pipeline.features.stack import Feature, FeatureStack
from pipeline.learn.kde import block_folds, log_kde_feature
from pipeline.learn.poisson import Objective, fit, kde_logr, term_params
from pipeline.learn.sufficient import (
    CONTINUOUS_FORMS,
    DISCRETE_FORMS,
    NODATA_INDEX,
    CellStats,
    PointStats,
    Term,
    cached_cell_stats,
    check_points,
    point_stats,
    with_range,
)
from pipeline.prior.likelihood import (
    BinnedLikelihood,
    CategoricalLikelihood,
    LikelihoodModel,
    RoadDistanceLikelihood,
)
from pipeline.prior.terrain import TerrainPrior

SPATIAL = "spatial_kde"
"""Name of the hybrid's learned spatial feature: log(KDE of the training points / uniform density + KDE_EPS)."""
SPATIAL_BIN = 0.05
"""Fine-bin width of the log-KDE feature; r varies at most by a factor exp(γ·0.05) across a bin."""
Z95 = 1.959963984540054


def _template_values(term: Term, table, flexible: dict) -> list[float | None]:
    """The template's likelihood per level of a discrete term (None where it gives none)."""
    if term.form == "categorical" and table is not None:
        vals = [table.values.get(lv, table.values.get(str(int(c)))) for lv, c in zip(term.levels, term.codes, strict=True)]
        return [None if v is None else float(v) for v in vals]
    if term.form == "binned" and isinstance(table, BinnedLikelihood) and term.feature not in flexible:
        return [float(v) for v in table.values]
    return [None] * term.n_levels


def template_start(term: Term, template: LikelihoodModel | None, flexible: dict | None = None) -> tuple[Term, dict]:
    """``term`` with the template's structural zeros (values 0), and its start values for the fit."""
    table = template.terms.get(term.feature) if template else None
    if term.form in DISCRETE_FORMS:
        vals = _template_values(term, table, flexible or {})
        zeros = frozenset(k for k, v in enumerate(vals) if v == 0)
        return dataclasses.replace(term, zeros=zeros), {"logr": np.array([np.log(v) if v else 0.0 for v in vals])}
    if isinstance(table, RoadDistanceLikelihood):
        return term, {"rmd": table.rmd, "mv": table.mv}
    return term, {}


def make_terms(
    stack: FeatureStack,
    template: LikelihoodModel | None,
    feature_names: tuple[str, ...] | None,
    flexible: dict[str, list[float]] | None,
    bin_width: float | None,
    n_bins: int,
) -> tuple[list[Term], list[dict]]:
    """Terms to fit and their start values, following the template's forms and structural zeros.

    Without a template: categorical features -> categorical terms, continuous features in metres ->
    the road form, other continuous features -> ``n_bins`` quantile bins. ``flexible`` replaces a
    feature's form by bins with these left edges (feature units).
    """
    names = list(feature_names or (template.terms if template else [f.name for f in stack]))
    flexible = flexible or {}
    terms = []
    for name in names:
        f = stack[name]
        table = template.terms.get(name) if template else None
        nodata = float(getattr(table, "nodata", 1.0))
        if f.kind == "categorical":
            if table is not None and not isinstance(table, CategoricalLikelihood):
                raise ValueError(f"feature {name!r} is categorical but its template table is {type(table).__name__}")
            codes = tuple(int(c) for c in f.codes())
            terms.append(Term(name, "categorical", tuple(f.label(c) for c in codes), codes, nodata=nodata))
        elif name in flexible or isinstance(table, BinnedLikelihood) or (table is None and f.units != "m"):
            if name in flexible:
                edges = list(flexible[name])
            elif isinstance(table, BinnedLikelihood):
                edges = list(table.edges)
            else:
                finite = f.values[np.isfinite(f.values)]
                edges = list(np.unique(np.quantile(finite, np.linspace(0, 1, n_bins + 1)[:-1])))
            levels = tuple(f"{e:g}" for e in edges)
            terms.append(Term(name, "binned", levels, edges=tuple(float(e) for e in edges), nodata=nodata))
        else:
            width = bin_width or stack.grid.dx / 4.0
            terms.append(with_range(Term(name, "road", bin_width=width, nodata=nodata), f.values))
    pairs = [template_start(t, template, flexible) for t in terms]
    terms, starts = [p[0] for p in pairs], [p[1] for p in pairs]
    return terms, starts


class PriorEstimator(BaseEstimator):
    """Fit per-feature likelihoods r_t to past target points (metres, the grid's CRS).

    Parameters
    ----------
    features : the :class:`FeatureStack` the points are fitted on and scored on (None only for
        :meth:`fit_stats`). Clones share it (not copied): its arrays must not change in place.
    template : hand-set :class:`LikelihoodModel` giving each feature's form (categorical, road,
        binned edges), structural zeros (values 0, fixed, not fitted) and start values.
    feature_names : feature names to use (default: the template's, else all).
    method : ``"ml"`` (joint Poisson-process maximum likelihood) or ``"naive"`` (each term on its marginal).
    penalty_sd : σ of the Gaussian prior on each categorical / binned log-likelihood, nats.
        Default 3: a factor e³ ≈ 20 is one σ, so the penalty only bites for levels with few points.
    smooth_sd : τ of the Gaussian prior on differences of log r between adjacent bins of a binned term.
    on_zero : points on a structural zero: ``"drop"`` them (counted) or ``"soften"`` every zero to ``soften``.
    soften : likelihood (relative to the reference level) given to structural zeros when softened.
    flexible : feature -> left bin edges: fit that feature as bins instead of the road form.
    spatial_bandwidth : metres, or a list of candidates; when set, the hybrid: one more term
        (α + (1−α)·k)^γ, k the KDE of the training points over the uniform density, α =
        ``spatial_floor``, γ >= 0 fitted on each training point's KDE value from the points outside its
        group: squares of ``spatial_block`` metres dealt into ``spatial_folds`` folds, the geometry
        of spatial block CV (leave-one-out when ``spatial_block`` is None). With several
        candidates, the one whose fit has the highest log-likelihood on those held-out values wins
        (``spatial_bandwidth_``, ``bandwidth_loglik_``).
    spatial_block, spatial_folds : metres and a count; see ``spatial_bandwidth``.
    spatial_floor : α, the fixed share of the uniform density in the KDE term. Default 0.01: a
        target far from every past one costs at most γ·log(1/0.01) ≈ 4.6·γ nats over the terrain fit.
    bin_width : fine-bin width of continuous terms in feature units (default: a quarter cell).
    n_bins : quantile bins of continuous non-distance features without a template.
    """

    def __init__(
        self,
        features: FeatureStack | None = None,
        template: LikelihoodModel | None = None,
        feature_names: tuple[str, ...] | None = None,
        method: str = "ml",
        penalty_sd: float = 3.0,
        smooth_sd: float = 1.0,
        on_zero: str = "drop",
        soften: float = 1e-3,
        flexible: dict[str, list[float]] | None = None,
        spatial_bandwidth: float | list[float] | None = None,
        spatial_block: float | None = None,
        spatial_folds: int = 5,
        spatial_floor: float = 0.01,
        bin_width: float | None = None,
        n_bins: int = 8,
    ) -> None:
        self.features = features
        self.template = template
        self.feature_names = feature_names
        self.method = method
        self.penalty_sd = penalty_sd
        self.smooth_sd = smooth_sd
        self.on_zero = on_zero
        self.soften = soften
        self.flexible = flexible
        self.spatial_bandwidth = spatial_bandwidth
        self.spatial_block = spatial_block
        self.spatial_folds = spatial_folds
        self.spatial_floor = spatial_floor
        self.bin_width = bin_width
        self.n_bins = n_bins

    def __sklearn_clone__(self) -> PriorEstimator:
        """A clone sharing the feature stack: it is the data the points live on, not a setting, and
        a deep copy per CV fold would copy the grid and miss its cached grid pass."""
        params = self.get_params(deep=False)
        return type(self)(**{k: v if k == "features" else clone(v, safe=False) for k, v in params.items()})

    # ----------------------------------------------------------------------------------- fit
    def _check_params(self) -> None:
        if self.method not in ("ml", "naive"):
            raise ValueError(f"method must be 'ml' or 'naive', got {self.method!r}")
        if self.on_zero not in ("drop", "soften"):
            raise ValueError(f"on_zero must be 'drop' or 'soften', got {self.on_zero!r}")
        if not (self.penalty_sd > 0 and self.smooth_sd >= 0):
            raise ValueError(f"penalty_sd must be > 0 and smooth_sd >= 0, got {self.penalty_sd}, {self.smooth_sd}")
        if self.on_zero == "soften" and not 0 < self.soften < 1:
            raise ValueError(f"soften must be in (0, 1), got {self.soften}")

    def fit(self, X: np.ndarray, y: None = None) -> PriorEstimator:
        """Fit to points X (N, 2) in metres in the grid's CRS (``y`` is ignored). Points off the grid are
        dropped and counted; points on structural zeros are dropped or the zeros softened (``on_zero``)."""
        self._check_params()
        if self.features is None:
            raise ValueError("PriorEstimator.fit: no feature stack; give PriorEstimator(features=stack, ...)")
        pts = check_points(X)
        if self.spatial_bandwidth is not None and np.ndim(self.spatial_bandwidth) > 0:
            return self._fit_bandwidths(pts)
        t0, c0 = time.perf_counter(), time.process_time()
        features = stack = self.features
        self.spatial_bandwidth_ = float(self.spatial_bandwidth) if self.spatial_bandwidth else None
        terms, _ = make_terms(features, self.template, self.feature_names, self.flexible, self.bin_width, self.n_bins)
        loo = None
        if self.spatial_bandwidth_:
            inside = features.grid.contains(pts[:, 0], pts[:, 1])
            groups = None
            if self.spatial_block:
                groups = block_folds(pts[inside], features.grid.bounds[:2], self.spatial_block, self.spatial_folds)
            logk, loo_in = log_kde_feature(features.grid, pts[inside], self.spatial_bandwidth_, groups)
            loo = np.full(len(pts), np.nan)
            loo[inside] = loo_in
            stack = FeatureStack(features.grid, dict(features.features))
            stack.add(Feature(SPATIAL, logk, "continuous", "log(KDE over uniform)"))
            terms.append(with_range(Term(SPATIAL, "kde", bin_width=SPATIAL_BIN), logk))
        cells = cached_cell_stats(stack, tuple(terms))
        pass_times = (time.perf_counter() - t0, time.process_time() - c0)
        pstats = point_stats(stack, tuple(terms), pts)
        if loo is not None:
            pstats.value[:, -1] = loo
        self.stack_ = stack
        self.n_features_in_ = 2
        return self._fit_from_stats(cells, pstats, t0, c0, pass_times)

    def fit_stats(self, cells: CellStats, points: PointStats) -> PriorEstimator:
        """Fit from precomputed statistics: ``cells`` (e.g. from
        :func:`pipeline.tiled.learn.tiled_cell_stats`, so no process holds the grid) and the points'
        levels and values on the same terms (e.g. :func:`pipeline.tiled.learn.tiled_point_stats`).

        The same fit as :meth:`fit` on the grid those statistics came from (the terms carry the
        template's zeros; start values come from ``template``). Without the grid there is no
        ``prior_`` (so no :meth:`score` / :meth:`score_samples`) and no hybrid spatial term.
        """
        self._check_params()
        if self.spatial_bandwidth is not None:
            raise ValueError("fit_stats: the hybrid spatial term needs the grid (spatial_bandwidth must be None)")
        if tuple(points.terms) != tuple(cells.terms):
            raise ValueError(f"fit_stats: point statistics are on terms {[t.feature for t in points.terms]}, "
                             f"cell statistics on {[t.feature for t in cells.terms]}; they must be the same terms")
        t0, c0 = time.perf_counter(), time.process_time()
        self.spatial_bandwidth_ = None
        self.stack_ = None
        self.n_features_in_ = 2
        return self._fit_from_stats(cells, points, t0, c0, (np.nan, np.nan))  # the pass ran elsewhere

    def _fit_from_stats(self, cells: CellStats, pstats: PointStats, t0: float, c0: float,
                        pass_times: tuple[float, float]) -> PriorEstimator:
        """The fit proper, shared by :meth:`fit` and :meth:`fit_stats`: reference levels, parameters,
        the optimisation and every fitted attribute."""
        terms = [_with_reference(t, cells.level_area(k)) for k, t in enumerate(cells.terms)]
        cells = dataclasses.replace(cells, terms=tuple(terms))
        pstats = dataclasses.replace(pstats, terms=tuple(terms))
        starts = [{"alpha": self.spatial_floor} if t.form == "kde" else template_start(t, self.template, self.flexible)[1]
                  for t in terms]
        soften = self.soften if self.on_zero == "soften" else None
        params = [
            term_params(t, cells.level_area(k), soften, _shift(starts[k], t), cells.bin_value(k) if t.form in CONTINUOUS_FORMS else None)
            for k, t in enumerate(terms)
        ]
        keep, counts = _usable(pstats, params, soften is not None)
        used = pstats.subset(keep)
        if self.method == "ml":
            results = [fit(Objective(cells, used, params, list(range(len(terms))), self.penalty_sd, self.smooth_sd))]
        else:
            results = [fit(Objective(cells, used, params, [k], self.penalty_sd, self.smooth_sd)) for k in range(len(terms))]
        x = np.concatenate([r.x for r in results])
        cov = _block_diag([r.cov for r in results])
        full = Objective(cells, used, params, list(range(len(terms))), self.penalty_sd, self.smooth_sd)
        n_points = len(keep)
        self.terms_ = terms
        self.params_ = params
        self.theta_ = x
        self.cov_ = cov
        self.cell_stats_ = cells
        self.point_stats_ = used
        self.used_mask_ = keep
        self.n_points_ = n_points
        self.n_used_ = int(keep.sum())
        self.n_off_grid_ = counts["off_grid"]
        self.n_on_zero_ = counts["on_zero"]
        self.on_zero_detail_ = counts["detail"]
        self.loglik_ = full.loglik(x)
        self.penalty_ = full.penalty(x)[0]
        self.fit_results_ = results
        self.fit_seconds_ = time.perf_counter() - t0
        self.pass_seconds_, self.pass_cpu_seconds_ = pass_times
        self.fit_cpu_seconds_ = time.process_time() - c0
        self._describe(full)
        self.bandwidth_loglik_ = {self.spatial_bandwidth_: self.loglik_} if self.spatial_bandwidth_ else {}
        self.__dict__.pop("prior_", None)
        if counts["off_grid"] or counts["on_zero"]:
            warnings.warn(
                f"PriorEstimator.fit: {counts['off_grid']} of {n_points} points off the grid (dropped), "
                f"{counts['on_zero']} on structural zeros {counts['detail']} "
                f"({'dropped' if soften is None else f'zeros softened to {soften}'})",
                stacklevel=3,
            )
        return self

    def _fit_bandwidths(self, points: np.ndarray) -> PriorEstimator:
        """Fit the hybrid at each candidate bandwidth; keep the best held-out-value log-likelihood."""
        fits = [clone(self).set_params(spatial_bandwidth=float(b)).fit(points) for b in self.spatial_bandwidth]
        best = max(fits, key=lambda e: e.loglik_)
        self.__dict__.pop("prior_", None)
        self.__dict__.update({k: v for k, v in best.__dict__.items() if k.endswith("_") and not k.startswith("_")})
        self.bandwidth_loglik_ = {float(e.spatial_bandwidth): e.loglik_ for e in fits}
        return self

    def _describe(self, obj: Objective) -> None:
        """likelihoods_, stderr_, ci_ and model_ from theta_ and cov_."""
        se_all = np.sqrt(np.clip(np.diag(self.cov_), 0, None)) if self.cov_.size else np.zeros(0)
        self.likelihoods_, self.stderr_, self.ci_ = {}, {}, {}
        table_terms = {}
        for j, (th, k) in enumerate(zip(obj.split(self.theta_), obj.active, strict=True)):
            p = self.params_[k]
            t = p.term
            se = se_all[obj.offsets[j] : obj.offsets[j + 1]]
            if t.form in DISCRETE_FORMS:
                lut = p.lut(th)[:-1]
                se_lvl = np.full(t.n_levels, np.nan)
                se_lvl[p.free] = se
                se_lvl[t.reference] = 0.0
                vals = np.exp(lut)
                lo, hi = np.exp(lut - Z95 * se_lvl), np.exp(lut + Z95 * se_lvl)
                self.likelihoods_[t.feature] = dict(zip(t.levels, vals.tolist(), strict=True))
                self.stderr_[t.feature] = dict(zip(t.levels, se_lvl.tolist(), strict=True))
                self.ci_[t.feature] = {lv: (a, b) for lv, a, b in zip(t.levels, lo.tolist(), hi.tolist(), strict=True)}
                if t.form == "categorical":
                    table_terms[t.feature] = CategoricalLikelihood(dict(zip(t.levels, vals.tolist(), strict=True)), t.nodata)
                else:
                    table_terms[t.feature] = BinnedLikelihood(list(t.edges), vals.tolist(), t.nodata)
            elif t.form == "road":
                rmd, mv = float(np.exp(th[0])), float(th[1])
                self.likelihoods_[t.feature] = {"rmd": rmd, "mv": mv}
                self.stderr_[t.feature] = {"rmd": rmd * float(se[0]), "mv": float(se[1])}
                self.ci_[t.feature] = {
                    "rmd": (float(np.exp(th[0] - Z95 * se[0])), float(np.exp(th[0] + Z95 * se[0]))),
                    "mv": (float(max(mv - Z95 * se[1], 0.0)), float(min(mv + Z95 * se[1], 1.0))),
                }
                table_terms[t.feature] = RoadDistanceLikelihood(rmd, mv, t.nodata)
            else:
                self.likelihoods_[t.feature] = {"gamma": float(th[0]), "alpha": p.alpha}
                self.stderr_[t.feature] = {"gamma": float(se[0]), "alpha": 0.0}
                self.ci_[t.feature] = {"gamma": (float(max(th[0] - Z95 * se[0], 0.0)), float(th[0] + Z95 * se[0])),
                                       "alpha": (p.alpha, p.alpha)}
        meta = {
            "learned": {
                "method": self.method,
                "n_points": self.n_points_,
                "n_used": self.n_used_,
                "n_off_grid": self.n_off_grid_,
                "n_on_zero": self.n_on_zero_,
                "on_zero": self.on_zero,
                "penalty_sd": self.penalty_sd,
                "smooth_sd": self.smooth_sd,
                "loglik_nats": self.loglik_,
            }
        }
        if self.spatial_bandwidth_:
            meta["learned"]["spatial_term"] = (
                f"hybrid: also (alpha + (1 - alpha) * KDE / uniform)^gamma, KDE bandwidth {self.spatial_bandwidth_:g} m, "
                f"gamma = {self.likelihoods_[SPATIAL]['gamma']:.4g}, alpha = {self.likelihoods_[SPATIAL]['alpha']:.4g}; "
                "not representable in this table"
            )
        self.model_ = LikelihoodModel(table_terms, meta)

    # --------------------------------------------------------------------------- prediction
    @cached_property
    def prior_(self) -> TerrainPrior:
        """The fitted prior (density per m²) on the training grid, built on first use."""
        if self.stack_ is None:
            raise ValueError("prior_: this estimator was fitted from statistics (fit_stats), without the grid; "
                             "build the prior with `terrain-prior build --model` (tiled for large grids)")
        r = self.model_.evaluate(self.stack_)
        if self.spatial_bandwidth_:
            p = self.likelihoods_[SPATIAL]
            logr = kde_logr(self.stack_[SPATIAL].values, p["gamma"], p["alpha"])
            r *= np.exp(logr - logr.max())
        return TerrainPrior.from_array(r, self.stack_.grid, self.model_.to_dict())

    def score_samples(self, X: np.ndarray) -> np.ndarray:
        """log p(x) per point of X (N, 2) (metres; log of a density per m²); −inf off the grid or on an
        unsoftened structural zero."""
        check_is_fitted(self)
        pts = check_points(X)
        with np.errstate(divide="ignore"):
            return np.log(self.prior_.density_at(pts[:, 0], pts[:, 1]))

    def score(self, X: np.ndarray, y: None = None) -> float:
        """Mean log density per point of X (nats; density per m²) over points where it is positive;
        points off the grid or on structural zeros are left out with a warning giving their count.

        The mean (not the sum) so that scores of folds with different numbers of held-out points
        are comparable, as ``cross_val_score`` averages them; it is what :func:`pipeline.learn.evaluate.block_cv`
        reports per fold."""
        ld = self.score_samples(X)
        ok = np.isfinite(ld)
        if not ok.all():
            warnings.warn(f"score: {int((~ok).sum())} of {len(ld)} points have zero density (off grid or on a structural zero); left out", stacklevel=2)
        if not ok.any():
            raise ValueError("score: every point has zero density under the fitted prior")
        return float(ld[ok].mean())

    def empirical(self) -> dict[str, dict]:
        """Per term and level: share of the used points over share of the area (the naive ratio),
        normalised like the fitted values (reference level 1), with counts and areas (m²)."""
        out = {}
        n = max(self.n_used_, 1)
        for k, t in enumerate(self.terms_):
            if t.form not in DISCRETE_FORMS and t.form != "road":
                continue
            idx = self.point_stats_.index[:, k]
            area = self.cell_stats_.level_area(k)
            cnt = np.bincount(idx[idx >= 0], minlength=t.n_levels).astype(float)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = (cnt / n) / (area / self.cell_stats_.total_area)
            if t.form in DISCRETE_FORMS:
                ratio = ratio / ratio[t.reference] if ratio[t.reference] > 0 else ratio
                out[t.feature] = {"levels": list(t.levels), "count": cnt.tolist(), "area_m2": area.tolist(), "ratio": ratio.tolist()}
            else:
                out[t.feature] = {"bin_lo": (t.lo + t.bin_width * np.arange(t.n_levels)).tolist(), "bin_width": t.bin_width,
                                  "count": cnt.tolist(), "area_m2": area.tolist(), "ratio": ratio.tolist()}
        return out


# ------------------------------------------------------------------------------- helpers
def _with_reference(term: Term, level_area: np.ndarray) -> Term:
    """Discrete terms: the reference (r = 1) is the non-zero level with the most area."""
    if term.form not in DISCRETE_FORMS:
        return term
    area = np.where([k in term.zeros for k in range(term.n_levels)], -1.0, level_area)
    return dataclasses.replace(term, reference=int(np.argmax(area)))


def _shift(start: dict, term: Term) -> dict:
    """Start log-likelihoods relative to the reference level."""
    if "logr" not in start:
        return start
    logr = start["logr"]
    return {"logr": logr - logr[term.reference]}


def _usable(pstats: PointStats, params, softened: bool) -> tuple[np.ndarray, dict]:
    """Points to fit: on the grid and (unless softened) not on a structural zero; with counts."""
    keep = pstats.inside.copy()
    detail: dict[str, dict[str, int]] = {}
    on_zero = np.zeros(len(keep), dtype=bool)
    for k, p in enumerate(params):
        t = p.term
        if t.form not in DISCRETE_FORMS:
            continue
        idx = pstats.index[:, k]
        z = np.isin(idx, sorted(t.zeros)) & pstats.inside
        if t.nodata == 0:
            z |= (idx == NODATA_INDEX) & pstats.inside
        for lvl in np.unique(idx[z]):
            name = "nodata" if lvl == NODATA_INDEX else t.levels[lvl]
            detail.setdefault(t.feature, {})[name] = int((idx[z] == lvl).sum())
        on_zero |= z
    if not softened:
        keep &= ~on_zero
    return keep, {"off_grid": int((~pstats.inside).sum()), "on_zero": int(on_zero.sum()), "detail": detail}


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    o = 0
    for b in blocks:
        out[o : o + b.shape[0], o : o + b.shape[0]] = b
        o += b.shape[0]
    return out


__all__ = ["PriorEstimator", "make_terms", "template_start", "SPATIAL"]
