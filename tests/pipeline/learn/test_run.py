"""`terrain-prior learn` with forms, weights and the defensive mixture; the honest CV table (folds,
ties, the KDE baseline normalised over the grid)."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest
from scipy import integrate
from sklearn.neighbors import KernelDensity

from pipeline.cli import main
from pipeline.config.learn import load_learn_config
from pipeline.config.region import ConfigError
from pipeline.learn.evaluate import CVResult, kde_log_mass
from pipeline.prior.likelihood import BinnedLikelihood, LikelihoodModel
from tests.pipeline.gis_helpers import handset_targets, write_config
from tests.pipeline.test_learn_cli import cut_config


@pytest.fixture(scope="module")
def weighted_targets(tmp_path_factory):
    """400 targets of the cut's hand-set prior in a CSV with a weight column ``w`` (1..3)."""
    tmp = tmp_path_factory.mktemp("learn_run")
    pts = handset_targets(cut_config(tmp, None), 400)
    w = np.random.default_rng(1).integers(1, 4, len(pts))
    csv = tmp / "targets.csv"
    np.savetxt(csv, np.column_stack([pts, w]), delimiter=",", header="x,y,w", comments="")
    return tmp, csv, pts, w


def test_learn_with_forms_weights_and_defensive_mixture(weighted_targets, tmp_path, capsys) -> None:
    _, csv, _, _ = weighted_targets
    doc = tomllib.loads(cut_config(tmp_path, {"folds": 2, "block_size_m": 1500.0, "hybrid": False, "defensive": 0.05,
                                              "bandwidths_m": [200.0, 600.0]}).read_text())
    doc["features"]["elevation"] = {"type": "elevation", "layer": "dem"}
    doc["learn"]["forms"] = {"road_distance": {"form": "decreasing", "scale": "log1p", "knots": 4},
                             "elevation": {"form": "spline", "knots": 4, "smoothing": 1.0}}
    cfg = write_config(tmp_path / "forms.toml", doc)
    out = tmp_path / "m.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--weights", "w", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "eps = 0.05 (fixed)" in printed and "fold 1" in printed and "fold 2" in printed and "worst" in printed
    assert "clamped to the training points' range: road_distance, elevation" in printed
    model = LikelihoodModel.read_toml(out)
    assert isinstance(model.terms["road_distance"], BinnedLikelihood) and "elevation" in model.terms
    diag = json.loads(out.with_suffix(".diagnostics.json").read_text())
    assert diag["ml"]["likelihoods"]["elevation"] and model.meta["learned"]["defensive_epsilon"] == 0.05
    assert model.meta["learned"]["weighted"] is True
    assert len(diag["cv"]["gain_nats"]["terrain"]["per_fold"]) == 2
    lo, hi = diag["ml"]["clamped_range"]["road_distance"]
    assert 0 <= lo < hi and set(diag["ml"]["clamped_range"]) == {"road_distance", "elevation"}


def test_bad_weights_are_named_errors(weighted_targets, tmp_path, capsys) -> None:
    _, csv, pts, w = weighted_targets
    cfg = cut_config(tmp_path, {"hybrid": False})
    for value, name in [(0, "zero"), (-2, "negative"), ("nan", "NaN")]:
        bad = tmp_path / f"bad_{name}.csv"
        rows = [f"{x},{y},{v}" for (x, y), v in zip(pts, w, strict=True)]
        rows[5] = f"{pts[5, 0]},{pts[5, 1]},{value}"
        bad.write_text("x,y,w\n" + "\n".join(rows) + "\n")
        out = tmp_path / "m.toml"
        assert main(["-q", "learn", str(cfg), "--targets", str(bad), "--weights", "w", "--out", str(out), "--no-cv"]) == 1
        err = capsys.readouterr().err
        assert f"error: {bad}: column 'w' (--weights): 1 {name} weights (rows [5])" in err and "Traceback" not in err
        assert not out.exists()
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--weights", "mass", "--out", str(tmp_path / "m.toml"), "--no-cv"]) == 1
    assert "no column 'mass' (--weights)" in capsys.readouterr().err


def test_a_continuous_feature_without_a_form_is_an_error_naming_it(weighted_targets, tmp_path, capsys) -> None:
    _, csv, _, _ = weighted_targets
    doc = tomllib.loads(cut_config(tmp_path, {"hybrid": False}).read_text())
    doc["features"]["elevation"] = {"type": "elevation", "layer": "dem"}
    cfg = write_config(tmp_path / "elev.toml", doc)
    out = tmp_path / "m.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 1
    assert "[features.elevation] has no [likelihood.elevation] table nor [learn.forms.elevation]" in capsys.readouterr().err
    doc["learn"]["features"] = ["water", "elevation"]
    cfg = write_config(tmp_path / "listed.toml", doc)
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 1
    assert "feature 'elevation' is continuous and has no form" in capsys.readouterr().err
    doc["learn"]["forms"] = {"elevation": {"form": "linear"}}
    cfg = write_config(tmp_path / "formed.toml", doc)
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 0
    assert set(LikelihoodModel.read_toml(out).terms) == {"water", "elevation"}


