"""``terrain-prior learn``: fit a region's likelihoods to past targets, cross-validate, write outputs.

Writes ``--out model.toml`` (the likelihood tables ``terrain-prior build --model`` reads) and beside
it ``<stem>.diagnostics.json`` (fit, standard errors, counts of dropped points, empirical ratios, CV
scores) and ``<stem>.fit.png`` (fitted likelihoods against empirical ratios).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sklearn.base import clone

from common.atomic import atomic_paths
from common.tables import numeric_column, read_csv_table
from pipeline.build.region import build_features, unused_features
from pipeline.config.learn import LearnConfig, load_learn_config
from pipeline.config.region import RegionConfig
from pipeline.gis.layers import LayerSpec, read_vector
from pipeline.gis.targets import read_targets
from pipeline.learn.estimator import SPATIAL, PriorEstimator, with_features
from pipeline.learn.evaluate import (
    CVResult,
    block_cv,
    default_bandwidths,
    with_mixture,
    with_selection,
)
from pipeline.learn.forms import from_scale
from pipeline.learn.kde import block_ids, fit_kde_cv
from pipeline.learn.mixture import MixturePrior
from pipeline.learn.plots import plot_fit
from pipeline.learn.select import BackwardSelection
from pipeline.learn.sufficient import DISCRETE_FORMS, check_weights

log = logging.getLogger(__name__)
CATEGORICAL_TYPES = ("mask", "classes", "categories")
"""Region feature types that are categorical (a ``raster`` feature is when ``categorical = true``)."""


@dataclass
class LearnReport:
    """What ``learn`` fitted and measured, and where it wrote it."""

    estimator: PriorEstimator
    naive: PriorEstimator
    hybrid: PriorEstimator | None
    cv: CVResult | None
    paths: dict[str, Path]
    settings: LearnConfig
    mixture: MixturePrior | None = None
    selection: BackwardSelection | None = None
    """With ``[learn] select``: the selection, whose kept features ``estimator``, ``naive`` and ``hybrid`` fit."""

    def table(self) -> str:
        """Fitted likelihoods with 95% intervals beside the naive fit, then the CV scores."""
        est, nv = self.estimator, self.naive
        w = max(16, 2 + max((len(t.feature) for t in est.terms_), default=0))  # long names keep their columns
        lines = [f"{'feature':<{w}}{'level':<12}{'ML':>10}  {'95% CI':<22}{'naive':>10}"]
        for t, p in zip(est.terms_, est.params_, strict=True):
            f = t.feature
            if t.form in DISCRETE_FORMS:
                for k, lv in enumerate(t.levels):
                    v, nvv = est.likelihoods_[f][lv], nv.likelihoods_[f][lv]
                    if not p.has_area[k]:
                        lines.append(f"{f:<{w}}{lv:<12}{v:>10.4g}  {'no area: not fitted':<22}{nvv:>10.4g}")
                    elif k in t.zeros:
                        note = "structural zero" if v == 0 else f"softened zero {v:g}"
                        lines.append(f"{f:<{w}}{lv:<12}{v:>10.4g}  {note:<22}{nvv:>10.4g}")
                    elif k == t.reference:
                        lines.append(f"{f:<{w}}{lv:<12}{v:>10.4g}  {'reference':<22}{nvv:>10.4g}")
                    else:
                        lo, hi = est.ci_[f][lv]
                        lines.append(f"{f:<{w}}{lv:<12}{v:>10.4g}  [{lo:.4g}, {hi:.4g}]".ljust(34 + w) + f"{nvv:>10.4g}")
            else:
                for key in est.likelihoods_[f]:
                    lo, hi = est.ci_[f][key]
                    lines.append(f"{f:<{w}}{key:<12}{est.likelihoods_[f][key]:>10.4g}  [{lo:.4g}, {hi:.4g}]".ljust(34 + w)
                                 + f"{nv.likelihoods_[f][key]:>10.4g}")
        lines.append(
            f"points: {est.n_points_} read, {est.n_used_} used, {est.n_off_grid_} off the grid, "
            f"{est.n_on_zero_} on structural zeros {est.on_zero_detail_ or ''} ({est.on_zero})"
        )
        if est.defensive is not None:
            how = "cross-fitted ML over block folds" if est.defensive == "cv" else "fixed"
            lines.append(f"defensive mixture: p = (1 - eps) p_model + eps uniform, eps = {est.defensive_:.4g} ({how})")
        if est.temper is not None:
            lines.append(f"tempered: p_model proportional to r^tau, tau = {est.temper_:.4g}")
        clamped = [t.feature for t in est.terms_ if np.isfinite(t.clamp_hi)]
        if clamped:
            lines.append(f"clamped to the training points' range: {', '.join(clamped)}")
        if self.hybrid is not None:
            p = self.hybrid.likelihoods_[SPATIAL]
            lines.append(f"hybrid: terrain x (alpha + (1 - alpha) KDE/uniform)^gamma, gamma = {p['gamma']:.3f} "
                         f"(alpha = {p['alpha']:g}), KDE bandwidth {self.hybrid.spatial_bandwidth_:.0f} m")
        if self.selection is not None:
            lines.extend(selection_lines(self.selection))
        if self.mixture is not None:
            ws = ", ".join(f"{n} {w:.3f}" for n, w in zip(self.settings.mixture, self.mixture.weights_, strict=True))
            lines.append(f"mixture: p = sum of w_k p_k, w = {ws} (chosen on {self.mixture.n_folds} cross-fitted folds of "
                         f"{self.mixture.spatial_block:g} m blocks: held-out {self.mixture.cv_loglik_:.3f} nats/point)")
        if self.cv is not None:
            s = self.cv.summary()
            nf = s["folds"]
            lines.append(
                f"spatial block CV: {nf} folds of {s['block_size_m']:g} m blocks"
                + (" (each fold fitted with its held-out blocks unobserved)" if s["held_out_blocks_unobserved"] else "")
                + ", held-out nats/point over uniform "
                f"({s['uniform_nats']:.3f} nats/point); worst fold = fold {s['worst_fold'] + 1}:"
            )
            head = "".join(f"{f'fold {k + 1}':>9}" for k in range(nf))
            lines.append(f"  {'model':<10}{'pooled':>9}{'worst':>9}" + head)
            lines.append(f"  {'points':<10}{'':>18}" + "".join(f"{n:>9d}" for n in s["n_test_per_fold"]))
            if s["n_blocks_per_fold"] is not None:
                lines.append(f"  {'blocks':<10}{'':>18}" + "".join(f"{n:>9d}" for n in s["n_blocks_per_fold"]))
            for m, gsum in s["gain_nats"].items():
                if m == "uniform":
                    continue
                lines.append(f"  {m:<10}{gsum['pooled']:>9.3f}{gsum['min']:>9.3f}" + "".join(f"{v:>9.3f}" for v in gsum["per_fold"]))
            if "hybrid_fold_wins" in s:
                res = ", ".join(f"{m} {w}/{s['hybrid_fold_ties'][m]}/{nf - w - s['hybrid_fold_ties'][m]}"
                                for m, w in s["hybrid_fold_wins"].items() if m != "uniform")
                lines.append(f"  hybrid beats per fold (won/tied/lost of {nf}): {res}")
        return "\n".join(lines)


def selection_lines(sel: BackwardSelection) -> list[str]:
    """The backward selection's steps: per step the held-out score without each candidate feature."""
    dropped = [f for f in sel.path_[0]["features"] if f not in sel.features_]
    lines = [f"backward selection on {sel.n_folds} folds of {sel.spatial_block:g} m blocks: kept {', '.join(sel.features_)}; "
             f"dropped {', '.join(dropped) or 'none'}" + (f"; never dropped (structural zeros): {', '.join(sel.fixed_)}" if sel.fixed_ else ""),
             "  held-out mean log density (nats/point, density per m^2) of each step's features, and without each candidate:"]
    for k, step in enumerate(sel.path_):
        cands = ", ".join(f"{f} {v:.4f}" for f, v in sorted(step["candidates"].items(), key=lambda kv: -kv[1]))
        lines.append(f"  step {k + 1}: {len(step['features'])} features {step['score']:.4f}" + (f"; without {cands}" if cands else ""))
    return lines


