"""Grid KDE and its held-out values against direct sums; scikit-learn KDE baseline; spatial block CV."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from sklearn.model_selection import GroupKFold, cross_val_score

from pipeline.learn.estimator import PriorEstimator
from pipeline.learn.evaluate import block_cv
from pipeline.learn.kde import KDE_EPS, block_ids, fit_kde_cv, grid_kde, log_kde_feature
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.learn_synth import TRUE_MODEL, small_stack


def test_grid_kde_matches_a_direct_gaussian_sum() -> None:
    stack = small_stack(40, 50)
    rng = np.random.default_rng(0)
    pts = TerrainPrior.from_array(np.ones(stack.grid.shape), stack.grid).sample(60, rng)
    h = 90.0
    dens = grid_kde(stack.grid, pts, h)
    # oracle: 2-D Gaussian mixture of the points snapped to their cell centres, at every cell centre
    u, v = stack.grid.to_pixel(pts[:, 0], pts[:, 1])
    snapped = np.column_stack(stack.grid.transform @ (np.floor(u) + 0.5, np.floor(v) + 0.5))
    xs, ys = stack.grid.cell_centres()
    d2 = (xs[..., None] - snapped[:, 0]) ** 2 + (ys[..., None] - snapped[:, 1]) ** 2
    direct = np.exp(-d2 / (2 * h * h)).sum(-1) / (2 * np.pi * h * h * len(pts))
    big = direct > direct.max() * 1e-3  # the grid kernel is truncated at 4 bandwidths
    np.testing.assert_allclose(dens[big], direct[big], rtol=2e-3)


@pytest.mark.parametrize("block", [None, 300.0])
def test_held_out_kde_values_equal_a_kde_of_the_other_points(block) -> None:
    stack = small_stack(40, 50)
    pts = TerrainPrior.from_array(np.ones(stack.grid.shape), stack.grid).sample(80, np.random.default_rng(1))
    groups = None if block is None else block_ids(pts, stack.grid.bounds[:2], block)
    h = 70.0
    _, held = log_kde_feature(stack.grid, pts, h, groups)
    g = np.arange(len(pts)) if groups is None else groups
    area = stack.grid.width * stack.grid.height * stack.grid.cell_area
    u, v = stack.grid.to_pixel(pts[:, 0], pts[:, 1])
    for i in range(0, len(pts), 7):
        others = pts[g != g[i]]
        oracle = grid_kde(stack.grid, others, h)[int(v[i]), int(u[i])]
        assert held[i] == pytest.approx(np.log(oracle * area + KDE_EPS), rel=1e-9)


def test_kde_baseline_picks_a_candidate_and_scores_as_a_gaussian_mixture() -> None:
    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.normal([0, 0], 100, (150, 2)), rng.normal([3000, 0], 100, (150, 2))])
    groups = block_ids(pts, (-5000.0, -5000.0), 500.0)
    cands = np.array([10.0, 100.0, 2000.0])
    kde = fit_kde_cv(pts, groups, cands)
    assert kde.bandwidth == 100.0
    q = rng.normal([0, 0], 200, (20, 2))
    h = kde.bandwidth
    d2 = ((q[:, None, :] - pts[None]) ** 2).sum(-1)
    direct = np.log(np.exp(-d2 / (2 * h * h)).sum(1) / (2 * np.pi * h * h * len(pts)))
    np.testing.assert_allclose(kde.score_samples(q), direct, rtol=1e-6)


def test_block_cv_scores_models_on_the_same_held_out_blocks() -> None:
    stack = small_stack(60, 80)
    xs, ys = stack.grid.cell_centres()
    # a spatial cluster (sd 250 m, blocks of 300 m) the terrain lacks, which other blocks' points predict
    bump = np.exp(-((xs - xs.mean() + 300) ** 2 + (ys - ys.mean() - 200) ** 2) / (2 * 250.0**2))
    rng = np.random.default_rng(3)
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack) * (0.05 + 8 * bump), stack.grid).sample(1500, rng)
    rows, cols = np.nonzero(stack["water"].values == 1)
    wet = np.column_stack(stack.grid.transform @ (cols[:3] + 0.5, rows[:3] + 0.5))
    with pytest.warns(UserWarning, match="3 on structural zeros"):
        res = block_cv(np.vstack([pts, wet]), PriorEstimator(features=stack, template=TRUE_MODEL), n_folds=4,
                       block_size=300.0, bandwidths=np.array([60.0, 150.0, 400.0]), progress=False)
    s = res.summary()
    assert res.n_excluded == 3 and res.n_test.sum() == 1500 and s["folds"] == 4
    gain = {m: v["pooled"] for m, v in s["gain_nats"].items()}
    assert gain["uniform"] == 0.0
    # oracle for the uniform score: minus the log of the grid area
    area = stack.grid.width * stack.grid.height * stack.grid.cell_area
    assert s["uniform_nats"] == pytest.approx(-np.log(area))
    assert gain["terrain"] > 0.2 and gain["naive"] > 0.0
    assert gain["hybrid"] > gain["terrain"]  # the bump is a real spatial effect the terrain lacks
    assert set(res.bandwidths) <= {60.0, 150.0, 400.0}
    for m in s["gain_nats"]:
        g = s["gain_nats"][m]
        assert g["min"] <= g["mean"] <= g["max"] and len(g["per_fold"]) == 4
    # the blocks each fold held out, against the block of every held-out point counted by hand
    x0, y0 = stack.grid.bounds[:2]
    all_pts = np.vstack([pts, wet])
    by_hand = [sorted({(int((x - x0) // 300.0), int((y - y0) // 300.0)) for x, y in all_pts[te]}) for te in res.extra["test_index"]]
    assert s["n_blocks_per_fold"] == [len(b) for b in by_hand]
    assert sum(s["n_blocks_per_fold"]) == len({b for fold in by_hand for b in fold})  # no block in two folds


def test_block_cv_needs_enough_blocks() -> None:
    stack = small_stack()
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(50, np.random.default_rng(0))
    with pytest.raises(ValueError, match="blocks"):
        block_cv(pts, PriorEstimator(features=stack, template=TRUE_MODEL), n_folds=5, block_size=1e6, progress=False)


def test_cross_val_score_with_block_groups_equals_block_cv() -> None:
    """scikit-learn's own CV on spatial-block groups gives block_cv's per-fold terrain scores when
    the folds are fitted on the whole grid (``window=False``)."""
    stack = small_stack(60, 80)
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(800, np.random.default_rng(4))
    est = PriorEstimator(features=stack, template=TRUE_MODEL)
    res = block_cv(pts, est, n_folds=4, block_size=300.0, models=("uniform", "terrain"), progress=False, window=False)
    assert res.n_excluded == 0
    groups = block_ids(pts, stack.grid.bounds[:2], 300.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no held-out point may be left out of the score
        got = cross_val_score(est, pts, groups=groups, cv=GroupKFold(4))
    np.testing.assert_array_equal(got, res.scores[:, 1])