def test_form_config_errors_name_file_and_key(tmp_path) -> None:
    for forms, key in [({"road_distance": {"form": "wavy"}}, "learn.forms.road_distance.form"),
                       ({"road_distance": {"form": "spline", "colour": 1}}, "learn.forms.road_distance: unknown keys"),
                       ({"road_distance": {"scale": "log1p"}}, "no form"),
                       ({"nope": {"form": "linear"}}, "learn.forms: no feature 'nope'")]:
        cfg = cut_config(tmp_path, {"forms": forms})
        with pytest.raises(ConfigError, match=key) as info:
            load_learn_config(cfg)
        assert str(cfg) in str(info.value)
    for bad in ("maybe", 1.5, True):
        with pytest.raises(ConfigError, match="learn.defensive"):
            load_learn_config(cut_config(tmp_path, {"defensive": bad}))
    for bad in ("yes", 1):
        with pytest.raises(ConfigError, match="learn.clamp: must be true or false") as info:
            load_learn_config(cut_config(tmp_path, {"clamp": bad}))
        assert str(tmp_path) in str(info.value)
    assert load_learn_config(cut_config(tmp_path, {"clamp": False}))[1].clamp is False
    assert load_learn_config(cut_config(tmp_path, {}))[1].clamp is True


def test_ties_are_counted_as_ties() -> None:
    scores = np.array([[-10.0, -7.0, -8.0, -7.0], [-10.0, -6.0, -6.5, -6.0], [-10.0, -7.5, -7.3, -7.2]])
    cv = CVResult(("uniform", "terrain", "kde", "hybrid"), scores, np.array([10, 20, 30]), np.ones(3), 1000.0, 60, 0)
    s = cv.summary()
    assert s["hybrid_fold_wins"]["terrain"] == 1 and s["hybrid_fold_ties"]["terrain"] == 2
    assert s["hybrid_fold_wins"]["kde"] == 3 and s["hybrid_fold_ties"]["kde"] == 0
    assert s["worst_fold"] == 2  # the fold whose best model gains least


def test_kde_mass_on_the_grid_matches_dense_integration() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0], [1000, 600], (40, 2))
    pts[:5] = [[10, 10], [990, 5], [500, 595], [3, 300], [700, 1]]  # near the edges: mass leaks out
    h = 120.0
    kde = KernelDensity(bandwidth=h).fit(pts)
    dense, _ = integrate.nquad(lambda x, y: float(np.exp(kde.score_samples([[x, y]]))[0]), [[0, 1000], [0, 600]],
                               opts={"epsabs": 1e-6, "limit": 100})
    assert np.isclose(np.exp(kde_log_mass(pts, h, (0.0, 0.0, 1000.0, 600.0))), dense, rtol=1e-4)
    assert dense < 0.95  # the plane-normalised KDE would have been scored as if it were 1


