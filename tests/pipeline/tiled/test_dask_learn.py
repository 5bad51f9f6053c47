"""The learning pass per tile on a real 2-process Dask cluster against the single-process statistics."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.build.region import build_features
from pipeline.config.region import load_config
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import Grid
from pipeline.learn.estimator import make_terms
from pipeline.learn.sufficient import Term, cell_stats, with_range
from pipeline.tiled.cells import merge_cell_stats, tiled_cell_stats, tiled_terms
from pipeline.tiled.windows import TiledBuildError
from tests.dask_helpers import shared_client
from tests.pipeline.tiled.test_build import region


def assert_stats_equal(got, ref) -> None:
    """Same combinations in the same order, exact areas, continuous means within rounding."""
    np.testing.assert_array_equal(got.index, ref.index)
    np.testing.assert_array_equal(got.area, ref.area)
    np.testing.assert_allclose(got.value, ref.value, rtol=1e-12, atol=0, equal_nan=True)
    assert got.n_cells == ref.n_cells and got.cell_area == ref.cell_area and got.terms == ref.terms


def test_tiled_learning_pass_equals_single_process(tmp_path):
    config = load_config(region(tmp_path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack = build_features(config, progress=False)
    ref_terms, _ = make_terms(stack, config.model, tuple(config.model.terms), None, None, 8)
    client = shared_client()
    terms = tiled_terms(config, config.model, client, tile=150, progress=False)
    assert terms == ref_terms  # codes, labels, zeros and the distance's fine-bin range
    got = tiled_cell_stats(config, terms, client, tile=150, progress=False)
    assert_stats_equal(got, cell_stats(stack, tuple(ref_terms)))
    assert got.total_area == pytest.approx(config.grid.height * config.grid.width * config.grid.cell_area, rel=0, abs=0)


def test_fitted_distance_needs_a_configured_cap(tmp_path):
    config = load_config(region(tmp_path, max_distance_m=None))
    with pytest.raises(TiledBuildError, match=r"features.road_distance.*max_distance_m"):
        tiled_terms(config, config.model, shared_client(), progress=False)


@settings(max_examples=15, deadline=None)
@given(h=st.integers(2, 40), w=st.integers(1, 30), cuts=st.lists(st.integers(1, 39), max_size=4), seed=st.integers(0, 999))
def test_merge_over_row_bands_equals_whole(h, w, cuts, seed):
    """Oracle: cell_stats of the whole stack; parts: row bands of it, in shuffled order."""
    rng = np.random.default_rng(seed)
    grid = Grid("EPSG:32734", Affine(20.0, 0, 0, 0, -20.0, 0), h, w)
    cat = rng.integers(-1, 3, (h, w)).astype(np.int16)  # -1: no data
    dist = np.where(rng.random((h, w)) < 0.1, np.nan, rng.uniform(0, 300, (h, w)))
    stack = FeatureStack(grid, {"c": Feature("c", cat, "categorical", labels={0: "a", 1: "b", 2: "c"}),
                                "d": Feature("d", dist, "continuous", "m")})
    if not np.isfinite(dist).any():
        return
    terms = (Term("c", "categorical", ("a", "b", "c"), (0, 1, 2)), with_range(Term("d", "road", bin_width=25.0), dist))
    edges = sorted({0, h, *(c for c in cuts if c < h)})
    parts = []
    for r0, r1 in zip(edges, edges[1:], strict=False):
        sub = FeatureStack(grid.window_grid(r0, 0, r1 - r0, w),
                           {n: dataclasses.replace(f, values=f.values[r0:r1]) for n, f in stack.features.items()})
        parts.append(cell_stats(sub, terms))
    rng.shuffle(parts)
    assert_stats_equal(merge_cell_stats(parts), cell_stats(stack, terms))