def _jsonable(obj):
    """NaN/inf -> None, numpy -> Python, tuples -> lists (strict JSON)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def diagnostics(report: LearnReport) -> dict:
    """Everything the fit knows, as strict JSON."""
    est = report.estimator

    def fit_info(e: PriorEstimator) -> dict:
        return {
            "likelihoods": e.likelihoods_, "stderr": e.stderr_, "ci95": e.ci_,
            "loglik_nats": e.loglik_, "penalty_nats": e.penalty_,
            "converged": [r.success for r in e.fit_results_], "messages": [r.message for r in e.fit_results_],
            "iterations": [r.n_iter for r in e.fit_results_], "at_bound": [r.at_bound for r in e.fit_results_],
            "seconds": e.fit_seconds_, "pass_seconds": e.pass_seconds_,
            "defensive_epsilon": e.defensive_, "curves": e.curves_, "spline_aic_per_lambda": e.smoothing_aic_,
            "clamped_range": {t.feature: from_scale(t.scale, np.array([t.clamp_lo, t.clamp_hi])).tolist()
                              for t in e.terms_ if np.isfinite(t.clamp_hi)},
        }

    out = {
        "points": {"read": est.n_points_, "used": est.n_used_, "off_grid": est.n_off_grid_,
                   "on_structural_zero": est.n_on_zero_, "on_zero_detail": est.on_zero_detail_, "policy": est.on_zero},
        "settings": {k: v for k, v in est.get_params().items() if k not in ("features", "template")},
        "units": "likelihoods relative to the reference level (1); stderr of categorical/binned values "
                 "is of log r (nats); road rmd in metres; scores in nats per point, densities per m^2",
        "ml": fit_info(est),
        "naive": fit_info(report.naive),
        "empirical": est.empirical(),
        "cell_combinations": int(len(est.cell_stats_.area)),
    }
    if report.hybrid is not None:
        out["hybrid"] = fit_info(report.hybrid) | {"bandwidth_m": report.hybrid.spatial_bandwidth_,
                                                   "bandwidth_loglik": report.hybrid.bandwidth_loglik_,
                                                   "block_m": report.hybrid.spatial_block,
                                                   "folds": report.hybrid.spatial_folds}
    if report.mixture is not None:
        names = list(report.settings.mixture)
        out["mixture"] = {"weights": dict(zip(names, report.mixture.weights_, strict=True)),
                          "cv_loglik_nats": report.mixture.cv_loglik_, "block_m": report.mixture.spatial_block,
                          "folds": report.mixture.n_folds,
                          "components": {n: fit_info(e) | {"features": list(e.feature_names)}
                                         for n, e in zip(names, report.mixture.estimators_, strict=True)}}
    if report.selection is not None:
        sel = report.selection
        out["selection"] = {"features": list(sel.features_), "fixed": list(sel.fixed_), "score_nats": sel.score_,
                            "path": sel.path_, "block_m": sel.spatial_block, "folds": sel.n_folds}
    if report.cv is not None:
        out["cv"] = report.cv.summary()
        if "selected_features" in report.cv.extra:
            out["cv"]["selected_features_per_fold"] = report.cv.extra["selected_features"]
    return _jsonable(out)


def read_target_weights(path: str | Path, grid, layer: str | None, column: str) -> np.ndarray:
    """Per-target weights from ``column`` of the targets file (rows as :func:`read_targets` reads
    them), validated by :func:`pipeline.learn.sufficient.check_weights`."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        table = read_csv_table(path, "target points")
        if column not in table.columns:
            raise ValueError(f"{path}: no column {column!r} (--weights); the CSV has {list(table.columns)}")
        values = numeric_column(table, column)
        text = np.flatnonzero(np.isnan(values) & table[column].notna().to_numpy())
        if text.size:
            raise ValueError(f"{path}: column {column!r} (--weights): non-numeric values on data rows {text[:10].tolist()} (0-based)")
    else:
        values = read_vector(LayerSpec("targets", path, "vector", layer=layer), grid, [column]).attributes[column]
        try:
            values = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: column {column!r} (--weights) is not numeric") from None
    return check_weights(values, len(values), f"{path}: column {column!r} (--weights)")


