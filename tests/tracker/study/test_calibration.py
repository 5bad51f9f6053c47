"""Calibration study of the batch sampler: the reliability table against known calibrated and
miscalibrated probabilities, the model-exact simulation, and a small end-to-end study with its figure."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.study.calibration import (
    calibration_markdown,
    calibration_study,
    reliability,
    reliability_figure,
    simulate_model,
)
from tracker.study.experiment import expected_in_window, window_mask, window_prior
from tracker.study.simulate import central_windows


@pytest.fixture(scope="module")
def prior() -> TerrainPrior:
    n = 300
    yy, xx = np.mgrid[0:n, 0:n]
    r = 0.15 + np.exp(-0.5 * ((xx - 0.6 * yy - 80) / 5.0) ** 2) + np.exp(-0.5 * ((yy - 170) / 5.0) ** 2)
    return TerrainPrior.from_array(r, Grid("EPSG:32734", Affine(20.0, 0.0, 300000.0, 0.0, -20.0, 6200000.0), n, n))


def test_reliability_passes_calibrated_and_fails_miscalibrated_probabilities() -> None:
    rng = np.random.default_rng(0)
    p = rng.random(200_000)
    good = reliability(p, rng.random(p.size) < p)
    assert all(r["in_band"] for r in good) and sum(r["n"] for r in good) == p.size
    for r in good:
        assert r["fraction_same"] == pytest.approx(r["p"] + 0.05, abs=0.01)
    bad = reliability(p, rng.random(p.size) < p**2)  # overconfident: true frequency below p
    assert not any(r["in_band"] for r in bad[3:8])
    # SE over data sets: Σ same / Σ n per set, delta method; two sets of 4 pairs (3 and 1 same) → 0.25
    rows = reliability(np.full(8, 0.55), np.array([1, 1, 1, 0, 1, 0, 0, 0], bool), groups=np.repeat([0, 1], 4))
    assert rows[5]["fraction_same"] == 0.5 and rows[5]["std_error_sets"] == pytest.approx(np.sqrt(2 * 2 * 1.0**2) / 8)
    assert rows[0]["std_error_sets"] is None and rows[5]["in_band"]
    assert reliability(np.array([0.95]), np.array([True]))[0] == {"p": 0.0, "n": 0, "fraction_same": None,
                                                                   "mean_prob": None, "std_error": None, "in_band": False}


def test_simulate_model_draws_from_the_model(prior: TerrainPrior) -> None:
    _, keep = central_windows(prior, 14000.0, 0.5)
    wp = window_prior(prior, keep)
    mask = window_mask(prior, keep)
    assert wp.grid.bounds == pytest.approx(keep) and wp.density.sum() * wp.grid.cell_area == pytest.approx(1.0)
    counts = [len(simulate_model(wp, 7.0, 30, s).targets) for s in range(200)]
    assert np.mean(counts) == pytest.approx(7.0, abs=0.5) and np.var(counts) == pytest.approx(7.0, rel=0.3)
    sc = simulate_model(wp, 7.0, 30, 1)
    x, y = sc.targets[:, 0], sc.targets[:, 1]
    assert ((x >= keep[0]) & (x < keep[2]) & (y >= keep[1]) & (y < keep[3])).all()
    assert sc.reports.truth.max() < len(sc.targets)
    mu = expected_in_window(prior, 200)
    assert mu == pytest.approx(200 * prior.density[mask].sum() / prior.density.sum())


def test_small_calibration_study_and_figure(prior: TerrainPrior, tmp_path) -> None:
    studies = [calibration_study(prior, 2, design, n_targets=40, n_reports=25, burn_in=5, samples=20, split_merge=1)
               for design in ("model", "paper", "paper-grid")]
    for st in studies:
        assert st["pairs"] == sum(r["n"] for r in st["bins"]) > 0
        assert st["bins_with_pairs"] >= st["bins_in_band"] >= 0
        assert "| pairs |" in calibration_markdown(st) and "SE over data sets" in calibration_markdown(st)
    # "paper" and "paper-grid" associate the same data under r on the window and on the grid
    assert studies[1]["pairs"] == studies[2]["pairs"]
    assert [r["n"] for r in studies[1]["bins"]] != [r["n"] for r in studies[2]["bins"]]
    path = reliability_figure(studies, tmp_path / "rel.png")
    assert path.stat().st_size > 1000
    with pytest.raises(ValueError, match="design"):
        calibration_study(prior, 1, "other")
