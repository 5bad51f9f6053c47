"""The learning pass per tile on a real 2-process Dask cluster: cell and point statistics against the
single-process ones, and the fit from them against the in-memory fit."""

from __future__ import annotations

import dataclasses
import json
import re
import tomllib
import warnings

import numpy as np
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.build.region import build_features, build_prior
from pipeline.cli import main
from pipeline.config.region import load_config
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import Grid
from pipeline.learn.estimator import PriorEstimator, make_terms
from pipeline.learn.sufficient import Term, cell_stats, point_stats, with_range
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.tiled.learn import (
    merge_cell_stats,
    tiled_cell_stats,
    tiled_point_stats,
    tiled_stats,
    tiled_terms,
)
from pipeline.tiled.windows import TiledBuildError
from tests.dask_helpers import shared_client
from tests.pipeline.gis_helpers import write_config
from tests.pipeline.tiled.test_build import region

TILE = 96  # the 300 x 300 cut in 4 x 4 tiles, the last row and column ragged


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The cut region (distance capped at 600 m), its whole-grid features, and points: draws from
    the hand-set prior, points exactly on tile edges and grid corners, uniform points (some on
    structural zeros), and points off the grid."""
    tmp = tmp_path_factory.mktemp("learn_tiled")
    config = load_config(region(tmp))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack = build_features(config, progress=False)
    g = config.grid
    rng = np.random.default_rng(3)
    drawn = build_prior(stack, config.model).sample(600, rng)
    x0, y0, x1, y1 = g.bounds
    edges = np.array([[x0 + TILE * g.dx, y1 - TILE * g.dy], [x0 + 2 * TILE * g.dx, y1 - 5.0], [x0, y0 + 1e-6],
                      [x0 + 3 * TILE * g.dx, y1 - 3 * TILE * g.dy], [x1 - 1e-6, y1]])
    off = np.array([[x0 - 1.0, y1 - 100.0], [x1 + 50.0, y0 + 50.0], [x0 + 100.0, y1 + 0.5]])
    uniform = np.column_stack([rng.uniform(x0, x1, 200), rng.uniform(y0, y1, 200)])  # some on water / obstacles
    pts = np.concatenate([drawn, edges, uniform, off])
    return tmp, config, stack, pts


# ------------------------------------------------------------------------------ cell statistics
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


# ----------------------------------------------------------------------------- point statistics
def test_tiled_point_stats_equal_whole_grid_sampling(setup):
    """Oracle: point_stats on the whole grid's stack, for the same terms."""
    _, config, stack, pts = setup
    terms, _ = make_terms(stack, config.model, None, None, None, 8)
    got = tiled_point_stats(config, terms, pts, shared_client(), TILE, progress=False)
    ref = point_stats(stack, tuple(terms), pts)
    np.testing.assert_array_equal(got.inside, ref.inside)
    np.testing.assert_array_equal(got.index, ref.index)
    np.testing.assert_array_equal(got.value, ref.value)  # same cell, same value: exact
    assert (~got.inside).sum() == 3
    with pytest.raises(ValueError, match="tile must be >= 1"):
        tiled_point_stats(config, terms, pts, shared_client(), 0, progress=False)
    with pytest.raises(ValueError, match="non-finite coordinates at indices \\[1\\]"):
        tiled_point_stats(config, terms, np.array([[0.0, 0.0], [np.nan, 1.0]]), shared_client(), TILE, progress=False)


