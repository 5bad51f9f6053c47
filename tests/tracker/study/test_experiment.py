"""The experiment harness: τ parsing, the integral cache, per-data-set records cross-checked against
direct scoring of fresh (uncached) tracker runs, determinism across workers, summary and outputs."""

from __future__ import annotations

import json
from functools import partial

import numpy as np
import pandas as pd
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import associate, perfect_estimate
from tracker.integrate import integrate
from tracker.models.sfunc import ExpS, PoissonS
from tracker.study.experiment import (
    CachedIntegrator,
    ExperimentConfig,
    expected_in_window,
    fuse_sets,
    parse_taus,
    posterior_median,
    posterior_mixture,
    run_dataset,
    run_experiment,
    summarise,
    window_mask,
    window_prior,
    write_outputs,
)
from tracker.study.metrics import gospa, posterior_means, score
from tracker.study.simulate import AirborneSensor, central_windows, simulate

TAUS = (-4.0, -1.0, 2.0)


@pytest.fixture(scope="module")
def prior_path(tmp_path_factory) -> str:
    """A 6 km square prior with road-like ridges and a lake, written like `terrain-prior build` does."""
    n = 300
    yy, xx = np.mgrid[0:n, 0:n]
    r = 0.15 + np.exp(-0.5 * ((xx - 0.6 * yy - 80) / 5.0) ** 2) + np.exp(-0.5 * ((yy - 170) / 5.0) ** 2)
    r[(xx - 200) ** 2 + (yy - 90) ** 2 < 25**2] = 0.0
    grid = Grid("EPSG:32734", Affine(20.0, 0.0, 300000.0, 0.0, -20.0, 6200000.0), n, n)
    path = tmp_path_factory.mktemp("prior") / "prior.tif"
    TerrainPrior.from_array(r, grid).write(path)
    return str(path)


def _config(**kw) -> ExperimentConfig:
    base = dict(n_datasets=3, n_reports=40, taus=TAUS, n_targets=80, region_m=None,
                sensor=AirborneSensor(standoff_m=15000.0))
    base.update(kw)
    return ExperimentConfig(**base)


def test_parse_taus() -> None:
    taus = parse_taus("-3:3:0.25")
    assert len(taus) == 25 and taus[0] == -3.0 and taus[-1] == 3.0 and -1.75 in taus
    assert parse_taus("-1,0.5") == (-1.0, 0.5)
    for bad in ("3:-3:0.25", "-3:3:0", "a:b:c", "1:2"):
        with pytest.raises(ValueError, match="--tau"):
            parse_taus(bad)


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="variants"):
        ExperimentConfig(variants=("XX",))
    with pytest.raises(ValueError, match="n_datasets"):
        ExperimentConfig(n_datasets=1)
    with pytest.raises(ValueError, match="integrator 'strips' unknown"):
        ExperimentConfig(integrator="strips")


