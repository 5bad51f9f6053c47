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
from scipy import optimize
from sklearn.base import BaseEstimator, clone
from sklearn.utils.validation import check_is_fitted
from threadpoolctl import threadpool_limits

from pipeline.build.region import calibrate
from pipeline.config.learn import FormSpec
from pipeline.features.stack import Feature, FeatureStack
from pipeline.learn.forms import BASIS_FORMS, difference_penalty, from_scale, to_scale
from pipeline.learn.kde import block_folds, block_ids, log_kde_feature
from pipeline.learn.poisson import FitResult, Objective, TermParams, fit, kde_logr, term_params
from pipeline.learn.sufficient import (
    CONTINUOUS_FORMS,
    DISCRETE_FORMS,
    NODATA_INDEX,
    CellStats,
    PointStats,
    Term,
    cached_cell_stats,
    check_points,
    check_weights,
    point_stats,
    with_range,
)
from pipeline.learn.window import BlockWindow
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
EPS_MIN = 1e-9
"""Smallest cross-fitted defensive ε (:func:`fit_calibration` works in log ε)."""
TEMPER_MIN = 0.05
"""Smallest tempering exponent τ (τ → 0 is the uniform prior over the support)."""
DEFENSIVE_BLOCK_M = 2000.0
"""Block side (metres) of the folds that choose the defensive ε when ``spatial_block`` is None."""
BASIS_FLOOR = 1e-12
"""Smallest value of a basis form's written table relative to its maximum."""
SEARCH_FTOL = 1e-9
"""L-BFGS-B tolerance of the fits that compare λ candidates (the chosen one is then refitted at 1e-13)."""
SPLINE_LAMBDAS = tuple(10.0 ** np.arange(-1, 4))
"""Candidate λ of a spline term's difference penalty when its smoothing is chosen by AIC."""


def _template_values(term: Term, table, flexible: dict) -> list[float | None]:
    """The template's likelihood per level of a discrete term (None where it gives none)."""
    if term.form == "categorical" and table is not None:
        vals = [table.values.get(lv, table.values.get(str(int(c)))) for lv, c in zip(term.levels, term.codes, strict=True)]
        return [None if v is None else float(v) for v in vals]
    if term.form == "binned" and isinstance(table, BinnedLikelihood) and term.feature not in flexible:
        return [float(v) for v in table.values]
    return [None] * term.n_levels