@pytest.mark.parametrize("method", ["ml", "naive"])
def test_fit_from_tiled_stats_equals_in_memory_fit(setup, method):
    """Oracle: PriorEstimator.fit on the whole grid's stack with the same points."""
    _, config, stack, pts = setup
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # off-grid and structural-zero points, counted below
        ref = PriorEstimator(features=stack, template=config.model, method=method).fit(pts)
        cells, points = tiled_stats(config, ref, pts, shared_client(), TILE, progress=False)
        got = PriorEstimator(template=config.model, method=method).fit_stats(cells, points)
    assert got.terms_ == ref.terms_  # same levels, references and structural zeros
    assert (got.n_points_, got.n_used_, got.n_off_grid_, got.n_on_zero_) == (ref.n_points_, ref.n_used_, ref.n_off_grid_, ref.n_on_zero_)
    assert got.n_off_grid_ == 3 and got.n_on_zero_ > 0 and got.on_zero_detail_ == ref.on_zero_detail_
    np.testing.assert_allclose(got.theta_, ref.theta_, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(got.cov_, ref.cov_, rtol=1e-6, atol=1e-12)
    assert got.loglik_ == pytest.approx(ref.loglik_, rel=1e-12)
    for name, lik in ref.likelihoods_.items():
        for level, v in lik.items():
            assert got.likelihoods_[name][level] == pytest.approx(v, rel=1e-7, abs=1e-12), (name, level)
            assert got.stderr_[name][level] == pytest.approx(ref.stderr_[name][level], rel=1e-6, nan_ok=True), (name, level)
    emp_got, emp_ref = got.empirical(), ref.empirical()
    assert emp_got.keys() == emp_ref.keys()
    for name, table in emp_ref.items():
        for key, v in table.items():  # counts and areas exact; ratios NaN where a bin has no area
            np.testing.assert_array_equal(emp_got[name][key], v, err_msg=f"{name}.{key}")


def test_fit_stats_refuses_what_needs_the_grid(setup):
    _, config, stack, pts = setup
    est = PriorEstimator(template=config.model)
    terms, _ = make_terms(stack, config.model, None, None, None, 8)
    other, _ = make_terms(stack, config.model, ("water", "surface"), None, None, 8)
    cells = cell_stats(stack, tuple(terms))
    with pytest.raises(ValueError, match="same terms"):
        est.fit_stats(cells, point_stats(stack, tuple(other), pts[:10]))
    with pytest.raises(ValueError, match="spatial_bandwidth"):
        PriorEstimator(template=config.model, spatial_bandwidth=500.0).fit_stats(cells, point_stats(stack, tuple(terms), pts))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit_stats(cells, point_stats(stack, tuple(terms), pts))
    with pytest.raises(ValueError, match="fit_stats.*without the grid"):
        est.score(pts[:10])
    with pytest.raises(ValueError, match="template"):
        tiled_stats(config, PriorEstimator(), pts, shared_client(), TILE, progress=False)


def _numbers(model: LikelihoodModel) -> dict[str, float]:
    """Every number of the model's tables, keyed by feature and field."""
    out = {}
    for name, table in model.terms.items():
        for key, v in table.to_dict().items():
            if isinstance(v, dict):
                out |= {f"{name}.{key}.{k}": float(x) for k, x in v.items()}
            elif isinstance(v, int | float) and not isinstance(v, bool):
                out[f"{name}.{key}"] = float(v)
            elif isinstance(v, list):
                out |= {f"{name}.{key}.{i}": float(x) for i, x in enumerate(v)}
    return out


def test_cli_tiled_on_a_scheduler_writes_the_in_memory_model(setup, tmp_path, capsys):
    """Oracle: `learn --no-cv` on the whole grid; the tiled run goes to the shared cluster by address."""
    tmp, config, _, pts = setup
    doc = tomllib.loads(config.path.read_text())
    doc["learn"] = {"hybrid": False, "on_zero": "drop"}
    cfg = write_config(tmp_path / "region.toml", doc)
    csv = tmp_path / "targets.csv"
    np.savetxt(csv, pts[:600], delimiter=",", header="x,y", comments="")
    ref_out, got_out = tmp_path / "ref" / "model.toml", tmp_path / "tiled" / "model.toml"
    common = ["-q", "learn", str(cfg), "--targets", str(csv)]
    assert main([*common, "--out", str(ref_out), "--no-cv"]) == 0
    address = shared_client().scheduler.address
    assert main([*common, "--out", str(got_out), "--scheduler", address, "--tile", str(TILE)]) == 0
    assert "600 read, " in capsys.readouterr().out
    ref, got = LikelihoodModel.read_toml(ref_out), LikelihoodModel.read_toml(got_out)
    assert list(got.terms) == list(ref.terms)
    a, b = _numbers(got), _numbers(ref)
    assert a.keys() == b.keys() and len(a) > 10
    for k, v in b.items():
        assert a[k] == pytest.approx(v, rel=1e-7, abs=1e-12), k
    assert got.meta["learned"]["tiled"] == {"tile_cells": TILE, "scheduler": address}
    diag = json.loads(got_out.with_suffix(".diagnostics.json").read_text())
    assert "cv" not in diag and diag["ml"]["pass_seconds"] is None
    assert got_out.with_suffix(".fit.png").stat().st_size > 0


def test_cli_tiled_refuses_the_hybrid_prior(setup, tmp_path, capsys):
    tmp, config, _, pts = setup
    csv = tmp_path / "targets.csv"
    np.savetxt(csv, pts[:20], delimiter=",", header="x,y", comments="")
    code = main(["-q", "learn", str(config.path), "--targets", str(csv), "--out", str(tmp_path / "m.toml"),
                 "--hybrid-prior", str(tmp_path / "h.tif"), "--tiled"])
    assert code == 1
    assert re.search("error: .*hybrid-prior.*tiled", capsys.readouterr().err)
    assert not (tmp_path / "m.toml").exists()