def test_run_dataset_with_the_terraces_uses_them(prior_path: str) -> None:
    """``integrator="terraces"``: the records equal a direct run with the terraces throughout."""
    config = _config(taus=(-2.0,), variants=("TT",), integrator="terraces")
    rec = pd.DataFrame(run_dataset(prior_path, 5, config)).iloc[0]
    prior = TerrainPrior.read(prior_path)
    terraces = partial(integrate, method="terraces")
    sc = simulate(prior, 5, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    ref = perfect_estimate(prior, sc.reports, integrator=terraces)
    res = associate(prior, sc.reports, "TT", s_model=ExpS(-2.0), integrator=terraces)
    est = res.estimate
    expected = score(prior, est.means, est.covs, True, ref.means, ref.covs, True, integrator=terraces)
    assert rec.nd_hat == res.n_detected
    assert rec.score == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_cached_integrator_matches_terrace(prior_path: str) -> None:
    prior = TerrainPrior.read(prior_path)
    rng = np.random.default_rng(0)
    means = 300000.0 + rng.uniform(1000, 5000, size=(6, 2)) + np.array([0.0, 6194000.0 - 300000.0])
    covs = np.tile(np.diag([80.0**2, 30.0**2]), (6, 1, 1))
    cache = CachedIntegrator(prior)
    first = cache(prior, means[:4], covs[:4])
    mixed = cache(prior, means[2:], covs[2:], squared=False)
    sq = cache(prior, means, covs, squared=True)
    np.testing.assert_array_equal(first, integrate(prior, means[:4], covs[:4]))
    np.testing.assert_array_equal(mixed, integrate(prior, means[2:], covs[2:]))
    np.testing.assert_array_equal(sq, integrate(prior, means, covs, squared=True))
    assert cache.hits == 2 and cache.misses == 4 + 2 + 6
    with pytest.raises(ValueError, match="different prior"):
        cache(TerrainPrior.read(prior_path), means, covs)


def test_run_dataset_matches_direct_scoring(prior_path: str) -> None:
    config = _config(poisson_mu=150.0)
    records = pd.DataFrame(run_dataset(prior_path, 5, config))
    assert len(records) == 3 * (len(TAUS) + 1)
    exact = records[records.s_model == "poisson"]
    assert len(exact) == 3 and exact.tau.isna().all()
    prior = TerrainPrior.read(prior_path)
    sc = simulate(prior, 5, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    ref = perfect_estimate(prior, sc.reports)
    nd = np.unique(sc.reports.truth).size
    for _, rec in records.iterrows():
        assoc = "UU" if rec.variant == "UT" else rec.variant
        s_model = PoissonS(150.0) if rec.s_model == "poisson" else ExpS(rec.tau)
        res = associate(prior, sc.reports, assoc, s_model=s_model)  # fresh: no shared cache
        est = res.estimate
        expected = score(prior, est.means, est.covs, rec.variant != "UU", ref.means, ref.covs, True)
        assert rec.score == pytest.approx(expected, rel=1e-9, abs=1e-12)
        assert rec.nd == nd and rec.nd_hat == res.n_detected
        assert rec.nd_abs_error == abs(res.n_detected - nd)
        pts = est.means if rec.variant == "UU" else posterior_means(prior, est.means, est.covs)
        detected = sc.targets[np.unique(sc.reports.truth)]
        assert rec.gospa_m == pytest.approx(gospa(pts, detected, config.gospa_c_m)["gospa"], rel=1e-9)
    # UT associates exactly as UU: only the score may differ.
    uu = records[records.variant == "UU"].set_index(["s_model", "tau"])
    ut = records[records.variant == "UT"].set_index(["s_model", "tau"])
    for col in ("nd_hat", "purity"):
        pd.testing.assert_series_equal(uu[col], ut[col])


@pytest.fixture(scope="module")
def serial_results(prior_path: str) -> pd.DataFrame:
    return run_experiment(prior_path, _config(), workers=1, progress=False)


@pytest.mark.slow
def test_experiment_deterministic_across_workers(prior_path: str, serial_results: pd.DataFrame) -> None:
    parallel = run_experiment(prior_path, _config(), workers=2, progress=False)
    pd.testing.assert_frame_equal(serial_results, parallel)


def test_summary_and_outputs(serial_results: pd.DataFrame, tmp_path) -> None:
    summary = summarise(serial_results, _config())
    for v in ("UU", "UT", "TT"):
        means = serial_results[serial_results.variant == v].groupby("tau")["score"].mean()
        assert summary["variants"][v]["best_tau"] == means.idxmin()
        assert summary["variants"][v]["best_mean_score"] == pytest.approx(means.min())
    for form in ("table_normal", "table_t"):
        t = summary[form]
        assert t["TT"]["UU"] + t["UU"]["TT"] == pytest.approx(1.0)
        assert all(0.0 <= t[a][b] <= 1.0 for a in t for b in t if a != b)
    paths = write_outputs(serial_results, summary, tmp_path / "out", title="test")
    back = pd.read_parquet(paths["results"])
    pd.testing.assert_frame_equal(back, serial_results)
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["n_datasets"] == 3
    assert len(paths["figures"]) == 6
    assert "TT" in (tmp_path / "out" / "table1.md").read_text()


def test_cli_experiment(prior_path: str, tmp_path, capsys) -> None:
    from tracker.cli import main

    out = tmp_path / "cli"
    argv = ["experiment", "--prior", prior_path, "--datasets", "2", "--reports", "15", "--tau", "-2:2:2",
            "--targets", "60", "--workers", "1", "--quiet", "--poisson-mu", "80", "--integrator", "terraces",
            "--out", str(out)]
    assert main(argv) == 0
    results = pd.read_parquet(out / "results.parquet")
    paper = results[results.s_model == "exp"]
    assert sorted(paper["tau"].unique()) == [-2.0, 0.0, 2.0]
    assert set(results["seed"]) == {0, 1} and len(results) == 2 * 3 * (3 + 1)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["integrator"] == "terraces"
    exact_tt = results[(results.s_model == "poisson") & (results.variant == "TT")]["score"]
    assert summary["variants"]["TT"]["poisson_mean_score_x10^4.5"] == pytest.approx(exact_tt.mean() * 10**4.5)
    assert "best tau" in capsys.readouterr().out
    assert main(["experiment", "--prior", str(tmp_path / "missing.tif"), "--out", str(out)]) == 1
    assert "missing.tif" in capsys.readouterr().err
    assert main(["experiment", "--prior", prior_path, "--tau", "3:-3:1", "--out", str(out)]) == 1
    assert "--tau" in capsys.readouterr().err


def test_rebuilt_prior_at_the_same_path_is_reread(tmp_path) -> None:
    from pipeline.prior.terrain import PriorError
    from tracker.study.experiment import _load_prior

    grid = Grid("EPSG:32734", Affine(20.0, 0.0, 300000.0, 0.0, -20.0, 6200000.0), 50, 50)
    path = tmp_path / "prior.tif"
    TerrainPrior.uniform(grid).write(path)
    first = _load_prior(str(path)).density.copy()
    r = np.ones((50, 50))
    r[:, :25] = 3.0
    TerrainPrior.from_array(r, grid).write(path)
    again = _load_prior(str(path)).density
    np.testing.assert_allclose(first, 1.0 / (1000.0 * 1000.0), rtol=1e-6)
    np.testing.assert_allclose(again[0, 0] / again[0, -1], 3.0, rtol=1e-6)
    with pytest.raises(PriorError, match="missing.tif"):
        _load_prior(str(tmp_path / "missing.tif"))


@pytest.mark.parametrize("window", [False, True])
def test_run_dataset_with_batch_matches_a_direct_batch_run(prior_path: str, window: bool) -> None:
    """``methods=("greedy", "batch")``: batch rows come from the batch MAP search started at greedy's
    partition, under r over the grid or (``batch_window``) r restricted to the keep window; they score
    like a direct scoring of that partition, and never have a lower ln p(Λ|Z) than greedy's partition
    under the same model."""
    from tracker.association.batch import BatchAssociator, batch_estimate, log_posterior

    config = _config(taus=(-1.0,), variants=("UU", "TT"), methods=("greedy", "batch"), poisson_mu=150.0,
                     batch_anneal=4, batch_restarts=0, batch_window=window)
    records = pd.DataFrame(run_dataset(prior_path, 5, config))
    assert set(records.algorithm) == {"UU", "TT", "UU batch", "TT batch"} and len(records) == 8
    prior = TerrainPrior.read(prior_path)
    model = window_prior(prior, central_windows(prior, None, 0.5)[1]) if window else prior
    sc = simulate(prior, 5, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    ref = perfect_estimate(prior, sc.reports)
    for _, rec in records[records.method == "batch"].iterrows():
        s_model = PoissonS(150.0) if rec.s_model == "poisson" else ExpS(rec.tau)
        g = associate(prior, sc.reports, rec.variant, s_model=s_model).assignments  # fresh: no shared cache
        on = g >= 0
        if window and rec.variant == "TT":
            on &= integrate(model, sc.reports.means, sc.reports.covs) > 0
        kept = np.flatnonzero(on)
        sub = sc.reports.subset(kept)
        init = np.unique(g[kept], return_inverse=True)[1]
        res = BatchAssociator(model, rec.variant, s_model=s_model, anneal=4, restarts=0).fit(sub, init=init)
        est = batch_estimate(prior, sub, res.labels, "UU")
        expected = score(prior, est.means, est.covs, rec.variant != "UU", ref.means, ref.covs, True)
        assert rec.score == pytest.approx(expected, rel=1e-9, abs=1e-12)
        assert rec.nd_hat == res.n_detected
        assert rec.log_posterior == pytest.approx(log_posterior(model, sub, res.labels, s_model, rec.variant), abs=1e-6)
        assert rec.greedy_log_posterior == pytest.approx(log_posterior(model, sub, init, s_model, rec.variant), abs=1e-6)
        assert rec.log_posterior >= rec.greedy_log_posterior - 1e-9
        if not window:
            greedy = records[(records.method == "greedy") & (records.variant == rec.variant) & (records.s_model == rec.s_model)]
            assert rec.greedy_log_posterior == pytest.approx(greedy.log_posterior.iloc[0], abs=1e-9)


def test_window_prior_is_r_restricted_to_the_window(prior_path: str) -> None:
    """The design's model: r on the window's cells, renormalised there, on a grid that is the window
    (so UU's uniform density is 1 / window area); μ = n × the window's share of the region's mass."""
    from tracker.association.batch import log_posterior

    prior = TerrainPrior.read(prior_path)
    region, keep = central_windows(prior, None, 0.5)
    wp = window_prior(prior, keep)
    mask = window_mask(prior, keep)
    assert wp.grid.bounds == pytest.approx(keep) and wp.grid.shape == (150, 150) and mask.sum() == 150 * 150
    np.testing.assert_allclose(wp.density, prior.density[mask].reshape(150, 150) / (prior.density[mask].sum() * prior.grid.cell_area))
    assert wp.density.sum() * wp.grid.cell_area == pytest.approx(1.0)
    assert expected_in_window(prior, 200, None) == pytest.approx(200 * prior.density[mask].sum() / prior.density.sum())
    # UU: one report alone has ln L = ln u, u = 1 / window area
    rep = simulate(prior, 0, 10, 1, None, 0.5).reports
    area = (keep[2] - keep[0]) * (keep[3] - keep[1])
    assert area == 3000.0**2 and log_posterior(wp, rep, np.zeros(1, np.int64), ExpS(0.0), "UU") == pytest.approx(-np.log(area))
    with pytest.raises(ValueError, match="no cell centre"):
        window_prior(prior, (0.0, 0.0, 10.0, 10.0))


def test_posterior_median() -> None:
    assert posterior_median(np.array([3, 4, 5]), np.array([0.2, 0.3, 0.5])) == 4  # CDF reaches 1/2 at 4
    assert posterior_median(np.array([3, 4, 5]), np.array([0.2, 0.31, 0.49])) == 4
    assert posterior_median(np.array([3, 4, 5]), np.array([0.6, 0.3, 0.1])) == 3
    assert posterior_median(np.array([7]), np.array([1.0])) == 7


def test_batch_nd_is_the_posterior_median_with_exact_s_and_the_map_count_at_tau(prior_path: str) -> None:
    """run_experiment adds batch's Bayes N̂_D (the posterior median of a sampler started at the MAP) with
    the exact S and nowhere else; at τ* summarise compares batch's MAP count, with the exact S the median."""
    from tracker.association.batch import BatchAssociator

    config = _config(n_datasets=2, taus=(-3.0, 0.0), variants=("UU", "UT", "TT"), methods=("greedy", "batch"),
                     poisson_mu=150.0, batch_anneal=4, batch_restarts=0, batch_nd_samples=30, batch_nd_burn_in=5)
    results = run_experiment(prior_path, config, workers=1, progress=False)
    summary = summarise(results, config)
    batch = results[results.method == "batch"]
    assert results[results.method == "greedy"]["nd_hat_bayes"].isna().all()
    for v in ("UU", "UT", "TT"):
        best = summary["variants"][f"{v} batch"]["best_tau"]
        rows = batch[batch.variant == v]
        filled = rows[rows.nd_hat_bayes.notna()]
        assert (filled.s_model == "poisson").all() and len(filled) == 2
        at_best = rows[rows.tau == best].sort_values("seed")
        d = summary["batch_vs_greedy"][v]
        assert d["mean_nd_abs_error_best_tau"][0] == pytest.approx(at_best.nd_abs_error.mean())
        np.testing.assert_array_equal(at_best.nd_abs_error, (at_best.nd_hat - at_best.nd).abs())
        assert d["mean_nd_abs_error_exact_s"][0] == pytest.approx(filled.nd_abs_error_bayes.mean())
        assert d["mean_nd_abs_error_exact_s_map_count"][0] == pytest.approx(filled.nd_abs_error.mean())
        assert "mean_nd_abs_error_best_tau_map_count" not in d
        np.testing.assert_array_equal(filled.nd_abs_error_bayes, (filled.nd_hat_bayes - filled.nd).abs())
    # a direct sampler run from the MAP partition gives the same median
    prior = TerrainPrior.read(prior_path)
    model = window_prior(prior, central_windows(prior, None, 0.5)[1])
    rec = batch[(batch.variant == "TT") & (batch.s_model == "poisson") & (batch.seed == 1)].iloc[0]
    sc = simulate(prior, 1, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    g = associate(prior, sc.reports, "TT", s_model=PoissonS(150.0)).assignments
    kept = np.flatnonzero((g >= 0) & (integrate(model, sc.reports.means, sc.reports.covs) > 0))
    sub = sc.reports.subset(kept)
    mapped = BatchAssociator(model, "TT", s_model=PoissonS(150.0), anneal=4, restarts=0).fit(
        sub, init=np.unique(g[kept], return_inverse=True)[1])
    res = BatchAssociator(model, "TT", s_model=PoissonS(150.0), mode="sample", burn_in=5, samples=30, split_merge=1,
                          seed=1).fit(sub, init=mapped.labels)
    assert rec.nd_hat_bayes == posterior_median(res.nd_values, res.nd_prob)


def test_map_convergence_compares_the_experiments_map_with_a_long_search(prior_path: str) -> None:
    """The short side is the experiment's own batch MAP; the long search starts from greedy too and
    keeps its best state, so it is never below greedy's partition; both are ln p of a partition."""
    from tracker.study.experiment import map_convergence

    config = _config(n_datasets=2, taus=(-3.0,), variants=("TT",), methods=("greedy", "batch"), poisson_mu=150.0,
                     batch_anneal=4, batch_restarts=0, batch_nd_samples=0)
    results = run_experiment(prior_path, config, workers=1, progress=False)
    recs = map_convergence(prior_path, 1, config, (("TT", "poisson", None), ("TT", "exp", -3.0)), anneal=6, restarts=1,
                           split_merge=2)
    batch = results[(results.method == "batch") & (results.seed == 1)]
    for rec in recs:
        row = batch[batch.s_model == rec["s_model"]].iloc[0]
        assert rec["short_log_posterior"] == pytest.approx(row.log_posterior, abs=1e-9)
        assert rec["long_log_posterior"] >= row.greedy_log_posterior - 1e-9
        assert np.isfinite(rec["long_log_posterior"])


def test_cli_experiment_with_methods(prior_path: str, tmp_path, capsys) -> None:
    from tracker.cli import main

    out = tmp_path / "cli"
    argv = ["experiment", "--prior", prior_path, "--datasets", "2", "--reports", "15", "--tau", "-2,0",
            "--targets", "60", "--variants", "UU,TT", "--methods", "greedy,batch,posterior", "--workers", "1", "--quiet",
            "--out", str(out)]
    assert main(argv) == 0
    algorithms = {"UU", "TT", "UU batch", "TT batch", "UU posterior", "TT posterior"}
    results = pd.read_parquet(out / "results.parquet")
    assert set(results.algorithm) == algorithms
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["table_normal"]) == algorithms
    assert set(summary["batch_vs_greedy"]) == set(summary["posterior_vs_greedy"]) == {"UU", "TT"}
    gain = summary["batch_vs_greedy"]["TT"]["min_log_posterior_gain"]
    assert gain >= -1e-9 and 0.0 <= summary["batch_vs_greedy"]["TT"]["prob_better_score_best_tau"] <= 1.0
    for name in ("TT batch", "TT posterior"):
        assert (out / f"score_{name.replace(' ', '_')}.png").exists() and name in (out / "table1.md").read_text()
    printed = capsys.readouterr().out
    assert "TT batch vs greedy" in printed and "TT posterior vs greedy" in printed
    assert main(["experiment", "--prior", prior_path, "--methods", "greedy,mcmc", "--out", str(out)]) == 1
    assert "mcmc" in capsys.readouterr().err


# --- the posterior method: batch's Bayes estimates from a posterior sample -----------------------

@settings(max_examples=60, deadline=None)
@given(st.integers(1, 6), st.integers(1, 12), st.integers(0, 2**31 - 1))
def test_posterior_mixture_is_the_mean_of_the_sampled_mixtures(n_samples: int, n_kept: int, seed: int) -> None:
    """Each distinct cluster's weight is the mean over samples of 1/n_s where it occurs (brute force
    over frozensets of report indices); the weights sum to 1."""
    rng = np.random.default_rng(seed)
    n_reports = n_kept + int(rng.integers(0, 4))
    kept = np.sort(rng.choice(n_reports, n_kept, replace=False))
    samples = rng.integers(0, 4, (n_samples, n_kept)) * 7  # labels need not be 0..n−1
    sets, weights = posterior_mixture(samples, kept, n_reports)
    expected: dict[frozenset, float] = {}
    for labels in samples:
        clusters = {frozenset(kept[labels == c].tolist()) for c in np.unique(labels)}
        for c in clusters:
            expected[c] = expected.get(c, 0.0) + 1.0 / (len(clusters) * n_samples)
    got = {frozenset(np.frombuffer(m, np.int32).tolist()): w for m, w in zip(sets, weights, strict=True)}
    assert got.keys() == expected.keys() and len(sets) == len(got)
    for c, w in expected.items():
        assert got[c] == pytest.approx(w, rel=1e-12)
    assert weights.sum() == pytest.approx(1.0)
    assert all(np.all(np.diff(np.frombuffer(m, np.int32)) > 0) for m in sets)


def test_fuse_sets_fuses_overlapping_sets_like_perfect_estimate(prior_path: str) -> None:
    """Each set is fused as perfect_estimate fuses that set's reports alone."""
    prior = TerrainPrior.read(prior_path)
    reports = simulate(prior, 3, 40, 12, None, 0.5).reports
    sets = [np.array(s, np.int32).tobytes() for s in ([0, 3, 5], [3], [1, 2, 3, 4, 11], [0, 3, 5, 7])]
    fused = fuse_sets(prior, reports, sets)
    for q, m in enumerate(sets):
        idx = np.frombuffer(m, np.int32).astype(np.intp)
        sub = reports.subset(idx)
        one = perfect_estimate(prior, type(sub)(sub.means, sub.covs, sub.times, np.zeros(idx.size, np.int64)), terrain=False)
        np.testing.assert_allclose(fused.means[q], one.means[0], rtol=1e-12)
        np.testing.assert_allclose(fused.covs[q], one.covs[0], rtol=1e-10)


def test_run_dataset_posterior_scores_the_posterior_mean_of_the_sampled_mixtures(prior_path: str) -> None:
    """``methods=("posterior",)``: the Score is that of the mean over a direct sampler run's partitions
    of their equally weighted mixtures (every sample's clusters scored as separate components, no
    merging of equal clusters); N̂_D is that sample's posterior median; ln p and the point metrics are
    the MAP partition's (the batch rows')."""
    from tracker.association.batch import BatchAssociator, batch_estimate
    from tracker.study.metrics import ScoreGram

    config = _config(taus=(-1.0,), variants=("TT",), methods=("batch", "posterior"), poisson_mu=150.0,
                     batch_anneal=4, batch_restarts=0, batch_nd_samples=8, batch_nd_burn_in=2)
    records = pd.DataFrame(run_dataset(prior_path, 5, config))
    assert set(records.algorithm) == {"TT batch", "TT posterior"} and len(records) == 4
    prior = TerrainPrior.read(prior_path)
    model = window_prior(prior, central_windows(prior, None, 0.5)[1])
    sc = simulate(prior, 5, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    ref = perfect_estimate(prior, sc.reports)
    for _, rec in records[records.method == "posterior"].iterrows():
        s_model = PoissonS(150.0) if rec.s_model == "poisson" else ExpS(rec.tau)
        g = associate(prior, sc.reports, "TT", s_model=s_model).assignments
        kept = np.flatnonzero((g >= 0) & (integrate(model, sc.reports.means, sc.reports.covs) > 0))
        sub = sc.reports.subset(kept)
        mapped = BatchAssociator(model, "TT", s_model=s_model, anneal=4, restarts=0).fit(
            sub, init=np.unique(g[kept], return_inverse=True)[1])
        res = BatchAssociator(model, "TT", s_model=s_model, mode="sample", burn_in=2, samples=8, split_merge=1,
                              seed=5, keep_samples=True).fit(sub, init=mapped.labels)
        assert res.samples.shape == (8, kept.size)
        means, covs, weights = [], [], []
        for labels in res.samples:
            est = batch_estimate(prior, sub, np.unique(labels, return_inverse=True)[1], "UU")
            means.append(est.means)
            covs.append(est.covs)
            weights.append(np.full(len(est.means), 1.0 / (len(est.means) * len(res.samples))))
        means, covs = np.concatenate([*means, ref.means]), np.concatenate([*covs, ref.covs])
        w = np.concatenate([*weights, np.full(len(ref.means), -1.0 / len(ref.means))])
        gram = ScoreGram(prior, means, covs, np.ones(len(means), bool))
        assert rec.score == pytest.approx(gram.score(w)[0], rel=1e-6)
        assert rec.nd_hat == posterior_median(res.nd_values, res.nd_prob)
        twin = records[(records.method == "batch") & (records.s_model == rec.s_model)].iloc[0]
        for col in ("log_posterior", "greedy_log_posterior", "gospa_m", "purity"):
            assert rec[col] == twin[col]
        assert rec.score != twin.score


def test_posterior_method_needs_samples() -> None:
    with pytest.raises(ValueError, match="batch_nd_samples >= 1"):
        ExperimentConfig(methods=("greedy", "posterior"), batch_nd_samples=0)