def template_start(term: Term, template: LikelihoodModel | None, flexible: dict | None = None,
                   forms: dict | None = None) -> tuple[Term, dict]:
    """``term`` with the template's structural zeros (values 0), and its start values for the fit
    (a feature in ``flexible`` or ``forms`` keeps only the template's categorical zeros)."""
    table = template.terms.get(term.feature) if template else None
    if term.form in DISCRETE_FORMS:
        vals = _template_values(term, table, {**(flexible or {}), **(forms or {})})
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
    forms: dict[str, FormSpec | dict] | None = None,
) -> tuple[list[Term], list[dict]]:
    """Terms to fit and their start values: each feature's form from ``forms``, else ``flexible``
    (bins), else the template's table, else the default.

    Features: ``feature_names``, else every feature with a template table, a form or a flexible entry
    (features of the stack outside these are named in a warning: not fitted), else every feature.
    Defaults: categorical features -> categorical terms, continuous features in metres -> the road
    form, other continuous features -> ``n_bins`` quantile bins.
    """
    forms = {k: v if isinstance(v, FormSpec) else FormSpec(**v) for k, v in (forms or {}).items()}
    flexible = flexible or {}
    if feature_names is not None:
        names = list(feature_names)
    elif template is not None or forms or flexible:
        names = list(dict.fromkeys([*(template.terms if template else ()), *forms, *flexible]))
        left = [f.name for f in stack if f.name not in names and f.name != SPATIAL]
        if left:
            warnings.warn(f"PriorEstimator: features {left} have no template table or form and are not fitted; "
                          "list the features to fit in feature_names (they then get a form or the default)", stacklevel=3)
    else:
        names = [f.name for f in stack]
    missing = [n for n in [*names, *forms, *flexible] if n not in stack.features]
    if missing:
        raise ValueError(f"no feature {missing[0]!r} in the stack; features are {sorted(stack.features)}")
    terms = []
    for name in names:
        f = stack[name]
        table = template.terms.get(name) if template else None
        nodata = float(getattr(table, "nodata", 1.0))
        spec = forms.get(name)
        if spec is None and name in flexible:
            spec = FormSpec("bins", edges=tuple(flexible[name]))
        if spec is None:
            if f.kind == "categorical":
                spec = FormSpec("categorical")
            elif isinstance(table, BinnedLikelihood):
                spec = FormSpec("bins", edges=tuple(table.edges))
            elif isinstance(table, RoadDistanceLikelihood) or (table is None and f.units == "m"):
                spec = FormSpec("road")
            else:
                finite = f.values[np.isfinite(f.values)]
                spec = FormSpec("bins", edges=tuple(np.unique(np.quantile(finite, np.linspace(0, 1, n_bins + 1)[:-1]))))
        if (spec.form == "categorical") != (f.kind == "categorical"):
            raise ValueError(f"feature {name!r} is {f.kind}; form {spec.form!r} is for "
                             f"{'categorical' if spec.form == 'categorical' else 'continuous'} features")
        if spec.form == "categorical":
            if table is not None and not isinstance(table, CategoricalLikelihood):
                raise ValueError(f"feature {name!r} is categorical but its template table is {type(table).__name__}")
            codes = tuple(int(c) for c in f.codes())
            terms.append(Term(name, "categorical", tuple(f.label(c) for c in codes), codes, nodata=nodata))
        elif spec.form == "bins":
            edges = list(spec.edges)
            terms.append(Term(name, "binned", tuple(f"{e:g}" for e in edges), edges=tuple(edges), nodata=nodata))
        elif spec.form == "road":
            width = bin_width or stack.grid.dx / 4.0
            terms.append(with_range(Term(name, "road", bin_width=width, nodata=nodata), f.values))
        else:
            lam = spec.smoothing if spec.smoothing is not None else (SPLINE_LAMBDAS[len(SPLINE_LAMBDAS) // 2] if spec.form == "spline" else 0.0)
            term = Term(name, spec.form, nodata=nodata, n_fine=spec.bins, scale=spec.scale, n_knots=spec.knots or 1, lam=lam)
            terms.append(with_range(term, f.values))
    pairs = [template_start(t, template, flexible, forms) for t in terms]
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
    bin_width : fine-bin width of the road form in feature units (default: a quarter cell).
    n_bins : quantile bins of continuous non-distance features without a template or form.
    forms : feature -> :class:`pipeline.config.learn.FormSpec` (or a dict of its fields): the form
        each feature is fitted with (categorical, road, bins, linear, increasing, decreasing,
        spline; docs/learn.md "Forms"); overrides the template's and ``flexible``.
    defensive : the defensive mixture p = (1 − ε)·p_model + ε·u, u uniform over the model's support
        (structural zeros stay zero): None (ε = 0), a number ε in [0, 1), or ``"cv"``: ε maximises
        the weighted log-likelihood of each point under the model fitted without its block fold
        (``spatial_folds`` folds of ``spatial_block`` metres, 2000 m when None), cross-fitted on the
        same statistics (``defensive_`` is the ε used).
    temper : the tempered model p ∝ r^τ (before the mixture): None (τ = 1), a number, or ``"cv"``: τ
        chosen with ε on the same cross-fitted likelihood (``temper_``). τ < 1 flattens a model whose
        effects, learned in the training blocks, are too sharp elsewhere.
    clamp : hold every basis form at its end value beyond the range of the training points.
    window : the observation window, a :class:`pipeline.learn.window.BlockWindow`: the points were
        looked for on the grid less its unobserved blocks, so the fit's background ∫λ leaves them
        out (None: the whole grid). The fitted prior is still a density over the whole grid. Block
        CV sets it to the held-out blocks; the cross-fits of ``"cv"`` calibration leave out each
        inner fold's blocks the same way. A point inside an unobserved block is a ValueError.
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
        forms: dict | None = None,
        defensive: float | str | None = None,
        temper: float | str | None = None,
        clamp: bool = True,
        window: BlockWindow | None = None,
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
        self.forms = forms
        self.defensive = defensive
        self.temper = temper
        self.clamp = clamp
        self.window = window

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
        d = self.defensive
        if not (d is None or d == "cv" or (isinstance(d, int | float) and not isinstance(d, bool) and 0 <= d < 1)):
            raise ValueError(f"defensive must be None, 'cv' or a number in [0, 1), got {d!r}")
        t = self.temper
        if not (t is None or t == "cv" or (isinstance(t, int | float) and not isinstance(t, bool) and TEMPER_MIN <= t <= 1.5)):
            raise ValueError(f"temper must be None, 'cv' or a number in [{TEMPER_MIN}, 1.5], got {t!r}")
        if self.window is not None and not isinstance(self.window, BlockWindow):
            raise ValueError(f"window must be None or a BlockWindow, got {type(self.window).__name__}")

    def fit(self, X: np.ndarray, y: None = None, sample_weight: np.ndarray | None = None) -> PriorEstimator:
        """Fit to points X (N, 2) in metres in the grid's CRS (``y`` is ignored). Points off the grid are
        dropped and counted; points on structural zeros are dropped or the zeros softened (``on_zero``).

        ``sample_weight`` (N,): each point's weight in the weighted Poisson-process likelihood
        Σ w_i log p(x_i): a point of weight w counts as w targets there (counts per location), and
        fractional weights down-weight unreliable sightings. Weights must be finite and > 0 (a
        ValueError names the bad rows); standard errors treat them as counts."""
        self._check_params()
        if self.features is None:
            raise ValueError("PriorEstimator.fit: no feature stack; give PriorEstimator(features=stack, ...)")
        pts = check_points(X)
        weights = check_weights(sample_weight, len(pts))
        if self.spatial_bandwidth is not None and np.ndim(self.spatial_bandwidth) > 0:
            return self._fit_bandwidths(pts, weights)
        t0, c0 = time.perf_counter(), time.process_time()
        features = stack = self.features
        self.spatial_bandwidth_ = float(self.spatial_bandwidth) if self.spatial_bandwidth else None
        terms, _ = make_terms(features, self.template, self.feature_names, self.flexible, self.bin_width, self.n_bins, self.forms)
        if self.window is not None:
            outside = ~self.window.observed(features.grid, pts)
            if outside.any():
                raise ValueError(f"window: {int(outside.sum())} of {len(pts)} points lie in its unobserved blocks "
                                 f"(first at x = {pts[outside][0, 0]:.1f} m, y = {pts[outside][0, 1]:.1f} m)")
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
        # the grid pass is split by block where some fit leaves blocks out: the window's, else the
        # calibration folds' (the fit on all points then keeps the unsplit pass: the same fit as without ε, τ)
        cells = cached_cell_stats(stack, tuple(terms), None if self.window is None else float(self.window.size))
        calibrate = "cv" in (self.defensive, self.temper)
        split = cells if self.window is not None or not calibrate else \
            cached_cell_stats(stack, tuple(terms), float(self.spatial_block or DEFENSIVE_BLOCK_M))
        pass_times = (time.perf_counter() - t0, time.process_time() - c0)
        pstats = point_stats(stack, tuple(terms), pts, weights)
        if loo is not None:
            pstats.value[:, -1] = loo
        self.stack_ = stack
        self.n_features_in_ = 2
        groups = None
        if calibrate:
            groups = (block_folds(pts, features.grid.bounds[:2], self.spatial_block or DEFENSIVE_BLOCK_M, self.spatial_folds),
                      block_ids(pts, features.grid.bounds[:2], split.block_size), split)
        return self._fit_from_stats(cells, pstats, t0, c0, pass_times, groups)

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

    def _fit_from_stats(self, grid_cells: CellStats, pstats: PointStats, t0: float, c0: float,
                        pass_times: tuple[float, float], groups: tuple[np.ndarray, np.ndarray, CellStats] | None = None) -> PriorEstimator:
        """The fit proper, shared by :meth:`fit` and :meth:`fit_stats`: reference levels, parameters,
        the optimisation and every fitted attribute. ``grid_cells`` are the whole grid's statistics (the
        fit uses those inside ``window``); ``groups`` the points' calibration folds, their block ids and the
        grid's statistics split by those blocks."""
        cells = grid_cells.within(self.window)
        terms = [_with_reference(t, cells.level_area(k)) for k, t in enumerate(cells.terms)]
        cells = dataclasses.replace(cells, terms=tuple(terms))
        pstats = dataclasses.replace(pstats, terms=tuple(terms))
        starts = [{"alpha": self.spatial_floor} if t.form == "kde" else template_start(t, self.template, self.flexible, self.forms)[1]
                  for t in terms]
        soften = self.soften if self.on_zero == "soften" else None
        params = [
            term_params(t, cells.level_area(k), soften, _shift(starts[k], t), cells.bin_value(k) if t.form in CONTINUOUS_FORMS else None)
            for k, t in enumerate(terms)
        ]
        keep, counts = _usable(pstats, params, soften is not None)
        used = pstats.subset(keep)
        if self.clamp:
            params = [_clamped(p, used.value[:, k]) for k, p in enumerate(params)]
        if "cv" in (self.defensive, self.temper) and groups is None:
            raise ValueError("defensive='cv' / temper='cv' need the points' block folds; fit_stats takes numbers or None")
        params, self.smoothing_aic_, results = self._choose_smoothing(cells, used, params)
        terms = [p.term for p in params]
        cells = dataclasses.replace(cells, terms=tuple(terms))
        used = dataclasses.replace(used, terms=tuple(terms))
        results = results or self._solve(cells, used, params)
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
        if "cv" in (self.defensive, self.temper):
            split = dataclasses.replace(groups[2], terms=cells.terms)
            self.defensive_, self.temper_ = self._cross_fit_calibration(split, used, params, groups[0][keep], groups[1][keep])
        else:
            self.defensive_, self.temper_ = float(self.defensive or 0.0), float(self.temper or 1.0)
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

    def _solve(self, cells: CellStats, used: PointStats, params: list[TermParams],
               x0: np.ndarray | None = None, ftol: float = 1e-13) -> list[FitResult]:
        """The optimisation: all terms jointly (ml, from ``x0`` when given) or each alone on its marginal (naive)."""
        if self.method == "ml":
            return [fit(Objective(cells, used, params, list(range(len(params))), self.penalty_sd, self.smooth_sd), x0, ftol)]
        return [fit(Objective(cells, used, params, [k], self.penalty_sd, self.smooth_sd), None, ftol) for k in range(len(params))]

    def _form(self, name: str) -> FormSpec | None:
        spec = (self.forms or {}).get(name)
        return spec if spec is None or isinstance(spec, FormSpec) else FormSpec(**spec)

    def _choose_smoothing(self, cells: CellStats, used: PointStats,
                          params: list[TermParams]) -> tuple[list[TermParams], dict[str, dict[float, float]], list | None]:
        """λ of each spline term without a fixed ``smoothing``: the candidate in :data:`SPLINE_LAMBDAS`
        with the least AIC = −2ℓ + 2·edf, edf = K − tr(Cov·λP) the term's effective degrees of
        freedom (one sweep over the terms, the others at their current λ; each fit starts from the
        previous λ's). Returns the parameters, the AIC per λ and the chosen fit (None: no choice made)."""
        params = list(params)
        aic: dict[str, dict[float, float]] = {}
        chosen = None
        offsets = np.concatenate([[0], np.cumsum([p.size for p in params])]).astype(int)
        for k, p in enumerate(params):
            spec = self._form(p.term.feature)
            if p.term.form != "spline" or spec is None or spec.smoothing is not None:
                continue
            scores, fits, x = {}, {}, None
            for lam in SPLINE_LAMBDAS[::-1]:  # smooth to rough: each fit starts from the smoother one
                trial = list(params)
                trial[k] = _with_lambda(p, lam)
                res = self._solve(cells, used, trial, x, SEARCH_FTOL)
                x = np.concatenate([r.x for r in res])
                fits[float(lam)] = res
                cov = np.nan_to_num(_block_diag([r.cov for r in res]))
                sl = slice(offsets[k], offsets[k + 1])
                edf = p.size - float(np.trace(cov[sl, sl] @ trial[k].pen))
                ll = Objective(cells, used, trial, list(range(len(trial))), self.penalty_sd, self.smooth_sd).loglik(x)
                scores[float(lam)] = -2.0 * ll + 2.0 * edf
            best = min(scores, key=scores.get)
            params[k] = _with_lambda(p, best)
            aic[p.term.feature] = scores
            chosen = fits[best]
        if chosen is not None and self.method == "ml":  # polish the chosen fit to full precision
            chosen = self._solve(cells, used, params, chosen[0].x)
        return params, aic, chosen

    def _cross_fit_calibration(self, grid_cells: CellStats, used: PointStats, params: list[TermParams],
                               fold: np.ndarray, block: np.ndarray) -> tuple[float, float]:
        """(ε, τ) maximising Σ_i w_i log((1 − ε)·p^τ_{−f(i)}(x_i) + ε·u): p_{−f} the model fitted
        without fold f in the window less the blocks ``block`` of fold f's points (``grid_cells``: the
        grid's statistics split by those blocks), p^τ ∝ r^τ its tempered density over the whole grid (τ = 1 unless
        ``temper="cv"``, ε = 0 unless ``defensive="cv"``), u uniform over the support (1 / its area, m⁻²)."""
        folds = np.unique(fold)
        if len(folds) < 2:
            return 0.0, 1.0
        window = self.window or BlockWindow(grid_cells.block_size)
        lr = np.empty(len(fold))
        per_fold = []
        support = np.ones(len(grid_cells.area), dtype=bool)
        for f in folds:
            train = used.subset(fold != f)
            test = fold == f
            inner = grid_cells.within(window.without(np.unique(block[test])))
            res = self._solve(inner, train, params, self.theta_ if self.method == "ml" else None)  # warm start: the full fit
            x = np.concatenate([r.x for r in res])
            obj = Objective(inner, train, params, list(range(len(params))), self.penalty_sd, self.smooth_sd)
            lr_f = np.zeros(int(test.sum()))
            lc = np.zeros(len(grid_cells.area))
            for k, th in enumerate(obj.split(x)):
                lr_f += params[k].logr(th, used.index[test, k], used.value[test, k].copy())
                lc += params[k].cell_lut(th)[grid_cells.index[:, k]]
            lr[test] = lr_f
            support &= np.isfinite(lc)
            per_fold.append((test, lc))
        log_u = -np.log(grid_cells.area[support].sum())
        log_area = np.log(grid_cells.area)
        per_fold = [(test, lc[np.isfinite(lc)], log_area[np.isfinite(lc)]) for test, lc in per_fold]
        w = used.weights / used.weights.sum()
        return fit_calibration(per_fold, lr, log_u, w, self.defensive, self.temper)

    def _fit_bandwidths(self, points: np.ndarray, weights: np.ndarray | None) -> PriorEstimator:
        """Fit the hybrid at each candidate bandwidth; keep the best held-out-value log-likelihood."""
        fits = [clone(self).set_params(spatial_bandwidth=float(b)).fit(points, sample_weight=weights)
                for b in self.spatial_bandwidth]
        best = max(fits, key=lambda e: e.loglik_)
        self.__dict__.pop("prior_", None)
        self.__dict__.update({k: v for k, v in best.__dict__.items() if k.endswith("_") and not k.startswith("_")})
        self.bandwidth_loglik_ = {float(e.spatial_bandwidth): e.loglik_ for e in fits}
        return self

    def _describe(self, obj: Objective) -> None:
        """likelihoods_, stderr_, ci_ and model_ from theta_ and cov_."""
        se_all = np.sqrt(np.clip(np.diag(self.cov_), 0, None)) if self.cov_.size else np.zeros(0)
        self.likelihoods_, self.stderr_, self.ci_, self.curves_ = {}, {}, {}, {}
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
            elif t.form in BASIS_FORMS:
                cov = np.nan_to_num(self.cov_[obj.offsets[j] : obj.offsets[j + 1], obj.offsets[j] : obj.offsets[j + 1]])
                self.curves_[t.feature] = _curve(t, th, cov)
                if t.form == "linear":
                    keys, lr, se_lr = ["beta"], th, np.nan_to_num(se)
                    vals = lr
                else:
                    at = from_scale(t.scale, t.kappa if t.form != "spline" else np.linspace(t.kappa[0], t.kappa[-1], 6))
                    b = t.basis(at)
                    keys, lr, se_lr = [f"r({v:.4g})" for v in at], b @ th, np.sqrt(np.clip(np.einsum("ij,jk,ik->i", b, cov, b), 0.0, None))
                    vals = np.exp(lr)
                lo, hi = (lr - Z95 * se_lr, lr + Z95 * se_lr) if t.form == "linear" else (np.exp(lr - Z95 * se_lr), np.exp(lr + Z95 * se_lr))
                self.likelihoods_[t.feature] = dict(zip(keys, np.asarray(vals, float).tolist(), strict=True))
                self.stderr_[t.feature] = dict(zip(keys, np.asarray(se_lr, float).tolist(), strict=True))
                self.ci_[t.feature] = {k: (float(a), float(c)) for k, a, c in zip(keys, lo, hi, strict=True)}
                g_edges = t.lo + t.bin_width * np.arange(t.n_levels)
                # floored at BASIS_FLOOR of the maximum: a fitted curve never makes a structural zero
                # (a steep tail fitted to few points would underflow the prior's float32 cells)
                fine = np.maximum(p.cell_lut(th)[:-1] - p.cell_lut(th)[:-1].max(), np.log(BASIS_FLOOR))
                table_terms[t.feature] = BinnedLikelihood(from_scale(t.scale, g_edges).tolist(), np.exp(fine).tolist(), t.nodata)
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
                "defensive_epsilon": self.defensive_,
                "temper_exponent": self.temper_,
                "weighted": self.point_stats_.weight is not None,
            }
        }
        if self.temper_ != 1.0:
            meta["learned"]["tempering"] = (f"p proportional to r^{self.temper_:.4g} (r: these tables); "
                                            "build --model applies it (temper_exponent)")
        if self.defensive_:
            meta["learned"]["defensive_mixture"] = (
                f"p = (1 - {self.defensive_:.4g}) * p_model + {self.defensive_:.4g} * uniform over the support; "
                "build --model applies it (defensive_epsilon)")
        forms = {t.feature: t.form + (f" in {t.scale}, {t.n_knots} knots" if t.form in ("increasing", "decreasing", "spline") else "")
                 + (f", lambda {t.lam:g}" if t.form == "spline" else "") for t in self.terms_ if t.form in BASIS_FORMS}
        if forms:
            meta["learned"]["basis_forms"] = {k: f"{v}; written as fine bins" for k, v in forms.items()}
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
        # τ and ε as `build --model` applies them to the written tables (one formula)
        return TerrainPrior.from_array(calibrate(r, self.temper_, self.defensive_), self.stack_.grid, self.model_.to_dict())

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
            if t.form == "kde":
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
                centre = t.lo + t.bin_width * (np.arange(t.n_levels) + 0.5)
                if t.form in BASIS_FORMS:
                    centre = from_scale(t.scale, centre)
                out[t.feature] = {"bin_lo": (t.lo + t.bin_width * np.arange(t.n_levels)).tolist(), "bin_width": t.bin_width,
                                  "bin_centre": centre.tolist(), "scale": t.scale if t.form in BASIS_FORMS else "linear",
                                  "count": cnt.tolist(), "area_m2": area.tolist(), "ratio": ratio.tolist()}
        return out


