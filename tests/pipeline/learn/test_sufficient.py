"""Sufficient statistics and the Poisson objective against direct per-cell evaluation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import approx_fprime

from pipeline.learn.estimator import PriorEstimator, make_terms
from pipeline.learn.poisson import Objective, term_params
from pipeline.learn.sufficient import cell_stats, point_stats
from pipeline.prior.likelihood import (
    BinnedLikelihood,
    CategoricalLikelihood,
    LikelihoodModel,
)
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.learn_synth import TRUE_MODEL, small_stack


def objective_for(stack, template, points, flexible=None):
    est = PriorEstimator(features=stack, template=template, flexible=flexible, penalty_sd=1e6, smooth_sd=0.0)
    est.fit(points)
    return est, Objective(est.cell_stats_, est.point_stats_, est.params_, list(range(len(est.terms_))), 1e6, 0.0)


def model_at(est, x):
    """The LikelihoodModel that parameter vector x stands for (written through the estimator's own path)."""
    est.theta_ = x
    est._describe(Objective(est.cell_stats_, est.point_stats_, est.params_, list(range(len(est.terms_))), 1e6, 0.0))
    return est.model_


@given(rows_per_chunk=st.integers(1, 70), seed=st.integers(0, 10_000))
@settings(max_examples=15, deadline=None)
def test_cell_stats_areas_match_brute_force_counts(rows_per_chunk: int, seed: int) -> None:
    stack = small_stack(23, 31, seed=seed)
    terms, _ = make_terms(stack, TRUE_MODEL, None, None, 7.0, 8)
    cells = cell_stats(stack, tuple(terms), rows_per_chunk)
    # brute force: every cell's tuple of level indices, counted with a Python dict
    idx = np.stack([t.index(stack[t.feature].values.ravel()) for t in terms], axis=1)
    counts: dict[tuple, int] = {}
    sums: dict[tuple, float] = {}
    d = stack["road_distance"].values.ravel()
    for row, dv in zip(map(tuple, idx), d, strict=True):
        counts[row] = counts.get(row, 0) + 1
        sums[row] = sums.get(row, 0.0) + dv
    assert len(counts) == len(cells.area)
    k_road = [t.feature for t in terms].index("road_distance")
    for row, area, val in zip(map(tuple, cells.index), cells.area, cells.value[:, k_road], strict=True):
        assert area == pytest.approx(counts[row] * stack.grid.cell_area)
        assert val == pytest.approx(sums[row] / counts[row])
    assert cells.total_area == pytest.approx(stack.grid.width * stack.grid.height * stack.grid.cell_area)


def test_unique_path_equals_dense_bincount(monkeypatch) -> None:
    import pipeline.learn.sufficient as suff

    stack = small_stack(40, 50)
    terms, _ = make_terms(stack, TRUE_MODEL, None, None, 1.0, 8)
    dense = cell_stats(stack, tuple(terms), 7)
    monkeypatch.setattr(suff, "_DENSE_KEYS", 1)
    sparse = cell_stats(stack, tuple(terms), 7)
    np.testing.assert_array_equal(dense.index, sparse.index)
    np.testing.assert_allclose(dense.area, sparse.area)
    np.testing.assert_allclose(dense.value, sparse.value, equal_nan=True)


@pytest.mark.parametrize("flexible", [None, {"road_distance": [0.0, 50.0, 150.0, 400.0]}])
def test_loglik_matches_direct_per_cell_density(flexible) -> None:
    """ℓ(θ) from the statistics == Σ log density_at(points) of the prior built cell by cell by the
    lead's LikelihoodModel.evaluate + TerrainPrior (fine distance bins are the only approximation)."""
    stack = small_stack()
    rng = np.random.default_rng(3)
    r = TRUE_MODEL.evaluate(stack)
    pts = TerrainPrior.from_array(r, stack.grid).sample(400, rng)
    est, obj = objective_for(stack, TRUE_MODEL, pts, flexible)
    for trial in range(4):
        x = obj.x0 + (rng.normal(scale=0.4, size=obj.x0.shape) if trial else 0.0)
        lo = np.array([b[0] if b[0] is not None else -np.inf for b in obj.bounds])
        hi = np.array([b[1] if b[1] is not None else np.inf for b in obj.bounds])
        x = np.clip(x, lo, hi)
        model = model_at(est, x)
        prior = TerrainPrior.from_array(model.evaluate(stack), stack.grid)
        direct = np.log(prior.density_at(pts[:, 0], pts[:, 1])).sum()
        assert obj.loglik(x) == pytest.approx(direct, rel=2e-5, abs=1e-3)


def test_gradient_matches_finite_differences() -> None:
    stack = small_stack()
    rng = np.random.default_rng(4)
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(300, rng)
    template = LikelihoodModel({**TRUE_MODEL.terms, "land": CategoricalLikelihood({"grass": 1.0, "bush": 0.7, "rock": 0.3})})
    # the bin [10, 20) m is empty on a 20 m grid (distances 0, 20, 28.3, ...): fixed, unidentified
    est, obj = objective_for(stack, template, pts, {"road_distance": [0.0, 10.0, 20.0, 100.0, 300.0]})
    obj.penalty_sd, obj.smooth_sd = 1.5, 0.7  # exercise both penalty gradients
    x = obj.x0 + rng.normal(scale=0.2, size=obj.x0.shape)
    g = obj(x)[1]
    fd = approx_fprime(x, lambda z: obj(z)[0], 1e-7)
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6)
    # penalty oracle by hand: ridge on free values, smoothness over consecutive bins that have area
    k = [t.feature for t in est.terms_].index("road_distance")
    p = est.params_[k]
    assert p.has_area.tolist() == [True, False, True, True, True]
    road = obj.split(x)[obj.active.index(k)]
    lut = p.lut(road)[:-1]
    steps = np.diff(lut[[0, 2, 3, 4]])
    ridge = sum(float(th @ th) for th in obj.split(x)) / 1.5**2
    assert obj.penalty(x)[0] == pytest.approx(0.5 * ridge + 0.5 * float(steps @ steps) / 0.7**2, rel=1e-12)


