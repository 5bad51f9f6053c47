"""The observation window: cell statistics split by block, fits that leave unobserved blocks out, CV folds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.learn import BlockWindow, PriorEstimator, block_cv, block_ids, cell_stats, make_terms
from pipeline.learn.window import cell_blocks
from pipeline.prior.likelihood import CategoricalLikelihood, LikelihoodModel
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.learn_synth import TRUE_MODEL, small_stack


@given(block=st.sampled_from([100.0, 230.0, 400.0, 10_000.0]), rows_per_chunk=st.integers(1, 40), seed=st.integers(0, 1000))
@settings(max_examples=12, deadline=None)
def test_cell_stats_by_block_match_brute_force_counts(block: float, rows_per_chunk: int, seed: int) -> None:
    stack = small_stack(23, 31, seed=seed)
    terms, _ = make_terms(stack, TRUE_MODEL, None, None, 7.0, 8)
    cells = cell_stats(stack, tuple(terms), rows_per_chunk, block_size=block)
    # brute force: each cell's levels and the block of its centre (block_ids of the centre point)
    xs, ys = stack.grid.cell_centres()
    blocks = block_ids(np.column_stack([xs.ravel(), ys.ravel()]), stack.grid.bounds[:2], block)
    np.testing.assert_array_equal(cell_blocks(stack.grid, block), blocks)
    idx = np.stack([t.index(stack[t.feature].values.ravel()) for t in terms], axis=1)
    counts: dict[tuple, int] = {}
    for key in zip(map(tuple, idx), blocks.tolist(), strict=True):
        counts[key] = counts.get(key, 0) + 1
    assert len(counts) == len(cells.area) and cells.block_size == block
    for row, b, area in zip(map(tuple, cells.index), cells.block.tolist(), cells.area, strict=True):
        assert area == pytest.approx(counts[(row, b)] * stack.grid.cell_area)
    # a window is a selection of rows: its area is the observed cells'
    drop = set(np.unique(blocks)[::2].tolist())
    inside = cells.within(BlockWindow(block, drop))
    assert inside.total_area == pytest.approx(float(np.sum(~np.isin(blocks, list(drop)))) * stack.grid.cell_area)


def test_a_windowed_fit_is_the_closed_form_on_the_observed_area() -> None:
    """One categorical feature: the Poisson ML fit in a window W is r_c ∝ n_c / A_c(W), areas counted in W only."""
    stack = small_stack(60, 80)
    model = LikelihoodModel({"land": CategoricalLikelihood({"grass": 1.0, "bush": 0.5, "rock": 0.2})})
    pts = TerrainPrior.from_array(model.evaluate(stack), stack.grid).sample(3000, np.random.default_rng(1))
    origin = stack.grid.bounds[:2]
    blocks = block_ids(pts, origin, 300.0)
    held = set(np.unique(blocks)[1::3].tolist())
    window = BlockWindow(300.0, held)
    train = pts[~np.isin(blocks, list(held))]
    est = PriorEstimator(features=stack, template=model, penalty_sd=1e6, window=window).fit(train)
    xs, ys = stack.grid.cell_centres()
    observed = ~np.isin(block_ids(np.column_stack([xs.ravel(), ys.ravel()]), origin, 300.0), list(held))
    land = stack["land"].values.ravel()
    at = stack.sample(train[:, 0], train[:, 1])["land"]
    rate = {name: np.sum(at == code) / np.sum(observed & (land == code)) for code, name in ((0, "grass"), (1, "bush"), (2, "rock"))}
    fitted = est.likelihoods_["land"]
    for name in ("bush", "rock"):
        assert fitted[name] / fitted["grass"] == pytest.approx(rate[name] / rate["grass"], rel=1e-5)
    # the whole-grid fit of the same points counts the held-out blocks as searched and empty: another answer
    plain = PriorEstimator(features=stack, template=model, penalty_sd=1e6).fit(train)
    other = plain.likelihoods_["land"]
    assert abs(other["rock"] / other["grass"] - fitted["rock"] / fitted["grass"]) > 1e-3
    # still a density over the whole grid
    assert float(est.prior_.density.sum() * stack.grid.cell_area) == pytest.approx(1.0, rel=1e-5)


def test_points_in_unobserved_blocks_are_an_error() -> None:
    stack = small_stack(60, 80)
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(200, np.random.default_rng(2))
    window = BlockWindow(300.0, {int(block_ids(pts[:1], stack.grid.bounds[:2], 300.0)[0])})
    with pytest.raises(ValueError, match="window: .* points lie in its unobserved blocks"):
        PriorEstimator(features=stack, template=TRUE_MODEL, window=window).fit(pts)
    with pytest.raises(ValueError, match="block size must be > 0"):
        BlockWindow(0.0)
    with pytest.raises(ValueError, match="window must be None or a BlockWindow"):
        PriorEstimator(features=stack, template=TRUE_MODEL, window={"size": 300}).fit(pts)


def test_block_cv_fits_each_fold_without_its_held_out_blocks() -> None:
    stack = small_stack(60, 80)
    pts = TerrainPrior.from_array(TRUE_MODEL.evaluate(stack), stack.grid).sample(800, np.random.default_rng(4))
    est = PriorEstimator(features=stack, template=TRUE_MODEL)
    res = block_cv(pts, est, n_folds=4, block_size=300.0, models=("uniform", "terrain"), progress=False)
    origin = stack.grid.bounds[:2]
    for j, test in enumerate(res.extra["test_index"]):
        train = np.setdiff1d(np.arange(len(pts)), test)
        window = BlockWindow(300.0, set(block_ids(pts[test], origin, 300.0).tolist()))
        assert res.extra["windows"][j] == window
        assert res.scores[j, 1] == pytest.approx(est.set_params(window=window).fit(pts[train]).score(pts[test]), abs=1e-12)
    plain = block_cv(pts, est.set_params(window=None), n_folds=4, block_size=300.0, models=("uniform", "terrain"),
                     progress=False, window=False)
    assert plain.extra["windows"] == [None] * 4 and not np.allclose(plain.scores[:, 1], res.scores[:, 1])


@given(st.sets(st.integers(0, 50)), st.sets(st.integers(0, 50)))
def test_without_adds_unobserved_blocks(a: set[int], b: set[int]) -> None:
    assert BlockWindow(100.0, a).without(b) == BlockWindow(100.0, a | b)
