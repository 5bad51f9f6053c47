"""tracker.study.regimes: the sensor scaling against the closed form (covariances scale by s²), the
best-τ summary against a brute-force loop over a synthetic results table, and the grid's cells
against direct runs of the experiment."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from affine import Affine
from hypothesis import example, given, settings
from hypothesis import strategies as st

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.study.experiment import ExperimentConfig, run_experiment
from tracker.study.regimes import best_tau_summary, regime_grid, report_spread_m, scaled_sensor
from tracker.study.simulate import AirborneSensor


@given(scale=st.floats(0.05, 20.0), seed=st.integers(0, 1000))
@example(scale=2.5, seed=500)
@settings(max_examples=25, deadline=None)
def test_scaled_sensor_scales_covariances_by_the_square(scale: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    sensor = AirborneSensor(range_std_m=rng.uniform(1, 30), azimuth_std_rad=rng.uniform(1e-4, 1e-2))
    platform = rng.uniform(-3e4, 3e4, (20, 2))
    targets = platform + rng.uniform(1e3, 5e4, (20, 1)) * np.stack([np.cos(a := rng.uniform(0, 6.3, 20)), np.sin(a)], 1)
    got = scaled_sensor(sensor, scale).covariances(platform, targets)
    expected = scale**2 * sensor.covariances(platform, targets)
    # relative to each matrix's largest entry: an off-diagonal entry is a difference of two terms that
    # can cancel, so its own relative error is unbounded (scale 2.5, seed 500: 2.3e-12 of itself)
    err, size = np.abs(got - expected).max(axis=(1, 2)), np.abs(expected).max(axis=(1, 2))
    assert (err <= 1e-12 * size).all(), (err / size).max()
    assert scaled_sensor(sensor, scale).altitude_m == sensor.altitude_m


@pytest.mark.parametrize("scale", [0.0, -1.0, math.inf, math.nan])
def test_scaled_sensor_rejects_bad_scale(scale: float) -> None:
    with pytest.raises(ValueError, match="scale"):
        scaled_sensor(AirborneSensor(), scale)


def _synthetic_results(rng: np.random.Generator, n_seeds: int, taus: list[float]) -> pd.DataFrame:
    rows = [
        {"seed": s, "variant": v, "tau": t, "score": rng.uniform(0.5, 2.0)}
        for s in range(n_seeds) for v in ("UU", "UT", "TT") for t in taus
    ]
    return pd.DataFrame(rows).sample(frac=1.0, random_state=int(rng.integers(1 << 30)))  # row order must not matter


@given(seed=st.integers(0, 10_000), n_seeds=st.integers(2, 6), n_taus=st.integers(1, 5))
@settings(max_examples=30, deadline=None)
def test_best_tau_summary_matches_a_brute_force_loop(seed: int, n_seeds: int, n_taus: int) -> None:
    rng = np.random.default_rng(seed)
    taus = sorted(rng.choice(np.arange(-10.0, 3.0, 0.5), n_taus, replace=False).tolist())
    df = _synthetic_results(rng, n_seeds, taus)
    got = best_tau_summary(df)
    # Oracle: plain dictionaries and loops, the normal-form probability written out with math.erf.
    table = {(r.variant, r.tau, r.seed): r.score for r in df.itertuples()}
    best = {}
    for v in ("UU", "UT", "TT"):
        means = {t: sum(table[(v, t, s)] for s in range(n_seeds)) / n_seeds for t in taus}
        tau_star = min(taus, key=lambda t: (means[t], taus.index(t)))
        best[v] = [table[(v, tau_star, s)] for s in range(n_seeds)]
        assert got[f"best_tau_{v}"] == tau_star
        assert got[f"score_{v}"] == pytest.approx(means[tau_star], rel=1e-12)
    for a, b in (("TT", "UU"), ("UT", "UU"), ("TT", "UT")):
        assert got[f"gain_{a}_over_{b}"] == pytest.approx(1 - sum(best[a]) / sum(best[b]), rel=1e-9, abs=1e-12)
        d = [x - y for x, y in zip(best[a], best[b], strict=True)]
        mean = sum(d) / len(d)
        sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (len(d) - 1))
        expected = 0.5 * (1 + math.erf(-mean * math.sqrt(len(d)) / sd / math.sqrt(2))) if sd > 0 else float(mean < 0)
        assert got[f"p_{a}_better_{b}"] == pytest.approx(expected, abs=1e-9)


@pytest.fixture(scope="module")
def prior_path(tmp_path_factory) -> str:
    """A 6 km square prior with two road-like ridges, written like `terrain-prior build` does."""
    n = 300
    yy, xx = np.mgrid[0:n, 0:n]
    r = 0.15 + np.exp(-0.5 * ((xx - 0.6 * yy - 80) / 5.0) ** 2) + np.exp(-0.5 * ((yy - 170) / 5.0) ** 2)
    grid = Grid("EPSG:32734", Affine(20.0, 0.0, 300000.0, 0.0, -20.0, 6200000.0), n, n)
    path = tmp_path_factory.mktemp("prior") / "prior.tif"
    TerrainPrior.from_array(r, grid).write(path)
    return str(path)


def test_regime_grid_cells_equal_direct_runs(prior_path: str) -> None:
    base = ExperimentConfig(n_datasets=2, n_reports=40, taus=(-5.0, -2.0, 1.0), n_targets=60, region_m=None,
                            sensor=AirborneSensor(standoff_m=15000.0))
    grid = regime_grid(prior_path, [1.0, 3.0], [40, 80], base, workers=1, progress=False)
    assert list(zip(grid["noise_scale"], grid["n_targets"], strict=True)) == [(1.0, 40), (1.0, 80), (3.0, 40), (3.0, 80)]
    assert np.isfinite(grid["gain_TT_over_UU"]).all()
    prior = TerrainPrior.read(prior_path)
    unit_spread = report_spread_m(prior, replace(base, n_targets=40))
    for row in grid.itertuples():
        config = replace(base, n_targets=row.n_targets,
                         sensor=AirborneSensor(standoff_m=15000.0, range_std_m=12.0 * row.noise_scale,
                                               azimuth_std_rad=0.002 * row.noise_scale))
        direct = run_experiment(prior_path, config, workers=1, progress=False)
        expected = best_tau_summary(direct)
        for key, value in expected.items():
            assert getattr(row, key) == pytest.approx(value, rel=1e-12, nan_ok=True), key
        assert row.mean_targets_in_window == direct.groupby("seed")["n_targets"].first().mean()
        if row.n_targets == 40:
            # The ellipses depend on geometry only, so the spread scales exactly with the noise.
            assert row.spread_m == pytest.approx(row.noise_scale * unit_spread, rel=1e-9)


def test_gain_is_nan_when_the_baseline_is_perfect() -> None:
    df = pd.DataFrame([{"seed": s, "variant": v, "tau": 0.0, "score": 0.0 if v == "UU" else 1.0 + s}
                       for s in range(3) for v in ("UU", "UT", "TT")])
    got = best_tau_summary(df)
    assert math.isnan(got["gain_TT_over_UU"]) and got["p_TT_better_UU"] < 1e-3  # TT scores worse on every set
    assert got["gain_TT_over_UT"] == 0.0


def test_regime_grid_rejects_empty_axes(prior_path: str) -> None:
    with pytest.raises(ValueError, match="noise_scales"):
        regime_grid(prior_path, [], [10], ExperimentConfig(n_datasets=2))