def with_features(estimator: PriorEstimator, features: tuple[str, ...] | list[str]) -> PriorEstimator:
    """An unfitted clone of ``estimator`` fitting only ``features``, each with its form and flexible edges."""
    keep = set(features)
    return clone(estimator).set_params(
        feature_names=tuple(features),
        forms={k: v for k, v in (estimator.forms or {}).items() if k in keep} or None,
        flexible={k: v for k, v in (estimator.flexible or {}).items() if k in keep} or None)


def cross_fitted(estimator: PriorEstimator, X: np.ndarray, fold: np.ndarray, sample_weight: np.ndarray | None = None,
                 block_size: float = DEFENSIVE_BLOCK_M) -> np.ndarray:
    """log p_{-f(i)}(x_i) per point of X (N, 2, metres): ``estimator`` (unfitted) fitted without point
    i's fold (``fold``: N ids) and scored at x_i (log of a density per m²; -inf where it is zero).
    Each fit's observation window (the estimator's ``window``, else the grid in blocks of ``block_size``
    metres) leaves out the blocks holding the fold's points: they were held out, not searched."""
    out = np.empty(len(X))
    window = estimator.window or BlockWindow(block_size)
    grid = estimator.features.grid
    for f in np.unique(fold):
        test = fold == f
        fitted = clone(estimator).set_params(window=window.without_points(grid, X[test]))
        out[test] = fitted.fit(X[~test], sample_weight=None if sample_weight is None else sample_weight[~test]).score_samples(X[test])
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


