"""Learning from real targets: centroids of the Swellendam buildings with water, slope classes,
road distance and protected areas as features, scored on held-out spatial blocks."""

from __future__ import annotations

import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest

from pipeline.build.region import build_features
from pipeline.config.learn import load_learn_config
from pipeline.gis.targets import read_targets
from pipeline.learn.estimator import PriorEstimator
from pipeline.learn.evaluate import block_cv
from tests.pipeline.gis_helpers import REPO, write_config

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def swellendam_fit(swellendam: Path, tmp_path_factory):
    doc = tomllib.loads((REPO / "terrain_data" / "swellendam.toml").read_text())
    for layer in doc["layers"].values():
        layer["path"] = str(swellendam / Path(layer["path"]).name)
    cfg, _ = load_learn_config(write_config(tmp_path_factory.mktemp("sw") / "swellendam.toml", doc))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack = build_features(cfg, progress=False)
    pts = read_targets(swellendam / "training_data.gpkg", cfg.grid, layer="buildings")
    with pytest.warns(UserWarning, match="on structural zeros"):
        est = PriorEstimator(features=stack, template=cfg.model).fit(pts)
    return cfg, stack, pts, est


def test_building_centroids_fit_with_water_points_counted(swellendam_fit) -> None:
    cfg, stack, pts, est = swellendam_fit
    assert set(est.likelihoods_) == {"water", "road_distance", "slope_class", "protected"}
    assert len(pts) == 4708 and est.n_off_grid_ == 0
    # oracle for the count: buildings whose centroid cell is water, straight from the feature grid
    u, v = stack.grid.to_pixel(pts[:, 0], pts[:, 1])
    wet = int((stack["water"].values[v.astype(int), u.astype(int)] == 1).sum())
    assert wet > 0 and est.n_on_zero_ == wet and est.n_used_ == len(pts) - wet
    assert all(r.success for r in est.fit_results_)
    # buildings sit beside roads and avoid protected areas and steep ground
    assert est.likelihoods_["road_distance"]["rmd"] < 100.0
    assert est.likelihoods_["protected"]["protected"] < 0.5
    assert est.likelihoods_["slope_class"]["15-30"] < est.likelihoods_["slope_class"]["<5"]


def test_terrain_fit_beats_uniform_on_held_out_blocks(swellendam_fit) -> None:
    _, stack, pts, est = swellendam_fit
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = block_cv(pts, est, n_folds=3, block_size=2000.0, models=("uniform", "terrain"), progress=False)
    gains = res.gains()[:, 1]
    assert np.all(gains > 0.5), gains  # every held-out fold, not only on average


@pytest.mark.slow
def test_hybrid_beats_uniform_naive_terrain_and_kde(swellendam_fit) -> None:
    _, stack, pts, est = swellendam_fit
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = block_cv(pts, est, n_folds=5, block_size=2000.0, progress=False)
    s = res.summary()
    g = {m: v["pooled"] for m, v in s["gain_nats"].items()}
    assert g["hybrid"] > max(g["uniform"], g["naive"], g["terrain"], g["kde"]), g
    assert s["hybrid_fold_wins"]["uniform"] == 5


def test_learning_config_reads_the_farm_tracks_and_fits_every_listed_feature(swellendam: Path, tmp_path) -> None:
    """terrain_data/swellendam_learn.toml: its tracks layer is exactly the roads layer's tracks, paths and
    footways and its residential layer the residential streets (counted straight from the file), and every
feature of [learn] and of its mixture has a form."""
    import pyogrio

    from pipeline.gis.layers import read_vector

    doc = tomllib.loads((REPO / "terrain_data" / "swellendam_learn.toml").read_text())
    for layer in doc["layers"].values():
        layer["path"] = str(swellendam / Path(layer["path"]).name)
    cfg, learn = load_learn_config(write_config(tmp_path / "swellendam_learn.toml", doc))
    highway = pyogrio.read_dataframe(swellendam / "training_data.gpkg", layer="roads", read_geometry=False)["highway"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tracks = read_vector(cfg.layers["tracks"], cfg.grid)
        streets = read_vector(cfg.layers["residential"], cfg.grid)
    assert len(tracks.geometries) == int(highway.isin(["track", "path", "footway"]).sum()) > 100
    assert cfg.features["track_end_distance"].to == "ends"
    assert len(streets.geometries) == int((highway == "residential").sum()) > 100
    fitted = [*learn.features, *(f for features in learn.mixture.values() for f in features)]
    continuous = [f for f in fitted if cfg.features[f].type not in ("mask", "categories")]
    assert continuous and all(f in learn.forms for f in continuous) and len(learn.mixture) == 2