def prepare_learning(
    region: str | Path, targets: str | Path, layer: str | None = None, x: str = "x", y: str = "y",
    targets_crs: str | None = None,
) -> tuple[RegionConfig, LearnConfig, np.ndarray, PriorEstimator]:
    """The region and learn configs, the target points (metres, grid CRS) and the unfitted estimator
    they describe: what every learning path (in memory or tiled) starts from.

    Features fitted: ``[learn] features``, else every feature of the config except the source of a
    fitted ``classes`` feature. Each gets its ``[learn.forms.*]`` form, else its ``[likelihood.*]``
    table's, else (categorical features only) the categorical form; a continuous feature with
    neither is an error naming it (which form a distance or an elevation should have is the
    analyst's choice, see docs/learn.md "Forms").
    """
    config, lc = load_learn_config(region)
    tables = set(config.model.terms) if config.model is not None else set()
    with_form = tables | set(lc.forms) | set(lc.flexible)
    if lc.features is not None:
        names = list(lc.features)
        kinds = {n: "categorical" if config.features[n].type in CATEGORICAL_TYPES or config.features[n].categorical
                 else "continuous" for n in names}
        no_form = [n for n in names if n not in with_form and kinds[n] == "continuous"]
        if no_form:
            raise ValueError(
                f"{config.path}: feature {no_form[0]!r}{f' (and {no_form[1:]})' if no_form[1:] else ''} is continuous and has "
                f"no form: add [learn.forms.{no_form[0]}] form = \"decreasing\" (or increasing, spline, linear, road, bins) "
                f"or a [likelihood.{no_form[0]}] table, or leave it out of [learn] features")
    else:
        names = [n for n in config.features if n in with_form]
        unused = unused_features(config, set(names))
        if not names and not unused:
            raise ValueError(f"{config.path}: no [likelihood.*] template and no learn.features; nothing says what to fit")
        if unused:
            # Without [learn] features every feature is fitted; one with no form would be left out without a word.
            raise ValueError(
                f"{config.path}: [features.{unused[0]}] has no [likelihood.{unused[0]}] table nor [learn.forms.{unused[0]}], "
                f"so learn would not fit it{f' (nor {unused[1:]})' if unused[1:] else ''}: give it a form or a table, or "
                "list the features to fit in [learn] features"
            )
    mixed = [f for features in lc.mixture.values() for f in features if f not in names]
    no_form = [f for f in dict.fromkeys(mixed) if f not in with_form and not (config.features[f].type in CATEGORICAL_TYPES
                                                                          or config.features[f].categorical)]
    if no_form:
        raise ValueError(f"{config.path}: [learn.mixture] feature {no_form[0]!r} is continuous and has no form: add "
                         f"[learn.forms.{no_form[0]}] form = \"decreasing\" (or increasing, spline, linear, road, bins)")
    for key, given in (("flexible", lc.flexible), ("forms", lc.forms)):
        ignored = sorted(set(given) - set(names) - set(mixed))
        if ignored:
            raise ValueError(f"{config.path}: [learn] {key} names {ignored}, which this fit does not include "
                             "(see [learn] features and the [likelihood.*] tables)")
    pts = read_targets(targets, config.grid, layer, x, y, targets_crs)
    est = PriorEstimator(
        template=config.model, feature_names=tuple(names), penalty_sd=lc.penalty_sd, smooth_sd=lc.smooth_sd,
        on_zero=lc.on_zero, soften=lc.soften, flexible=lc.flexible or None, bin_width=lc.bin_width,
        forms=dict(lc.forms) or None, defensive=lc.defensive, temper=lc.temper, spatial_block=lc.block_size_m, spatial_folds=lc.folds,
        clamp=lc.clamp,
    )
    return config, lc, pts, est


