"""``terrain-prior learn``: fit a region's likelihoods to past targets, cross-validate, write outputs.

Writes ``--out model.toml`` (the likelihood tables ``terrain-prior build --model`` reads) and beside
it ``<stem>.diagnostics.json`` (fit, standard errors, counts of dropped points, empirical ratios, CV
scores) and ``<stem>.fit.png`` (fitted likelihoods against empirical ratios).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from sklearn.base import clone

from common.atomic import atomic_paths
from pipeline.build.region import build_features, unused_features
from pipeline.config.learn import LearnConfig, load_learn_config
from pipeline.config.region import RegionConfig
from pipeline.gis.targets import read_targets
from pipeline.learn.estimator import SPATIAL, PriorEstimator
from pipeline.learn.evaluate import CVResult, block_cv, default_bandwidths
from pipeline.learn.kde import block_ids, fit_kde_cv
from pipeline.learn.plots import plot_fit
from pipeline.learn.sufficient import DISCRETE_FORMS

log = logging.getLogger(__name__)


@dataclass
class LearnReport:
    """What ``learn`` fitted and measured, and where it wrote it."""

    estimator: PriorEstimator
    naive: PriorEstimator
    hybrid: PriorEstimator | None
    cv: CVResult | None
    paths: dict[str, Path]
    settings: LearnConfig

    def table(self) -> str:
        """Fitted likelihoods with 95% intervals beside the naive fit, then the CV scores."""
        est, nv = self.estimator, self.naive
        lines = [f"{'feature':<16}{'level':<12}{'ML':>10}  {'95% CI':<22}{'naive':>10}"]
        for t, p in zip(est.terms_, est.params_, strict=True):
            f = t.feature
            if t.form in DISCRETE_FORMS:
                for k, lv in enumerate(t.levels):
                    v, nvv = est.likelihoods_[f][lv], nv.likelihoods_[f][lv]
                    if not p.has_area[k]:
                        lines.append(f"{f:<16}{lv:<12}{v:>10.4g}  {'no area: not fitted':<22}{nvv:>10.4g}")
                    elif k in t.zeros:
                        note = "structural zero" if v == 0 else f"softened zero {v:g}"
                        lines.append(f"{f:<16}{lv:<12}{v:>10.4g}  {note:<22}{nvv:>10.4g}")
                    elif k == t.reference:
                        lines.append(f"{f:<16}{lv:<12}{v:>10.4g}  {'reference':<22}{nvv:>10.4g}")
                    else:
                        lo, hi = est.ci_[f][lv]
                        lines.append(f"{f:<16}{lv:<12}{v:>10.4g}  [{lo:.4g}, {hi:.4g}]".ljust(50) + f"{nvv:>10.4g}")
            else:
                for key in est.likelihoods_[f]:
                    lo, hi = est.ci_[f][key]
                    lines.append(f"{f:<16}{key:<12}{est.likelihoods_[f][key]:>10.4g}  [{lo:.4g}, {hi:.4g}]".ljust(50)
                                 + f"{nv.likelihoods_[f][key]:>10.4g}")
        lines.append(
            f"points: {est.n_points_} read, {est.n_used_} used, {est.n_off_grid_} off the grid, "
            f"{est.n_on_zero_} on structural zeros {est.on_zero_detail_ or ''} ({est.on_zero})"
        )
        if self.hybrid is not None:
            p = self.hybrid.likelihoods_[SPATIAL]
            lines.append(f"hybrid: terrain x (alpha + (1 - alpha) KDE/uniform)^gamma, gamma = {p['gamma']:.3f} "
                         f"(alpha = {p['alpha']:g}), KDE bandwidth {self.hybrid.spatial_bandwidth_:.0f} m")
        if self.cv is not None:
            s = self.cv.summary()
            lines.append(
                f"spatial block CV: {s['folds']} folds of {s['block_size_m']:g} m blocks, "
                f"held-out nats/point over uniform ({s['uniform_nats']:.3f} nats/point):"
            )
            lines.append(f"  {'model':<10}{'pooled':>9}{'mean':>9}{'sd':>8}{'min':>9}{'max':>9}")
            for m, gsum in s["gain_nats"].items():
                lines.append(f"  {m:<10}{gsum['pooled']:>9.3f}{gsum['mean']:>9.3f}{gsum['sd']:>8.3f}{gsum['min']:>9.3f}{gsum['max']:>9.3f}")
            if "hybrid_fold_wins" in s:
                wins = ", ".join(f"{m} {w}/{s['folds']}" for m, w in s["hybrid_fold_wins"].items())
                lines.append(f"  hybrid beats per fold: {wins}")
        return "\n".join(lines)


def _jsonable(obj):
    """NaN/inf -> None, numpy -> Python, tuples -> lists (strict JSON)."""
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
    if report.cv is not None:
        out["cv"] = report.cv.summary()
    return _jsonable(out)


def prepare_learning(
    region: str | Path, targets: str | Path, layer: str | None = None, x: str = "x", y: str = "y",
    targets_crs: str | None = None,
) -> tuple[RegionConfig, LearnConfig, np.ndarray, PriorEstimator]:
    """The region and learn configs, the target points (metres, grid CRS) and the unfitted estimator
    they describe: what every learning path (in memory or tiled) starts from."""
    config, lc = load_learn_config(region)
    if config.model is None and lc.features is None:
        raise ValueError(f"{config.path}: no [likelihood.*] template and no learn.features; nothing says what to fit")
    fitted = set(lc.features) if lc.features is not None else set(config.model.terms)
    if lc.features is None:
        # Without [learn] features the template's tables say what to fit; a feature with none would be
        # left out of the fit without a word.
        unused = unused_features(config, fitted)
        if unused:
            raise ValueError(
                f"{config.path}: [features.{unused[0]}] has no [likelihood.{unused[0]}] table, so learn would not fit it"
                f"{f' (nor {unused[1:]})' if unused[1:] else ''}: add a table (its form and start values) or list "
                "the features to fit in [learn] features"
            )
    ignored = sorted(set(lc.flexible or ()) - fitted)
    if ignored:
        raise ValueError(f"{config.path}: [learn] flexible names {ignored}, which this fit does not include (see [learn] features and the [likelihood.*] tables)")
    pts = read_targets(targets, config.grid, layer, x, y, targets_crs)
    est = PriorEstimator(
        template=config.model, feature_names=lc.features, penalty_sd=lc.penalty_sd, smooth_sd=lc.smooth_sd,
        on_zero=lc.on_zero, soften=lc.soften, flexible=lc.flexible or None, bin_width=lc.bin_width,
    )
    return config, lc, pts, est


def fit_hybrid(est: PriorEstimator, pts: np.ndarray, lc: LearnConfig) -> PriorEstimator:
    """The hybrid of the fitted terrain estimator ``est``, refitted on points (N, 2) in metres: its KDE
    bandwidth chosen by block CV (``lc``'s candidates and blocks) on the points ``est`` used."""
    used = pts[est.used_mask_]
    stack = est.features
    bws = np.asarray(lc.bandwidths_m) if lc.bandwidths_m else default_bandwidths(stack)
    bw = fit_kde_cv(used, block_ids(used, stack.grid.bounds[:2], lc.block_size_m), bws).bandwidth
    return clone(est).set_params(spatial_bandwidth=float(bw), spatial_block=lc.block_size_m, spatial_folds=lc.folds).fit(pts)


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
) -> LearnReport:
    """Fit, evaluate and write (see the module doc). ``hybrid_prior``: also write the hybrid
    prior GeoTIFF there (the spatial term cannot be expressed as a likelihood table). Grids larger
    than memory: :func:`pipeline.tiled.learn.learn_region_tiled`."""
    config, lc, pts, est = prepare_learning(region, targets, layer, x, y, targets_crs)
    stack = build_features(config, progress)
    est.set_params(features=stack).fit(pts)
    naive = clone(est).set_params(method="naive").fit(pts)
    hyb = fit_hybrid(est, pts, lc) if lc.hybrid else None
    result = None
    if cv:
        models = ("uniform", "naive", "terrain", "kde", "hybrid") if lc.hybrid else ("uniform", "naive", "terrain", "kde")
        result = block_cv(pts, est, lc.folds, lc.block_size_m,
                          np.asarray(lc.bandwidths_m) if lc.bandwidths_m else None, models, progress)
    report = write_report(LearnReport(est, naive, hyb, result, report_paths(out), lc), targets)
    if hybrid_prior is not None and hyb is not None:
        report.paths["hybrid_prior"] = hyb.prior_.write(hybrid_prior)
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
