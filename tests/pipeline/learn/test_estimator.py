"""PriorEstimator: recovery of a known prior, standard errors, naive vs ML, score, zero policies, TOML."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from affine import Affine
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from sklearn.utils.estimator_checks import check_estimator

from pipeline.build.region import build_features, build_prior
from pipeline.config.region import load_config
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import Grid
from pipeline.learn.estimator import PriorEstimator
from pipeline.learn.sufficient import DISCRETE_FORMS
from pipeline.prior.likelihood import CategoricalLikelihood, LikelihoodModel, RoadDistanceLikelihood
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.gis_helpers import REGION_TOML
from tests.pipeline.learn_synth import TRUE_MODEL, small_stack


@pytest.fixture(scope="module")
def region():
    """The bundled synthetic region, its hand-set model (the truth here) and its prior density."""
    cfg = load_config(REGION_TOML)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack = build_features(cfg, progress=False)
    return stack, cfg.model, build_prior(stack, cfg.model).density


def true_params(est: PriorEstimator, model: LikelihoodModel) -> dict[tuple[str, str], float]:
    """The truth in the fit's parameters: log r relative to the fit's reference level; rmd, mv."""
    out = {}
    for t in est.terms_:
        table = model.terms[t.feature]
        if t.form in DISCRETE_FORMS:
            ref = table.values[t.levels[t.reference]]
            for k, lv in enumerate(t.levels):
                if k != t.reference and k not in t.zeros:
                    out[(t.feature, lv)] = np.log(table.values[lv] / ref)
        else:
            out[(t.feature, "rmd")] = table.rmd
            out[(t.feature, "mv")] = table.mv
    return out


def estimates(est: PriorEstimator, keys) -> tuple[np.ndarray, np.ndarray]:
    """Fitted values and standard errors on the scale of :func:`true_params`."""
    val, se = [], []
    for f, k in keys:
        if k in ("rmd", "mv"):
            val.append(est.likelihoods_[f][k])
        else:
            val.append(np.log(est.likelihoods_[f][k]))
        se.append(est.stderr_[f][k])
    return np.array(val), np.array(se)


def fit_region(region, n: int, seed: int) -> tuple[PriorEstimator, dict]:
    stack, model, density = region
    pts = TerrainPrior.from_array(density, stack.grid).sample(n, np.random.default_rng(seed))
    est = PriorEstimator(features=stack, template=model).fit(pts)
    return est, true_params(est, model)


def test_recovers_hand_set_table_within_standard_errors(region) -> None:
    est, truth = fit_region(region, 2000, seed=11)
    val, se = estimates(est, truth)
    z = (val - np.array(list(truth.values()))) / se
    assert np.all(np.isfinite(z)) and len(z) >= 10
    assert np.max(np.abs(z)) < 4.0, dict(zip(truth, np.round(z, 2), strict=True))
    assert est.n_used_ == 2000 and est.n_on_zero_ == 0 and all(r.success for r in est.fit_results_)


def _se_ratio(region, n_small: int, n_big: int) -> np.ndarray:
    small, truth = fit_region(region, n_small, seed=21)
    big, _ = fit_region(region, n_big, seed=22)
    return estimates(small, truth)[1] / estimates(big, truth)[1] / np.sqrt(n_big / n_small)


def test_standard_errors_shrink_like_root_n_200_to_2000(region) -> None:
    ratio = _se_ratio(region, 200, 2000)
    # se ∝ 1/√n up to the sampling noise of the observed information at n = 200
    assert 0.75 < np.median(ratio) < 1.33
    assert np.all((ratio > 0.4) & (ratio < 2.5))


@pytest.mark.slow
def test_standard_errors_shrink_like_root_n_2000_to_20000(region) -> None:
    ratio = _se_ratio(region, 2000, 20000)
    assert 0.9 < np.median(ratio) < 1.11
    assert np.all((ratio > 0.7) & (ratio < 1.4))
    est, truth = fit_region(region, 20000, seed=23)
    val, se = estimates(est, truth)
    assert np.max(np.abs((val - np.array(list(truth.values()))) / se)) < 4.0


def test_standard_errors_are_calibrated_over_replicates() -> None:
    """Independent oracle for the observed information: over replicate samples, the squared
    z-scores of the estimates average to 1 (chi-square with one degree of freedom)."""
    stack = small_stack()
    density = TRUE_MODEL.evaluate(stack)
    rng = np.random.default_rng(7)
    z2 = []
    for _ in range(30):
        est = PriorEstimator(features=stack, template=TRUE_MODEL).fit(TerrainPrior.from_array(density, stack.grid).sample(1500, rng))
        truth = true_params(est, TRUE_MODEL)
        val, se = estimates(est, truth)
        z2.extend(((val - np.array(list(truth.values()))) / se) ** 2)
    z2 = np.array(z2)  # 30 x 4 parameters; mean of 120 chi2(1) draws has sd ~0.13
    assert 0.65 < z2.mean() < 1.45


def independent_stack() -> FeatureStack:
    """Land class varies only along columns, road distance only along rows: areas factorise."""
    h, w, cell = 50, 60, 20.0
    grid = Grid("EPSG:32734", Affine(cell, 0.0, 300_000.0, 0.0, -cell, 6_200_000.0), h, w)
    land = np.broadcast_to((np.arange(w) * 7 // w % 3).astype(np.int16), (h, w)).copy()
    d = np.broadcast_to((np.abs(np.arange(h) - 12) * cell)[:, None].astype(np.float64), (h, w)).copy()
    stack = FeatureStack(grid)
    stack.add(Feature("land", land, "categorical", labels={0: "grass", 1: "bush", 2: "rock"}))
    stack.add(Feature("road_distance", d, "continuous", "m"))
    return stack


def test_naive_equals_ml_when_features_are_independent() -> None:
    stack = independent_stack()
    template = LikelihoodModel({"land": CategoricalLikelihood({"grass": 1.0, "bush": 0.5, "rock": 0.2}),
                                "road_distance": RoadDistanceLikelihood(100.0, 0.2)})
    pts = TerrainPrior.from_array(template.evaluate(stack), stack.grid).sample(3000, np.random.default_rng(2))
    ml = PriorEstimator(features=stack, template=template).fit(pts)
    naive = PriorEstimator(features=stack, template=template, method="naive").fit(pts)
    for f in ("land", "road_distance"):
        for k, v in ml.likelihoods_[f].items():
            assert naive.likelihoods_[f][k] == pytest.approx(v, rel=1e-4), (f, k)


def test_naive_is_count_ratio_and_differs_from_ml_when_features_correlate() -> None:
    stack = small_stack()
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(4000, np.random.default_rng(9))
    naive = PriorEstimator(features=stack, template=TRUE_MODEL, method="naive", penalty_sd=1e6).fit(pts)
    ml = PriorEstimator(features=stack, template=TRUE_MODEL, penalty_sd=1e6).fit(pts)
    # oracle: share of points over share of area per land class, straight from the arrays
    land = stack["land"].values
    r, c = (np.array(stack.grid.to_pixel(pts[:, 0], pts[:, 1]))[::-1]).astype(int)
    counts = np.bincount(land[r, c], minlength=3) / len(pts)
    areas = np.bincount(land.ravel(), minlength=3) / land.size
    ratio = counts / areas
    ref = naive.terms_[0].reference
    for k, lv in enumerate(("grass", "bush", "rock")):
        assert naive.likelihoods_["land"][lv] == pytest.approx(ratio[k] / ratio[ref], rel=1e-5)
    gaps = [abs(np.log(naive.likelihoods_["land"][lv] / ml.likelihoods_["land"][lv])) for lv in ("bush", "rock")]
    assert max(gaps) > 0.1  # land correlates with road distance here, so counting is biased


def test_score_is_mean_log_density_of_the_normalised_fit() -> None:
    stack = small_stack()
    rng = np.random.default_rng(12)
    density = TRUE_MODEL.evaluate(stack)
    est = PriorEstimator(features=stack, template=TRUE_MODEL).fit(TerrainPrior.from_array(density, stack.grid).sample(800, rng))
    test = TerrainPrior.from_array(density, stack.grid).sample(300, rng)
    # oracle: evaluate the fitted table per cell, normalise by hand (per m²), look up each point's cell
    r = est.model_.evaluate(stack)
    dens = r / (r.sum() * stack.grid.cell_area)
    u, v = stack.grid.to_pixel(test[:, 0], test[:, 1])
    expect = np.log(dens[v.astype(int), u.astype(int)]).mean()
    assert est.score(test) == pytest.approx(expect, rel=1e-10)
    off = np.vstack([test, [[0.0, 0.0]]])
    with pytest.warns(UserWarning, match="1 of 301 points have zero density"):
        assert est.score(off) == pytest.approx(expect, rel=1e-10)


def test_model_toml_round_trip_through_the_pipeline(tmp_path) -> None:
    stack = small_stack()
    est = PriorEstimator(features=stack, template=TRUE_MODEL).fit(
        TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(600, np.random.default_rng(1)))
    path = est.model_.write_toml(tmp_path / "model.toml")
    back = LikelihoodModel.read_toml(path)
    assert back.to_dict() == est.model_.to_dict()
    np.testing.assert_allclose(build_prior(stack, back).density, est.prior_.density, rtol=1e-12)
    assert back.terms["water"].values["water"] == 0.0


def test_points_on_water_and_off_grid_are_counted_dropped_or_softened() -> None:
    stack = small_stack()
    rng = np.random.default_rng(5)
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(500, rng)
    rows, cols = np.nonzero(stack["water"].values == 1)
    wet = np.column_stack(stack.grid.transform @ (cols[:7] + 0.5, rows[:7] + 0.5))
    allpts = np.vstack([pts, wet, [[0.0, 0.0], [1e9, 1e9]]])
    with pytest.warns(UserWarning, match=r"2 of 509 points off the grid.*7 on structural zeros"):
        dropped = PriorEstimator(features=stack, template=TRUE_MODEL).fit(allpts)
    assert (dropped.n_used_, dropped.n_on_zero_, dropped.n_off_grid_) == (500, 7, 2)
    assert dropped.on_zero_detail_ == {"water": {"water": 7}}
    assert dropped.likelihoods_["water"]["water"] == 0.0
    assert np.isneginf(dropped.score_samples(wet)).all()
    with pytest.warns(UserWarning, match="zeros softened to 0.001"):
        soft = PriorEstimator(features=stack, template=TRUE_MODEL, on_zero="soften", soften=1e-3).fit(allpts)
    assert soft.n_used_ == 507 and soft.likelihoods_["water"]["water"] == pytest.approx(1e-3)
    assert np.isfinite(soft.score_samples(wet)).all() and np.isfinite(soft.loglik_)


def test_flexible_binned_road_term_follows_the_true_curve() -> None:
    stack = small_stack()
    edges = [0.0, 40.0, 80.0, 160.0, 320.0]
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(6000, np.random.default_rng(8))
    est = PriorEstimator(features=stack, template=TRUE_MODEL, flexible={"road_distance": edges}, smooth_sd=0.0).fit(pts)
    (t,) = [t for t in est.terms_ if t.feature == "road_distance"]
    assert t.form == "binned"
    # oracle: the true road factor averaged over each bin's dry area (the other factors are
    # independent of position inside a bin only approximately, hence the loose bound)
    d = stack["road_distance"].values
    dry = stack["water"].values == 0
    bins = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, len(edges) - 1)
    r_true = TRUE_MODEL.terms["road_distance"](stack["road_distance"])
    mean_true = np.array([r_true[(bins == b) & dry].mean() for b in range(len(edges))])
    fitted = np.array([est.likelihoods_["road_distance"][lv] for lv in t.levels])
    np.testing.assert_allclose(fitted / fitted[t.reference], mean_true / mean_true[t.reference], rtol=0.2)


def test_sklearn_estimator_protocol() -> None:
    est = PriorEstimator(template=TRUE_MODEL, penalty_sd=2.0)
    params = est.get_params()
    assert params["penalty_sd"] == 2.0 and params["method"] == "ml" and "spatial_bandwidth" in params
    twin = clone(est).set_params(method="naive", on_zero="soften")
    assert twin.method == "naive" and est.method == "ml"
    stack = small_stack()
    with pytest.raises(ValueError, match="method"):
        PriorEstimator(features=stack, method="bayes").fit(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="on_zero"):
        PriorEstimator(features=stack, on_zero="ignore").fit(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="no points left"):
        PriorEstimator(features=stack, template=TRUE_MODEL).fit(np.array([[0.0, 0.0]]))
    with pytest.raises(NotFittedError):
        PriorEstimator(features=stack, template=TRUE_MODEL).score_samples(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="no feature stack"):
        PriorEstimator(template=TRUE_MODEL).fit(np.zeros((1, 2)))
    assert clone(PriorEstimator(features=stack)).features is stack  # the data is shared, not copied


_OFF_GRID = "X must be target points on the feature grid; the check's random X lies off it (no points left)"
_NOT_XY = "X must be (N, 2) map coordinates in metres; the check passes another number of columns"
SKLEARN_CHECKS_THAT_CANNOT_APPLY = {
    **dict.fromkeys(
        ["check_estimators_overwrite_params", "check_estimators_fit_returns_self", "check_readonly_memmap_input",
         "check_fit_idempotent", "check_fit_check_is_fitted", "check_n_features_in", "check_positive_only_tag_during_fit"],
        _OFF_GRID),
    **dict.fromkeys(
        ["check_fit_score_takes_y", "check_dont_overwrite_parameters", "check_n_features_in_after_fitting",
         "check_estimators_dtypes", "check_complex_data", "check_dtype_object", "check_estimators_empty_data_messages",
         "check_pipeline_consistency", "check_estimators_nan_inf", "check_estimators_pickle",
         "check_f_contiguous_array_estimator", "check_methods_sample_order_invariance", "check_methods_subset_invariance",
         "check_fit2d_1sample", "check_fit2d_1feature", "check_dict_unchanged", "check_fit2d_predict1d"],
        _NOT_XY),
    # sample_weight: the same contract on points on the grid is test_weights.py's (lists and Series,
    # not overwritten, zero weights refused by name, integer weights = repeated points)
    **dict.fromkeys(["check_sample_weights_pandas_series", "check_sample_weights_not_an_array",
                     "check_sample_weights_shape", "check_sample_weights_not_overwritten"], _OFF_GRID),
    **dict.fromkeys(["check_sample_weights_list", "check_all_zero_sample_weights_error",
                     "check_sample_weight_equivalence_on_dense_data"], _NOT_XY),
    **dict.fromkeys(["check_estimator_sparse_tag", "check_estimator_sparse_array", "check_estimator_sparse_matrix"],
                    "points are a dense (N, 2) array; check_points refuses sparse input with its own message"),
}
"""scikit-learn's estimator checks PriorEstimator fails by design, and why (docs/learn.md lists them)."""