def test_road_gradient_matches_finite_differences() -> None:
    stack = small_stack()
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(300, np.random.default_rng(5))
    _, obj = objective_for(stack, TRUE_MODEL, pts)
    x = obj.x0.copy()
    x[-2:] = [np.log(120.0), 0.3]  # the road term is last in TRUE_MODEL
    np.testing.assert_allclose(obj(x)[1], approx_fprime(x, lambda z: obj(z)[0], 1e-7), rtol=1e-4, atol=1e-6)


def test_point_stats_mark_off_grid_and_sample_exact_values() -> None:
    stack = small_stack()
    terms, _ = make_terms(stack, TRUE_MODEL, None, None, None, 8)
    xmin, ymin, xmax, ymax = stack.grid.bounds
    pts = np.array([[xmin + 30.0, ymax - 50.0], [xmin - 1.0, ymax - 50.0], [xmax + 5.0, ymin + 5.0]])
    ps = point_stats(stack, tuple(terms), pts)
    np.testing.assert_array_equal(ps.inside, [True, False, False])
    k = [t.feature for t in terms].index("road_distance")
    assert ps.value[0, k] == stack["road_distance"].values[2, 1]
    assert (ps.index[1:] == -1).all()


def test_binned_template_keeps_its_edges_and_zero_bins() -> None:
    stack = small_stack()
    template = LikelihoodModel({"road_distance": BinnedLikelihood([0.0, 30.0, 100.0], [0.0, 1.0, 0.5])})
    terms, _ = make_terms(stack, template, None, None, None, 8)
    (t,) = terms
    assert t.form == "binned" and t.edges == (0.0, 30.0, 100.0) and t.zeros == frozenset({0})
    p = term_params(t, np.array([1.0, 1.0, 1.0]), None)
    assert p.fixed[0] == -np.inf and 0 not in p.free


def test_bad_points_raise_naming_indices() -> None:
    stack = small_stack()
    terms, _ = make_terms(stack, TRUE_MODEL, None, None, None, 8)
    with pytest.raises(ValueError, match="shape"):
        point_stats(stack, tuple(terms), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"indices \[1\]"):
        point_stats(stack, tuple(terms), np.array([[300_100.0, 6_199_900.0], [np.nan, 0.0]]))