def _curve(t: Term, theta: np.ndarray, cov: np.ndarray, n: int = 200) -> dict[str, list[float]]:
    """A basis term's log r on ``n`` values equally spaced on its scale, with its standard error
    (nats; parameters at a bound count as fixed there)."""
    value = from_scale(t.scale, np.linspace(t.kappa[0], t.kappa[-1], n))
    b = t.basis(value)
    return {"value": value.tolist(), "logr": (b @ theta).tolist(),
            "se": np.sqrt(np.clip(np.einsum("ij,jk,ik->i", b, cov, b), 0.0, None)).tolist()}


def _clamped(p: TermParams, values: np.ndarray) -> TermParams:
    """A basis term's parameters with its basis clamped to the range of the points' ``values``
    (feature units; NaN ignored): beyond the training points the fitted curve stays at its end value,
    where the data say nothing of it. Other terms are returned as they are."""
    t = p.term
    g = to_scale(t.scale, values[np.isfinite(values)]) if t.form in BASIS_FORMS else np.zeros(0)
    if g.size == 0:
        return p
    return dataclasses.replace(p, term=dataclasses.replace(t, clamp_lo=float(g.min()), clamp_hi=float(g.max())))


def _with_lambda(p: TermParams, lam: float) -> TermParams:
    """A spline term's parameters with difference-penalty weight ``lam``."""
    return dataclasses.replace(p, term=dataclasses.replace(p.term, lam=float(lam)),
                               pen=float(lam) * difference_penalty(p.term.form, p.term.n_knots))


