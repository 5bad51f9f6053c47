"""The mixture of learned priors: its weights against a direct optimum, recovered on synthetic
ground truth, and its density consistent with its score."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar
from sklearn.base import clone

from pipeline.features.stack import Feature
from pipeline.learn import (
    BlockWindow,
    MixturePrior,
    PriorEstimator,
    block_folds,
    block_ids,
    simplex_weights,
)
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.learn_synth import small_stack

W_ROAD = 0.3
"""Weight of the road-driven part of the synthetic truth."""


@given(st.integers(0, 10_000), st.integers(5, 60), st.floats(0.1, 4.0))
@settings(max_examples=40, deadline=None)
def test_two_weights_match_a_bounded_scalar_optimum(seed: int, n: int, spread: float) -> None:
    logp = np.random.default_rng(seed).normal(0.0, spread, (n, 2))
    w = simplex_weights(logp)
    ll = lambda a: -np.mean(np.logaddexp(np.log(a) + logp[:, 0], np.log1p(-a) + logp[:, 1]))  # noqa: E731
    best = minimize_scalar(ll, bounds=(1e-12, 1 - 1e-12), method="bounded", options={"xatol": 1e-10})
    assert w.sum() == pytest.approx(1.0)
    assert ll(np.clip(w[0], 1e-12, 1 - 1e-12)) <= best.fun + 1e-9


def test_three_weights_beat_every_point_of_a_dense_simplex_grid() -> None:
    logp = np.random.default_rng(3).normal(0.0, 2.0, (200, 3))
    w = simplex_weights(logp)
    grid = [(a, b, 1 - a - b) for a in np.linspace(0, 1, 61) for b in np.linspace(0, 1, 61) if a + b <= 1]
    with np.errstate(divide="ignore"):
        lls = [np.mean(np.log(np.exp(logp) @ np.array(g))) for g in grid]
    assert np.mean(np.log(np.exp(logp) @ w)) >= max(lls) - 1e-9


def test_a_point_no_component_reaches_is_an_error() -> None:
    with pytest.raises(ValueError, match="every component"):
        simplex_weights(np.array([[0.0, -np.inf], [-np.inf, -np.inf]]))


@pytest.fixture(scope="module")
def world():
    """A 120 x 160 stack (20 m cells) with elevation; the truth is W_ROAD · p_road + (1 − W_ROAD) · p_elev,
    p_road depending on the road distance only and p_elev on elevation only."""
    stack = small_stack(120, 160)
    rows, cols = np.mgrid[0:120, 0:160]
    stack.add(Feature("elevation", 200 + 100 * np.sin(cols / 30.0) + 2.0 * rows, "continuous", "m"))
    dry = stack["water"].values == 0
    road = np.exp(-1.0 * np.log1p(stack["road_distance"].values)) * dry
    elev = np.exp(-0.5 * ((stack["elevation"].values - 260.0) / 40.0) ** 2) * dry
    truth = W_ROAD * road / road.sum() + (1 - W_ROAD) * elev / elev.sum()
    return stack, TerrainPrior.from_array(truth, stack.grid)


def components(stack) -> tuple[PriorEstimator, PriorEstimator]:
    return (PriorEstimator(features=stack, feature_names=("water", "road_distance"),
                           forms={"road_distance": {"form": "linear", "scale": "log1p"}}),
            PriorEstimator(features=stack, feature_names=("water", "elevation"),
                           forms={"elevation": {"form": "spline", "knots": 6, "smoothing": 1.0}}))


def test_the_weights_are_recovered_and_the_mixture_beats_each_component_held_out(world) -> None:
    stack, truth = world
    rng = np.random.default_rng(11)
    train, test = truth.sample(4000, rng), truth.sample(4000, rng)
    mix = MixturePrior(components(stack), spatial_block=400.0, n_folds=4).fit(train)
    held = mix.score(test)
    # the weights chosen on cross-fitted blocks are near the best fixed weights on fresh points
    logp = np.column_stack([e.score_samples(test) for e in mix.estimators_])
    best = max(np.mean(np.logaddexp(np.log(a) + logp[:, 0], np.log1p(-a) + logp[:, 1])) for a in np.linspace(0.01, 0.99, 99))
    assert 0.05 < mix.weights_[0] < 0.95 and held > best - 0.01
    for est in components(stack):
        assert held > est.fit(train).score(test) + 0.05
    # the density it writes is the one it scores, and it integrates to 1
    prior = mix.prior_
    d = prior.density_at(test[:, 0], test[:, 1])
    np.testing.assert_allclose(np.log(d), mix.score_samples(test), rtol=1e-5)
    assert float(np.sum(prior.density) * stack.grid.cell_area) == pytest.approx(1.0, rel=1e-5)
    # cross-fitted by hand: each component fitted without a fold's blocks, those blocks outside its window
    fold = block_folds(train, stack.grid.bounds[:2], 400.0, 4)
    by_hand = np.empty((len(train), 2))
    for f in range(4):
        out = fold == f
        window = BlockWindow(400.0, set(block_ids(train[out], stack.grid.bounds[:2], 400.0).tolist()))
        for k, est in enumerate(components(stack)):
            by_hand[out, k] = est.set_params(window=window).fit(train[~out]).score_samples(train[out])
    assert mix.cv_loglik_ == pytest.approx(float(np.mean(np.logaddexp(*(np.log(mix.weights_) + by_hand).T))), abs=1e-9)


def test_a_component_without_information_gets_almost_no_weight(world) -> None:
    stack, _ = world
    dry = stack["water"].values == 0
    road = TerrainPrior.from_array(np.exp(-1.0 * np.log1p(stack["road_distance"].values)) * dry, stack.grid)
    flat = PriorEstimator(features=stack, feature_names=("water",))  # uniform on dry land
    mix = MixturePrior((components(stack)[0], flat), spatial_block=400.0).fit(road.sample(3000, np.random.default_rng(2)))
    assert mix.weights_[1] < 0.05


def test_the_estimator_contract_and_named_errors(world) -> None:
    stack, truth = world
    mix = MixturePrior(components(stack), spatial_block=400.0)
    assert clone(mix).get_params()["spatial_block"] == 400.0
    pts = truth.sample(200, np.random.default_rng(0))
    with pytest.raises(ValueError, match="at least 2 components"):
        MixturePrior(components(stack)[:1]).fit(pts)
    with pytest.raises(ValueError, match="n_folds"):
        MixturePrior(components(stack), n_folds=1).fit(pts)
    with pytest.raises(ValueError, match="fewer than 2 blocks"):
        MixturePrior(components(stack), spatial_block=1e6).fit(pts)
