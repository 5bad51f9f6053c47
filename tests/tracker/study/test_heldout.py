"""Learn here, track there: folds disjoint, the learned model fitted on the training blocks only, the same
data sets for every prior, r^α, Appendix B against a hand computation, CLI errors; Swellendam (slow)."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from sklearn.base import clone

from pipeline.gis.grid import Grid
from pipeline.learn.run import learning_inputs
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.gis_helpers import handset_targets, region_doc, write_config
from tracker.cli import main
from tracker.study.heldout import (
    HeldoutConfig,
    _blocks,
    _cut,
    _matrix,
    prepare,
    run_heldout,
    summarise_heldout,
)
from tracker.study.simulate import central_windows, file_targets, simulate_points


@pytest.fixture(scope="module")
def region_targets(tmp_path_factory):
    """A 6 km cut of the bundled region and 1200 targets (CSV) from its hand-set prior."""
    tmp = tmp_path_factory.mktemp("heldout")
    doc = region_doc(bounds=[302000, 6190000, 308000, 6196000])
    doc["learn"] = {"hybrid": False}
    region = write_config(tmp / "region.toml", doc)
    pts = handset_targets(region, 1200)
    csv = tmp / "targets.csv"
    np.savetxt(csv, pts, delimiter=",", header="x,y", comments="")
    return region, csv, tmp


@pytest.fixture(scope="module")
def setting(region_targets):
    """The learning pass and the runs: 3 folds of 2 km blocks, 3 data sets of 15 targets."""
    region, csv, tmp = region_targets
    cfg = HeldoutConfig(str(region), str(csv), block_m=2000.0, n_folds=3, n_datasets=3, n_targets=15,
                        n_reports=30, taus=(-1.0, 1.0), alphas=(0.0, 1.0, 2.0), hybrid=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prepared = prepare(cfg, tmp / "priors", progress=False)
        results = run_heldout(cfg, prepared, workers=1, progress=False)
    return cfg, prepared, results, tmp


def test_blocks_and_cuts_against_brute_force():
    """Each block holds exactly the points inside its window; a cut is the 2-block square centred on it, zero off the grid."""
    grid = Grid.from_bounds((0.0, 0.0, 3000.0, 2000.0), 100.0, "EPSG:32634")
    pts = np.random.default_rng(2).uniform([0, 0], [3000, 2000], size=(300, 2))
    folds = np.arange(300) % 3
    blocks = _blocks(pts, grid.bounds[:2], 1000.0, folds)
    assert sum(b.n_points for b in blocks) == 300 and len(blocks) == 6
    for b in blocks:
        x0, y0, x1, y1 = b.window
        inside = (pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)
        assert inside.sum() == b.n_points and b.fold == folds[np.flatnonzero(inside)[0]]
    r = np.arange(grid.height * grid.width, dtype=float).reshape(grid.shape) + 1
    corner = next(b for b in blocks if b.index == (0, 0))
    cut, g = _cut(r, grid, corner, 1000.0)
    assert g.bounds == pytest.approx((-500.0, -500.0, 1500.0, 1500.0)) and cut.shape == (20, 20)
    xs, ys = g.cell_centres()
    on = grid.contains(xs, ys)
    row, col, _ = grid.cell_index(xs[on], ys[on])
    np.testing.assert_array_equal(cut[on], r[row, col])
    assert (cut[~on] == 0).all()


@pytest.mark.slow
def test_data_sets_use_only_held_out_locations(setting):
    """Oracle: regenerate each data set; its targets are locations of its block's fold and of no training fold."""
    cfg, prepared, results, _ = setting
    pts, folds = prepared.points, prepared.fold_of_point
    for seed, row in results.groupby("seed").first().iterrows():
        block = next(b for b in prepared.blocks if b.name == row["block"])
        prior = TerrainPrior.read(prepared.priors[block.name]["learned"])
        assert central_windows(prior, None, 0.5)[1] == pytest.approx(block.window)  # the block is the keep window
        sc = simulate_points(prior, file_targets(cfg.targets_file, None, prior.grid), int(seed), cfg.n_targets,
                             cfg.n_reports, None, 0.5, cfg.sensor)
        d = np.hypot(*(sc.targets[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
        owner = d.argmin(axis=1)
        assert d.min(axis=1).max() < 1e-6
        assert (folds[owner] == block.fold).all()
        assert int(row["n_targets"]) == len(sc.targets) == cfg.n_targets


@pytest.mark.slow
def test_each_fold_is_learned_from_the_other_folds_only(setting):
    cfg, prepared, _, _ = setting
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, pts, est = learning_inputs(cfg.region, cfg.targets_file)
        for f, info in prepared.models.items():
            train = pts[prepared.fold_of_point != f]
            assert info["n_train"] == len(train) < len(pts)
            refit = clone(est).fit(train)
            assert json.dumps(refit.likelihoods_, sort_keys=True, default=float) == json.dumps(
                info["likelihoods"], sort_keys=True, default=float)


@pytest.mark.slow
def test_every_prior_sees_the_same_data_sets(setting):
    _, _, results, _ = setting
    labels = {"UU", "UT", "TT", "TT-alpha0", "TT-alpha2", "TT-handset", "TT-other"}
    assert set(results["label"]) == labels
    per_seed = results.groupby("seed").agg(nd=("nd", "nunique"), n=("n_targets", "nunique"), labels=("label", "nunique"))
    assert (per_seed["nd"] == 1).all() and (per_seed["n"] == 1).all() and (per_seed["labels"] == len(labels)).all()
    assert set(results["s_model"]) == {"exp", "poisson"}


def test_batch_tt_runs_on_the_learned_prior_and_never_lowers_the_posterior(setting):
    """batch TT (``batch=True``) starts from greedy TT's partition, so its ln p(Λ|Z) is never lower; it is
    compared with greedy TT in the summary."""
    cfg, prepared, results, _ = setting
    cfg = dataclasses.replace(cfg, batch=True, n_datasets=2)
    with_batch = run_heldout(cfg, prepared, workers=1, progress=False)
    assert set(with_batch["label"]) == set(results["label"]) | {"TT batch"}
    key = ["seed", "tau", "s_model"]
    tt = with_batch[with_batch["label"] == "TT"].set_index(key)["log_posterior"]
    batch = with_batch[with_batch["label"] == "TT batch"].set_index(key)["log_posterior"]
    assert len(batch) == len(tt) > 0
    assert (batch - tt.reindex(batch.index) >= -1e-9).all()
    summary = summarise_heldout(with_batch, cfg)
    assert "TT batch vs TT" in summary["table"]["gospa_m"] and "TT batch" in summary["labels"]
    assert "score" in summary["labels"]["TT batch"]


@pytest.mark.slow
def test_alpha_priors_are_powers_of_the_learned_density(setting):
    _, prepared, _, _ = setting
    paths = prepared.priors[prepared.blocks[0].name]
    learned = TerrainPrior.read(paths["learned"]).density
    squared = TerrainPrior.read(paths["alpha2"]).density
    flat = TerrainPrior.read(paths["alpha0"]).density
    on = learned > 0
    ratio = squared[on] / learned[on] ** 2
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-5)  # float32 GeoTIFF
    assert (squared[~on] == 0).all()
    np.testing.assert_allclose(flat, flat.flat[0], rtol=1e-12)


@pytest.mark.slow
def test_comparisons_match_appendix_b_by_hand(setting):
    """P(TT better than UU) on GOSPA, t form: Φ_t(−m̄/(s/√L)) of the paired differences at each one's best τ."""
    cfg, prepared, results, _ = setting
    summary = summarise_heldout(results, cfg, prepared)
    g_tt, g_uu = _matrix(results, "TT", "gospa_m"), _matrix(results, "UU", "gospa_m")
    b_tt, b_uu = g_tt.mean(axis=0).argmin(), g_uu.mean(axis=0).argmin()
    for metric, sign in (("gospa_m", 1.0), ("purity", -1.0)):
        # GOSPA at its own best τ; purity at the best-GOSPA τ (purity alone would pick all-singleton τ).
        tt, uu = _matrix(results, "TT", metric), _matrix(results, "UU", metric)
        m = tt[:, b_tt] - uu[:, b_uu]
        if m.std(ddof=1) == 0:
            expected = 1.0 if m.mean() < 0 else (0.0 if m.mean() > 0 else 0.5)
        else:
            expected = stats.t.cdf(-m.mean() / (m.std(ddof=1) / np.sqrt(len(m))), df=len(m) - 1)
        assert summary["table"][metric]["TT vs UU"]["t"] == pytest.approx(expected)
        assert summary["labels"]["TT"][metric]["mean_at_best_tau"] == pytest.approx(sign * tt[:, b_tt].mean())
    assert set(summary["alpha_sweep"]) == {"0", "1", "2"}
    for entry in summary["table"]["gospa_m"].values():
        assert 0.0 <= entry["t"] <= 1.0 and 0.0 <= entry["normal_exact_s"] <= 1.0


@pytest.mark.slow
def test_data_sets_run_alike_in_a_pool(setting):
    """The pool's records equal the inline run's (run_one is a pure function of the task)."""
    cfg, prepared, results, _ = setting
    pooled = run_heldout(dataclasses.replace(cfg, n_datasets=2), prepared, workers=2, progress=False)
    inline = results[results["seed"] < 2].reset_index(drop=True)
    pd.testing.assert_frame_equal(pooled, inline, check_like=True)


def test_heldout_cli_names_a_setting_without_enough_targets(region_targets, tmp_path, capsys):
    region, csv, _ = region_targets
    cfg = HeldoutConfig(str(region), str(csv))
    out = tmp_path / "out"
    assert main(["-q", "heldout", "--region", cfg.region, "--targets-file", cfg.targets_file, "--targets", "5000",
                 "--no-hybrid", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"terrain-track: error: {cfg.targets_file}: no 2000 m block holds 5000 targets (--targets)" in err
    assert "Traceback" not in err and not out.exists()
    assert main(["-q", "heldout", "--region", cfg.region, "--targets-file", cfg.targets_file, "--alphas", "1,x",
                 "--out", str(out)]) == 1
    assert "error: --alphas '1,x': expected a comma list" in capsys.readouterr().err


@pytest.mark.slow
def test_swellendam_buildings_learn_here_track_there(swellendam, tmp_path):
    """The real setting, small: held-out blocks hold >= 50 buildings, fits never see them, the table answers."""
    from pathlib import Path

    region = Path(__file__).resolve().parents[3] / "terrain_data" / "swellendam.toml"
    cfg = HeldoutConfig(str(region), str(swellendam / "training_data.gpkg"), "buildings", n_datasets=2,
                        taus=(-6.0, -3.0), alphas=(1.0,), hybrid=False, other_region=False, exact_s=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 4 buildings on water cells: dropped from the fits and counted
        prepared = prepare(cfg, tmp_path, progress=False)
        results = run_heldout(cfg, prepared, workers=1, progress=False)
    assert len(prepared.points) == 4708 and all(b.n_points >= 50 for b in prepared.blocks)
    for f, info in prepared.models.items():
        assert info["n_train"] == int((prepared.fold_of_point != f).sum()) < 4708
    summary = summarise_heldout(results, cfg, prepared)
    assert summary["n_datasets"] == 2 and set(summary["labels"]) == {"UU", "UT", "TT", "TT-handset"}
    assert 0.0 <= summary["table"]["gospa_m"]["TT vs UU"]["t"] <= 1.0
    assert results.loc[results["label"] == "TT", "gospa_m"].notna().all()