def fit_calibration(per_fold: list, lr: np.ndarray, log_u: float, w: np.ndarray, defensive: float | str | None,
                    temper: float | str | None) -> tuple[float, float]:
    """(ε, τ) minimising :func:`calibration_nll`: each fitted when its setting is "cv", else fixed at it
    (None: ε = 0, τ = 1). ε is fitted as log ε in [log EPS_MIN, log 0.999]: in ε the derivative is
    unbounded at 0 whenever a held-out point lies far below uniform, and L-BFGS-B stopped there
    (ABNORMAL) up to 0.4 nats per point short of the optimum; in log ε each point's term is at most 1."""
    fit_eps, fit_tau = defensive == "cv", temper == "cv"
    eps0 = 0.0 if fit_eps else float(defensive or 0.0)
    tau0 = 1.0 if fit_tau else float(temper or 1.0)

    def nll(z: np.ndarray) -> tuple[float, np.ndarray]:
        eps = float(np.exp(z[0])) if fit_eps else eps0
        value, grad = calibration_nll(eps, tau0 if not fit_tau else z[-1], per_fold, lr, log_u, w, (fit_eps, fit_tau))
        if fit_eps:
            grad[0] *= eps
        return value, grad

    z0 = np.array([np.log(0.01)] * fit_eps + [1.0] * fit_tau)
    bounds = [(np.log(EPS_MIN), np.log(0.999))] * fit_eps + [(TEMPER_MIN, 1.5)] * fit_tau
    with threadpool_limits(limits=1, user_api="blas"):
        z = optimize.minimize(nll, z0, jac=True, method="L-BFGS-B", bounds=bounds).x
    return (float(np.exp(z[0])) if fit_eps else eps0), (float(z[-1]) if fit_tau else tau0)