def test_sklearn_estimator_checks() -> None:
    """Every check of scikit-learn's estimator contract that can apply to an estimator of map points
    on one grid passes; the others are listed with the reason."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_estimator(PriorEstimator(features=small_stack(), template=TRUE_MODEL),
                        expected_failed_checks=SKLEARN_CHECKS_THAT_CANNOT_APPLY)


def test_grid_pass_is_cached_per_stack() -> None:
    stack = small_stack()
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(300, np.random.default_rng(2))
    first = PriorEstimator(features=stack, template=TRUE_MODEL).fit(pts)
    again = clone(first).set_params(method="naive").fit(pts[:200])
    assert again.cell_stats_.area is first.cell_stats_.area  # the one pass, not redone
    copy = FeatureStack(stack.grid, dict(stack.features))
    other = PriorEstimator(features=copy, template=TRUE_MODEL).fit(pts)
    assert other.cell_stats_.area is not first.cell_stats_.area
    np.testing.assert_array_equal(other.cell_stats_.area, first.cell_stats_.area)
    np.testing.assert_array_equal(other.theta_, first.theta_)


def test_hybrid_finds_a_spatial_cluster_and_stays_flat_without_one() -> None:
    """Targets from the terrain prior times a Gaussian bump: the hybrid's spatial term switches on
    (γ > 0) and beats the terrain-only fit on fresh points; on pure terrain data it changes nothing."""
    stack = small_stack()
    xs, ys = stack.grid.cell_centres()
    cx, cy = xs.mean() - 300, ys.mean() - 200
    bump = np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * 150.0**2))
    rng = np.random.default_rng(4)
    bumpy = TRUE_MODEL.evaluate(stack) * (0.2 + 5 * bump)
    pts = TerrainPrior.from_array(bumpy, stack.grid).sample(2000, rng)
    terrain = PriorEstimator(features=stack, template=TRUE_MODEL).fit(pts)
    hybrid = PriorEstimator(features=stack, template=TRUE_MODEL, spatial_bandwidth=120.0).fit(pts)
    p = hybrid.likelihoods_["spatial_kde"]
    assert p["gamma"] > 0.3 and 0 < p["alpha"] <= 1
    test = TerrainPrior.from_array(bumpy, stack.grid).sample(2000, rng)
    assert hybrid.score(test) > terrain.score(test) + 0.05
    plain = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(2000, rng)
    fresh = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(2000, rng)
    t2 = PriorEstimator(features=stack, template=TRUE_MODEL).fit(plain)
    h2 = PriorEstimator(features=stack, template=TRUE_MODEL, spatial_bandwidth=120.0).fit(plain)
    assert abs(h2.score(fresh) - t2.score(fresh)) < 0.02