def test_build_model_applies_tempering_and_defensive_mixture_as_scored(weighted_targets, tmp_path) -> None:
    """`build --model` (in memory and tiled) gives the estimator's own density: τ and ε from [meta.learned]."""
    import warnings

    from pipeline.build.region import build_features, build_region_prior
    from pipeline.learn.estimator import PriorEstimator
    from pipeline.prior.terrain import PriorError, TerrainPrior
    from pipeline.tiled.build import build_prior_tiled
    from tests.dask_helpers import shared_client

    _, _, pts, _ = weighted_targets
    region, _ = load_learn_config(cut_config(tmp_path, None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack = build_features(region, progress=False)
        est = PriorEstimator(features=stack, template=region.model, defensive=0.2, temper=0.6,
                             forms={"road_distance": {"form": "decreasing", "scale": "log1p", "knots": 4}}).fit(pts)
    est.model_.write_toml(tmp_path / "m.toml")
    model = LikelihoodModel.read_toml(tmp_path / "m.toml")
    assert model.meta["learned"]["temper_exponent"] == 0.6 and model.meta["learned"]["defensive_epsilon"] == 0.2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        built = build_region_prior(region, model, progress=False)
        plain = build_region_prior(region, LikelihoodModel(model.terms), progress=False)
    scored = est.prior_.density
    assert np.allclose(built.density, scored, rtol=1e-9, atol=0)
    support = scored > 0
    floor = 0.2 / (support.sum() * region.grid.cell_area)  # ε·u: every supported cell keeps at least this
    assert scored[support].min() >= floor * (1 - 1e-12) and plain.density[support].min() < floor
    assert not np.allclose(plain.density, scored, rtol=1e-3)
    out = build_prior_tiled(region, tmp_path / "tiled.tif", model, client=shared_client(), tile=96, progress=False)
    assert np.allclose(TerrainPrior.read(out["path"]).density, scored, rtol=2e-7, atol=0)  # float32 on disk
    bad = LikelihoodModel(model.terms, {"learned": {"defensive_epsilon": 1.5}})
    with pytest.raises(PriorError, match="defensive_epsilon"):
        build_region_prior(region, bad, progress=False)


def test_learn_fits_a_mixture_whose_prior_is_the_weighted_sum_of_its_components_built_from_their_tables(
        weighted_targets, tmp_path, capsys) -> None:
    from pipeline.prior import TerrainPrior

    _, csv, _, _ = weighted_targets
    doc = tomllib.loads(cut_config(tmp_path, {"folds": 2, "block_size_m": 1500.0, "hybrid": False}).read_text())
    doc["features"]["elevation"] = {"type": "elevation", "layer": "dem"}
    doc["learn"]["features"] = ["water", "road_distance"]
    doc["learn"]["forms"] = {"elevation": {"form": "linear"}}
    doc["learn"]["mixture"] = {"roads": {"features": ["water", "road_distance"]}, "relief": {"features": ["water", "elevation"]}}
    cfg = write_config(tmp_path / "mix.toml", doc)
    out, mix_tif = tmp_path / "m.toml", tmp_path / "mix.tif"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--mixture-prior", str(mix_tif)]) == 0
    printed = capsys.readouterr().out
    assert "mixture: p = sum of w_k p_k, w = roads " in printed and "relief" in printed
    assert any(line.split()[:1] == ["mixture"] and len(line.split()) == 5 for line in printed.splitlines())  # its CV row
    diag = json.loads(out.with_suffix(".diagnostics.json").read_text())
    assert len(diag["cv"]["gain_nats"]["mixture"]["per_fold"]) == 2
    weights = diag["mixture"]["weights"]
    assert set(weights) == {"roads", "relief"} and sum(weights.values()) == pytest.approx(1.0)
    assert diag["mixture"]["components"]["relief"]["features"] == ["water", "elevation"]
    mixed = TerrainPrior.read(mix_tif).density
    built = 0.0
    for name, w in weights.items():
        tables = out.with_suffix(f".mixture.{name}.toml")
        assert set(LikelihoodModel.read_toml(tables).terms) == set(diag["mixture"]["components"][name]["features"])
        tif = tmp_path / f"{name}.tif"
        assert main(["-q", "build", str(cfg), "--model", str(tables), "--out", str(tif)]) == 0
        built = built + w * np.asarray(TerrainPrior.read(tif).density, dtype=np.float64)
    np.testing.assert_allclose(np.asarray(mixed, dtype=np.float64), built, rtol=1e-4, atol=1e-6 * built.max())


def test_mixture_config_and_option_errors_are_named(weighted_targets, tmp_path, capsys) -> None:
    _, csv, _, _ = weighted_targets
    for mixture, key in [({"a": {"features": ["water"]}}, "learn.mixture: expected at least 2"),
                         ({"a": {"features": ["water"]}, "b": {"feats": ["water"]}}, "learn.mixture.b: expected a table"),
                         ({"a": {"features": ["water"]}, "b": {"features": []}}, "learn.mixture.b.features"),
                         ({"a": {"features": ["water"]}, "b": {"features": ["nope"]}}, "learn.mixture.b.features: no feature 'nope'")]:
        cfg = cut_config(tmp_path, {"mixture": mixture})
        with pytest.raises(ConfigError, match=key) as info:
            load_learn_config(cfg)
        assert str(cfg) in str(info.value)
    doc = tomllib.loads(cut_config(tmp_path, {"hybrid": False}).read_text())
    doc["features"]["elevation"] = {"type": "elevation", "layer": "dem"}
    doc["learn"]["features"] = ["water", "road_distance"]
    doc["learn"]["mixture"] = {"a": {"features": ["water"]}, "b": {"features": ["water", "elevation"]}}
    cfg = write_config(tmp_path / "noform.toml", doc)
    out = tmp_path / "m.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 1
    assert "[learn.mixture] feature 'elevation' is continuous and has no form" in capsys.readouterr().err
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--tiled"]) == 1
    assert "[learn.mixture] needs the whole grid" in capsys.readouterr().err
    plain = cut_config(tmp_path, {"hybrid": False})
    assert main(["-q", "learn", str(plain), "--targets", str(csv), "--out", str(out), "--no-cv", "--mixture-prior",
                 str(tmp_path / "x.tif")]) == 1
    err = capsys.readouterr().err
    assert "--mixture-prior: the config has no [learn.mixture] tables" in err and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "x.tif").exists()