def calibration_nll(eps: float, tau: float, per_fold: list, lr: np.ndarray, log_u: float, w: np.ndarray,
                    free: tuple[bool, bool] = (True, True)) -> tuple[float, np.ndarray]:
    """Minus the mean log-likelihood Σ_i w_i log((1 − ε)·p^τ_{−f(i)}(x_i) + ε·u) (``w`` summing to 1)
    and its gradient in the ``free`` ones of (ε, τ). ``per_fold``: (held-out mask, log r per support
    combination, log area per combination) of each fold's model; ``lr`` each point's log r under the
    model that did not see it; ``log_u`` log of the uniform density over the support (per m²).
    d log p_i / dτ = log r_i − E[log r] under the fold's tempered density; d/dε by the mixture's chain rule."""
    logp, dlogp = np.empty(len(lr)), np.empty(len(lr))
    for test, lc, la in per_fold:
        e = tau * lc + la
        top = float(e.max())
        q = np.exp(e - top)
        z_f = q.sum()
        logp[test] = tau * lr[test] - (top + np.log(z_f))
        dlogp[test] = lr[test] - float(q @ lc) / z_f
    if eps > 0:
        mix = np.logaddexp(np.log1p(-eps) + logp, np.log(eps) + log_u)
        rho = np.exp(np.log1p(-eps) + logp - mix)  # the model's share of each point's mixture density
        d_eps = np.exp(log_u - mix) - np.exp(logp - mix)
    else:
        # the one-sided derivative at ε = 0 is unbounded when a point has p ≪ u: capped (e^700) rather
        # than overflowing (fit_calibration fits log ε, so it never evaluates ε = 0)
        mix, rho, d_eps = logp, np.ones(len(lr)), np.exp(np.minimum(log_u - logp, 700.0)) - 1.0
    grad = [-(w @ d_eps)] * free[0] + [-(w @ (rho * dlogp))] * free[1]
    return -float(w @ mix), np.array(grad, dtype=np.float64)


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    o = 0
    for b in blocks:
        out[o : o + b.shape[0], o : o + b.shape[0]] = b
        o += b.shape[0]
    return out


__all__ = ["PriorEstimator", "make_terms", "template_start", "SPATIAL"]
