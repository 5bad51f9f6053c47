"""terrain-prior learn end to end on a cut of the bundled region: outputs, config errors, build --model."""

from __future__ import annotations

import json
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest
import shapely

from pipeline.build.region import build_features, build_prior
from pipeline.cli import main
from pipeline.config.learn import load_learn_config
from pipeline.config.region import ConfigError
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.gis_helpers import REGION_TOML, handset_targets, write_config, write_vector

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def cut_config(tmp: Path, learn: dict | None) -> Path:
    """The bundled region on a 6 km x 6 km cut (absolute layer paths), with a [learn] table."""
    doc = tomllib.loads(REGION_TOML.read_text())
    doc["region"]["bounds"] = [302000, 6190000, 308000, 6196000]
    for layer in doc["layers"].values():
        layer["path"] = str((REGION_TOML.parent / layer["path"]).resolve())
    if learn is not None:
        doc["learn"] = learn
    return write_config(tmp / "region.toml", doc)


@pytest.fixture(scope="module")
def targets(tmp_path_factory):
    """Targets drawn from the hand-set prior of the cut, as CSV and as GeoJSON polygons (centroids)."""
    tmp = tmp_path_factory.mktemp("learn_cli")
    pts = handset_targets(cut_config(tmp, None), 1200)
    csv = tmp / "targets.csv"
    np.savetxt(csv, pts, delimiter=",", header="x,y", comments="")
    squares = [shapely.box(x - 2, y - 2, x + 2, y + 2) for x, y in pts[:300]]
    gj = write_vector(tmp / "targets.geojson", squares, driver="GeoJSON")
    return tmp, csv, gj, pts


def test_learn_writes_model_diagnostics_and_plot_and_build_reads_it(targets, tmp_path, capsys) -> None:
    tmp, csv, _, pts = targets
    cfg = cut_config(tmp_path, {"hybrid": False, "on_zero": "drop", "penalty_sd": 2.5})
    out = tmp_path / "out" / "model.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 0
    printed = capsys.readouterr().out
    assert "road_distance" in printed and "95% CI" in printed and "1200 read, 1200 used" in printed
    model = LikelihoodModel.read_toml(out)
    assert set(model.terms) == {"water", "obstacles", "slope_class", "road_distance", "surface", "vegetation"}
    assert model.terms["water"].values["water"] == 0.0 and model.meta["learned"]["penalty_sd"] == 2.5
    diag = json.loads((out.parent / "model.diagnostics.json").read_text())  # strict JSON: no NaN
    assert diag["points"]["used"] == 1200 and diag["ml"]["converged"] == [True]
    assert set(diag["naive"]["likelihoods"]) == set(model.terms)
    assert (out.parent / "model.fit.png").read_bytes()[:8] == PNG_MAGIC
    # the learned table is what build --model reads
    prior_path = tmp_path / "prior.tif"
    assert main(["-q", "build", str(cfg), "--model", str(out), "--out", str(prior_path)]) == 0
    prior = TerrainPrior.read(prior_path)
    # oracle: rebuild the prior straight from the TOML and the features
    region, _ = load_learn_config(cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        direct = build_prior(build_features(region, progress=False), model)
    np.testing.assert_allclose(prior.density, direct.density.astype(np.float32), rtol=1e-6)
    assert np.isfinite(np.log(prior.density_at(pts[:, 0], pts[:, 1]))).all()


def test_learn_reads_polygon_centroids_from_a_vector_file(targets, tmp_path, capsys) -> None:
    tmp, _, gj, pts = targets
    cfg = cut_config(tmp_path, {"hybrid": False})
    out = tmp_path / "m.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(gj), "--out", str(out), "--no-cv"]) == 0
    diag = json.loads(out.with_suffix(".diagnostics.json").read_text())
    assert diag["points"]["read"] == 300 and diag["points"]["used"] == 300


@pytest.mark.slow
def test_learn_cross_validates_against_baselines(targets, tmp_path, capsys) -> None:
    tmp, csv, _, _ = targets
    cfg = cut_config(tmp_path, {"folds": 3, "block_size_m": 1500.0, "bandwidths_m": [150.0, 400.0, 1000.0]})
    out = tmp_path / "m.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out),
                 "--hybrid-prior", str(tmp_path / "hybrid.tif")]) == 0
    printed = capsys.readouterr().out
    assert "spatial block CV: 3 folds" in printed and "hybrid beats per fold" in printed
    assert "(each fold fitted with its held-out blocks unobserved)" in printed
    cv = json.loads(out.with_suffix(".diagnostics.json").read_text())["cv"]
    blocks = next(line for line in printed.splitlines() if line.strip().startswith("blocks")).split()[1:]
    assert [int(b) for b in blocks] == cv["n_blocks_per_fold"] and len(blocks) == 3
    assert cv["gain_nats"]["terrain"]["pooled"] > 0.2
    assert TerrainPrior.read(tmp_path / "hybrid.tif").grid.shape == (300, 300)