def fit_hybrid(
    est: PriorEstimator, pts: np.ndarray, lc: LearnConfig, sample_weight: np.ndarray | None = None,
) -> PriorEstimator:
    """The hybrid of the fitted terrain estimator ``est``, refitted on points (N, 2) in metres (with
    ``sample_weight`` per point, if given): its KDE bandwidth chosen by block CV (``lc``'s candidates and
    blocks) on the points ``est`` used."""
    used = pts[est.used_mask_]
    stack = est.features
    bws = np.asarray(lc.bandwidths_m) if lc.bandwidths_m else default_bandwidths(stack)
    bw = fit_kde_cv(used, block_ids(used, stack.grid.bounds[:2], lc.block_size_m), bws).bandwidth
    return clone(est).set_params(spatial_bandwidth=float(bw), spatial_block=lc.block_size_m, spatial_folds=lc.folds).fit(pts, sample_weight=sample_weight)


def fit_mixture(est: PriorEstimator, pts: np.ndarray, lc: LearnConfig, sample_weight: np.ndarray | None = None) -> MixturePrior:
    """The mixture of ``lc.mixture``'s components (``est``'s settings, each with its own features and their
    forms), its weights cross-fitted on ``lc``'s blocks and folds, fitted on points (N, 2) in metres."""
    components = tuple(with_features(est, features) for features in lc.mixture.values())
    return MixturePrior(components, spatial_block=lc.block_size_m, n_folds=lc.folds).fit(pts, sample_weight=sample_weight)


def learning_inputs(
    region: str | Path, targets: str | Path, layer: str | None = None, progress: bool = True,
) -> tuple[RegionConfig, LearnConfig, np.ndarray, PriorEstimator]:
    """:func:`prepare_learning` with the region's feature stack built and set on the (unfitted)
    estimator: ready to fit on any subset of the points, a fold's for instance."""
    config, lc, pts, est = prepare_learning(region, targets, layer)
    est.set_params(features=build_features(config, progress))
    return config, lc, pts, est


