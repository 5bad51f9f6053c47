"""Validate once, at the boundary: one check_gaussians pass per batch of reports, however many
integrals the association and the run use case compute from it."""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
import pytest

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import associate
from tracker.integrate import integrate, integrate_checked
from tracker.models.motion import ConstantVelocity
from tracker.run import track_files
from tracker.types import reports as reports_module
from tracker.types.reports import Reports


@pytest.fixture
def calls(monkeypatch) -> list[str]:
    """Counts every call of check_gaussians, wherever a module bound the name."""
    original = reports_module.check_gaussians
    seen: list[str] = []

    def counting(means, covs, what):
        seen.append(what)
        return original(means, covs, what)

    for module in list(sys.modules.values()):
        if getattr(module, "check_gaussians", None) is original and module.__name__.startswith("tracker"):
            monkeypatch.setattr(module, "check_gaussians", counting)
    return seen


def _prior() -> TerrainPrior:
    g = Grid.from_bounds((0.0, 0.0, 6000.0, 6000.0), 20.0, "EPSG:32634")
    yy, xx = np.mgrid[0 : g.height, 0 : g.width]
    return TerrainPrior.from_array(1.0 + 0.8 * np.cos(xx / 7.0) * np.sin(yy / 11.0), g)


def _arrays(n: int = 60, seed: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    targets = rng.uniform(1500, 4500, (6, 2))
    sd = rng.uniform(15, 60, (n, 2))
    means = targets[rng.integers(0, 6, n)] + rng.normal(0, 1, (n, 2)) * sd
    covs = np.zeros((n, 2, 2))
    covs[:, 0, 0], covs[:, 1, 1] = sd[:, 0] ** 2, sd[:, 1] ** 2
    return means, covs, np.arange(n, dtype=np.float64)


@pytest.mark.parametrize("variant", ["TT", "UT", "UU"])
def test_associate_checks_a_batch_once(calls, variant):
    reports = Reports.create(*_arrays())
    assert calls == ["reports"]
    result = associate(_prior(), reports, variant, tau=-1.0)
    assert result.stats["integrals"] >= (0 if variant == "UU" else len(reports))  # many integrals, one check
    assert calls == ["reports"]


def test_associate_with_motion_checks_a_batch_once(calls):
    reports = Reports.create(*_arrays())
    associate(_prior(), reports, "TT", tau=-1.0, motion=ConstantVelocity(0.1, 10.0))
    assert calls == ["reports"]


def test_track_files_checks_a_batch_once(calls, tmp_path):
    prior = _prior()
    prior.write(tmp_path / "prior.tif")
    means, covs, times = _arrays()
    pd.DataFrame({"x": means[:, 0], "y": means[:, 1], "time": times, "cov_xx": covs[:, 0, 0],
                  "cov_xy": covs[:, 0, 1], "cov_yy": covs[:, 1, 1]}).to_csv(tmp_path / "r.csv", index=False)
    track_files(tmp_path / "prior.tif", tmp_path / "r.csv", tmp_path / "t.gpkg", "TT",
                assignments_csv=tmp_path / "a.csv")
    assert calls == ["reports"]


def test_subset_is_not_checked_again(calls):
    reports = Reports.create(*_arrays())
    sub = reports.subset(slice(10, 20))
    assert calls == ["reports"] and len(sub) == 10
    np.testing.assert_array_equal(sub.means, reports.means[10:20])


def test_integrate_checks_and_integrate_checked_does_not(calls):
    prior = _prior()
    means, covs, _ = _arrays(8)
    np.testing.assert_array_equal(integrate(prior, means, covs), integrate_checked(prior, means, covs))
    assert calls == ["integrate"]


def test_the_constructor_checks_too():
    means, covs, times = _arrays(5)
    covs[3] = [[1.0, 2.0], [2.0, 1.0]]
    with pytest.raises(ValueError, match=r"positive definite at indices \[3\]"):
        Reports(means, covs, times, np.full(5, -1))