def test_learn_config_errors_name_file_and_key(tmp_path) -> None:
    for learn, key in [({"on_zero": "ignore"}, "learn.on_zero"), ({"folds": 1}, "learn.folds"),
                       ({"features": ["nope"]}, "learn.features"), ({"colour": 1}, "unknown keys"),
                       ({"flexible": {"road_distance": [0, 10, 5]}}, "learn.flexible.road_distance")]:
        cfg = cut_config(tmp_path, learn)
        with pytest.raises(ConfigError, match=key) as info:
            load_learn_config(cfg)
        assert str(cfg) in str(info.value)


def test_learn_reports_bad_targets(targets, tmp_path, capsys) -> None:
    cfg = cut_config(tmp_path, {"hybrid": False})
    bad = tmp_path / "bad.csv"
    bad.write_text("east,north\n1,2\n")
    assert main(["-q", "learn", str(cfg), "--targets", str(bad), "--out", str(tmp_path / "m.toml"), "--no-cv"]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "no column 'x'" in err
    assert not (tmp_path / "m.toml").exists()


def test_learn_refuses_a_feature_it_would_silently_leave_out(targets, tmp_path, capsys) -> None:
    """A feature with no [likelihood.*] table (and no [learn] features list) would be dropped from the fit
    without a word: an error naming it and the two ways out; nothing written."""
    _, csv, _, _ = targets
    doc = tomllib.loads(cut_config(tmp_path, {"hybrid": False}).read_text())
    dropped = next(name for name in doc["likelihood"] if name != "road_distance")
    del doc["likelihood"][dropped]
    cfg = write_config(tmp_path / "dropped.toml", doc)
    out = tmp_path / "model.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 1
    err = capsys.readouterr().err
    assert f"[features.{dropped}] has no [likelihood.{dropped}] table" in err and "[learn] features" in err
    assert not out.exists()
    # Listing the features to fit is the explicit way to leave one out: then it learns.
    doc["learn"]["features"] = [n for n in doc["likelihood"]]
    cfg = write_config(tmp_path / "listed.toml", doc)
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 0
    assert set(LikelihoodModel.read_toml(out).terms) == set(doc["likelihood"])


def test_learn_refuses_a_flexible_entry_it_would_ignore(targets, tmp_path, capsys) -> None:
    _, csv, _, _ = targets
    doc = tomllib.loads(cut_config(tmp_path, {"hybrid": False}).read_text())
    doc["learn"]["features"] = ["water"]
    doc["learn"]["flexible"] = {"road_distance": [0, 50, 100, 200]}
    cfg = write_config(tmp_path / "flex.toml", doc)
    out = tmp_path / "model.toml"
    assert main(["-q", "learn", str(cfg), "--targets", str(csv), "--out", str(out), "--no-cv"]) == 1
    assert "[learn] flexible names ['road_distance'], which this fit does not include" in capsys.readouterr().err
    assert not out.exists()