def learn_region(
    region: str | Path,
    targets: str | Path,
    out: str | Path,
    layer: str | None = None,
    x: str = "x",
    y: str = "y",
    targets_crs: str | None = None,
    cv: bool = True,
    hybrid_prior: str | Path | None = None,
    progress: bool = True,
    weights: str | None = None,
    mixture_prior: str | Path | None = None,
) -> LearnReport:
    """Fit, evaluate and write (see the module doc). ``hybrid_prior``: also write the hybrid
    prior GeoTIFF there (the spatial term cannot be expressed as a likelihood table). ``weights``: a
    column of the targets giving each point's weight (default ``[learn] weights``; none: all 1).
    With ``[learn.mixture]``: each component's tables beside ``out`` (``<stem>.mixture.<name>.toml``) and,
    given ``mixture_prior``, the mixture prior GeoTIFF there (a mixture is not one set of tables).
    Grids larger than memory: :func:`pipeline.tiled.learn.learn_region_tiled`."""
    config, lc, pts, est = prepare_learning(region, targets, layer, x, y, targets_crs)
    if mixture_prior is not None and not lc.mixture:  # before any fit
        raise ValueError("--mixture-prior: the config has no [learn.mixture] tables")
    column = weights or lc.weights
    w = read_target_weights(targets, config.grid, layer, column) if column else None
    if w is not None and len(w) != len(pts):
        raise ValueError(f"{targets}: column {column!r} (--weights) has {len(w)} values for {len(pts)} targets")
    stack = build_features(config, progress)
    est.set_params(features=stack).fit(pts, sample_weight=w)
    listed, sel = est, None
    if lc.select:
        sel = BackwardSelection(est, lc.block_size_m, lc.folds, progress).fit(pts, sample_weight=w)
        est = sel.estimator_
    naive = clone(est).set_params(method="naive").fit(pts, sample_weight=w)
    hyb = fit_hybrid(est, pts, lc, sample_weight=w) if lc.hybrid else None
    result = None
    if cv:
        models = ("uniform", "naive", "terrain", "kde", "hybrid") if lc.hybrid else ("uniform", "naive", "terrain", "kde")
        result = block_cv(pts, listed, lc.folds, lc.block_size_m,
                          np.asarray(lc.bandwidths_m) if lc.bandwidths_m else None, models, progress, sample_weight=w)
        if sel is not None:  # the whole selection nested in each outer training fold
            result = with_selection(result, BackwardSelection(listed, lc.block_size_m, lc.folds), pts, sample_weight=w)
    mix = fit_mixture(listed, pts, lc, sample_weight=w) if lc.mixture else None
    if result is not None and mix is not None:
        result = with_mixture(result, clone(mix), pts, sample_weight=w)
    report = write_report(LearnReport(est, naive, hyb, result, report_paths(out), lc, mix, sel), targets)
    if hybrid_prior is not None and hyb is not None:
        report.paths["hybrid_prior"] = hyb.prior_.write(hybrid_prior)
    if mix is not None:
        for name, e in zip(lc.mixture, mix.estimators_, strict=True):
            report.paths[f"mixture {name}"] = Path(out).with_suffix(f".mixture.{name}.toml")
            e.model_.write_toml(report.paths[f"mixture {name}"])
        if mixture_prior is not None:
            report.paths["mixture_prior"] = mix.prior_.write(mixture_prior)
    return report


def report_paths(out: str | Path) -> dict[str, Path]:
    """Where a model written to ``out`` puts its diagnostics JSON and its fit plot."""
    out = Path(out)
    return {"model": out, "diagnostics": out.with_suffix(".diagnostics.json"), "plot": out.with_suffix(".fit.png")}


def write_report(report: LearnReport, targets: str | Path) -> LearnReport:
    """The model TOML, diagnostics JSON and fit plot of a finished report."""
    est, paths = report.estimator, report.paths
    if report.cv is not None:
        g = report.cv.summary()["gain_nats"]
        est.model_.meta["learned"]["cv_gain_nats_over_uniform"] = {m: round(v["pooled"], 6) for m, v in g.items()}
    est.model_.meta["learned"]["targets"] = str(Path(targets).resolve())
    est.model_.write_toml(paths["model"])
    with atomic_paths(paths["diagnostics"]) as (tmp,):
        tmp.write_text(json.dumps(diagnostics(report), indent=1, allow_nan=False))
    plot_fit(est, paths["plot"])
    return report
