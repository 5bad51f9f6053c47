"""Backward feature selection by spatial block CV: its scores against a by-hand cross-fit, what it
drops on synthetic ground truth, its nesting in the outer CV, and the `learn` command's use of it."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest
from scipy import ndimage
from sklearn.model_selection import GroupKFold

from pipeline.cli import main
from pipeline.config.learn import load_learn_config
from pipeline.config.region import ConfigError
from pipeline.features.stack import Feature
from pipeline.learn import (
    BackwardSelection,
    BlockWindow,
    PriorEstimator,
    block_cv,
    block_ids,
    with_selection,
)
from pipeline.prior.likelihood import CategoricalLikelihood, LikelihoodModel
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.gis_helpers import write_config
from tests.pipeline.learn.test_run import weighted_targets  # noqa: F401  (the module fixture)
from tests.pipeline.learn_synth import small_stack
from tests.pipeline.test_learn_cli import cut_config

BLOCK_M = 600.0
FORMS = {"road_distance": {"form": "linear", "scale": "log1p"}, "noise": {"form": "linear"}}
LAKE = LikelihoodModel({"water": CategoricalLikelihood({"dry": 1.0, "water": 0.0})})
"""The template: the lake is a structural zero."""


@pytest.fixture(scope="module")
def world():
    """A 120 x 160 stack (20 m cells) with a smooth random ``noise`` raster; the truth depends on the
    road distance (and the lake's structural zero) only. 3,000 points drawn from it."""
    stack = small_stack(120, 160, seed=4)
    stack.add(Feature("noise", ndimage.gaussian_filter(np.random.default_rng(9).normal(size=(120, 160)), 6) * 50.0,
                      "continuous", "1"))
    dry = stack["water"].values == 0
    truth = np.exp(-1.2 * np.log1p(stack["road_distance"].values)) * dry
    pts = TerrainPrior.from_array(truth / (truth.sum() * stack.grid.cell_area), stack.grid).sample(3000, np.random.default_rng(2))
    return stack, pts


def estimator(stack, names=("water", "road_distance", "noise")) -> PriorEstimator:
    return PriorEstimator(features=stack, template=LAKE, feature_names=names, forms={k: v for k, v in FORMS.items() if k in names})


def by_hand(stack, pts, names) -> float:
    """Pooled held-out mean log density over GroupKFold folds of the blocks, fitted fold by fold with
    the held-out blocks outside the observation window."""
    groups = block_ids(pts, stack.grid.bounds[:2], BLOCK_M)
    ld = np.empty(len(pts))
    for train, test in GroupKFold(n_splits=3).split(pts, groups=groups):
        window = BlockWindow(BLOCK_M, set(groups[test].tolist()))
        fitted = estimator(stack, names).set_params(window=window).fit(pts[train])
        ld[test] = np.log(fitted.prior_.density_at(pts[test, 0], pts[test, 1]))
    ok = np.isfinite(ld)
    return float(ld[ok].mean())


def test_the_noise_feature_is_dropped_and_the_scores_are_the_hand_computed_cross_fit(world) -> None:
    stack, pts = world
    sel = BackwardSelection(estimator(stack), spatial_block=BLOCK_M, n_folds=3).fit(pts)
    assert sel.features_ == ("water", "road_distance") and sel.fixed_ == ("water",)
    first = sel.path_[0]
    assert first["features"] == ["water", "road_distance", "noise"] and set(first["candidates"]) == {"road_distance", "noise"}
    assert first["score"] == pytest.approx(by_hand(stack, pts, ("water", "road_distance", "noise")), abs=1e-9)
    assert first["candidates"]["noise"] == pytest.approx(by_hand(stack, pts, ("water", "road_distance")), abs=1e-9)
    assert first["candidates"]["road_distance"] == pytest.approx(by_hand(stack, pts, ("water", "noise")), abs=1e-9)
    # the road distance carries the truth: dropping it costs far more than the noise's estimation error gains
    assert first["candidates"]["road_distance"] < first["score"] - 0.1 < first["candidates"]["noise"] - 0.1
    assert sel.score_ == first["candidates"]["noise"] and sel.path_[-1]["candidates"] == {}  # one covariate left: stop
    assert sel.estimator_.feature_names == ("water", "road_distance")
    np.testing.assert_array_equal(sel.score_samples(pts[:50]), sel.estimator_.score_samples(pts[:50]))


def test_it_stops_when_every_removal_scores_lower(world) -> None:
    stack, pts = world
    sel = BackwardSelection(estimator(stack, ("water", "road_distance", "land")), spatial_block=BLOCK_M, n_folds=3).fit(pts)
    last = sel.path_[-1]
    assert last["score"] == sel.score_ and all(v <= sel.score_ for v in last["candidates"].values())
    assert "road_distance" in sel.features_


def test_nested_in_the_outer_cv_each_fold_selects_on_its_own_training_points(world) -> None:
    stack, pts = world
    est = estimator(stack)
    cv = block_cv(pts, est, n_folds=2, block_size=BLOCK_M, models=("uniform", "terrain"), progress=False)
    sel = BackwardSelection(est, spatial_block=BLOCK_M, n_folds=3)
    nested = with_selection(cv, sel, pts)
    assert nested.models == ("uniform", "terrain", "selected") and len(nested.extra["selected_features"]) == 2
    for j, test in enumerate(cv.extra["test_index"]):
        train = np.concatenate([i for k, i in enumerate(cv.extra["test_index"]) if k != j])
        window = cv.extra["windows"][j]
        assert window == BlockWindow(BLOCK_M, set(block_ids(pts[test], stack.grid.bounds[:2], BLOCK_M).tolist()))
        alone = BackwardSelection(est, spatial_block=BLOCK_M, n_folds=3, window=window).fit(pts[train])
        assert nested.extra["selected_features"][j] == list(alone.features_)
        assert nested.scores[j, 2] == pytest.approx(alone.score_samples(pts[test]).mean(), abs=1e-12)


def test_bad_settings_are_errors() -> None:
    with pytest.raises(ValueError, match="needs a PriorEstimator"):
        BackwardSelection().fit(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="n_folds"):
        BackwardSelection(PriorEstimator(), n_folds=1).fit(np.zeros((3, 2)))


def test_learn_with_select_writes_the_kept_features_and_nests_the_selection_in_its_cv(weighted_targets, tmp_path, capsys) -> None:  # noqa: F811
    _, csv, _, _ = weighted_targets
    learn = {"folds": 2, "block_size_m": 1500.0, "hybrid": False, "defensive": "none", "select": "backward",
             "features": ["water", "road_distance", "slope_class", "surface"]}
    cfg = cut_config(tmp_path, learn)
    out = tmp_path / "m.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "backward selection on 2 folds of 1500 m blocks" in printed and "never dropped (structural zeros): water" in printed
    assert any(line.split()[:1] == ["selected"] and len(line.split()) == 5 for line in printed.splitlines())  # its CV row
    diag = json.loads(out.with_suffix(".diagnostics.json").read_text())
    kept = diag["selection"]["features"]
    assert set(LikelihoodModel.read_toml(out).terms) == set(kept) and "water" in kept
    assert diag["selection"]["path"][0]["features"] == learn["features"]
    assert len(diag["cv"]["selected_features_per_fold"]) == 2 and len(diag["cv"]["gain_nats"]["selected"]["per_fold"]) == 2
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(tmp_path / "t.toml"), "--tiled"]) == 1
    err = capsys.readouterr().err
    assert "learn.select needs the whole grid" in err and "Traceback" not in err and not (tmp_path / "t.toml").exists()


def test_a_bad_select_value_names_the_file_and_key(tmp_path) -> None:
    cfg = cut_config(tmp_path, {"select": "forward"})
    with pytest.raises(ConfigError, match="learn.select: must be \"backward\" or \"none\"") as info:
        load_learn_config(cfg)
    assert str(cfg) in str(info.value)
    doc = tomllib.loads(cut_config(tmp_path, {"select": "none"}).read_text())
    assert load_learn_config(write_config(tmp_path / "n.toml", doc))[1].select is None
