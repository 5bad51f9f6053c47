"""Scenario generator: sampler frequencies (chi-square), windows, sensor model against a Jacobian oracle."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine
from scipy import stats

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.prior.test_terrain import random_prior
from tracker.study.simulate import AirborneSensor, central_windows, simulate

CRS = "EPSG:32633"


def test_central_windows_paper_geometry() -> None:
    grid = Grid(CRS, Affine(20.0, 0.0, 0.0, 0.0, -20.0, 20000.0), 1000, 1000)  # 20 km square
    prior = TerrainPrior.uniform(grid)
    region, keep = central_windows(prior, 14000.0, 0.5)
    assert region == (3000.0, 3000.0, 17000.0, 17000.0)
    assert keep == (6500.0, 6500.0, 13500.0, 13500.0)
    # A grid smaller than the region: the whole grid, central half kept.
    small = TerrainPrior.uniform(Grid(CRS, Affine(20.0, 0.0, 0.0, 0.0, -20.0, 4000.0), 200, 300))
    region, keep = central_windows(small, 14000.0, 0.5)
    assert region == (0.0, 0.0, 6000.0, 4000.0)
    assert keep == (1500.0, 1000.0, 4500.0, 3000.0)


def test_sensor_covariance_matches_range_azimuth_jacobian() -> None:
    """Oracle: V = J diag(σ_ρ², σ_θ²) Jᵀ with J the numerical Jacobian of (slant range, azimuth) ↦ ground point."""
    sensor = AirborneSensor()
    rng = np.random.default_rng(6)
    platform = rng.uniform(-1000, 1000, size=(5, 2))
    targets = platform + rng.uniform(5000, 40000, size=(5, 1)) * np.stack(
        [np.cos(a := rng.uniform(0, 2 * np.pi, 5)), np.sin(a)], axis=1
    )
    V = sensor.covariances(platform, targets)
    h = sensor.altitude_m
    for k in range(5):
        d = targets[k] - platform[k]
        rho, az = np.hypot(np.hypot(*d), h), np.arctan2(d[1], d[0])

        def ground(rho_: float, az_: float, k: int = k) -> np.ndarray:
            g = np.sqrt(rho_**2 - h**2)
            return platform[k] + g * np.array([np.cos(az_), np.sin(az_)])

        e = 1e-3
        J = np.stack(
            [(ground(rho + e, az) - ground(rho - e, az)) / (2 * e), (ground(rho, az + 1e-7) - ground(rho, az - 1e-7)) / 2e-7],
            axis=1,
        )
        expected = J @ np.diag([sensor.range_std_m**2, sensor.azimuth_std_rad**2]) @ J.T
        np.testing.assert_allclose(V[k], expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())


def test_platform_track_geometry() -> None:
    sensor = AirborneSensor(standoff_m=20000.0, speed_mps=100.0)
    times = np.arange(11) * 10.0
    centre = np.array([1000.0, 2000.0])
    track = sensor.platform_track(times, centre, 0.7)
    assert np.hypot(*(track[5] - centre)) == pytest.approx(20000.0)
    np.testing.assert_allclose(np.hypot(*np.diff(track, axis=0).T), 1000.0)
    assert np.hypot(*(track - centre).T).min() == pytest.approx(20000.0)


def test_simulate_windows_truth_and_noise() -> None:
    prior = random_prior(350, 350, 40.0, 7)  # 14 km square
    sc = simulate(prior, seed=11, n_targets=200, n_reports=4000)
    keep = sc.keep
    assert keep == pytest.approx((303500.0, 6189500.0, 310500.0, 6196500.0))
    t = sc.targets
    assert ((t[:, 0] >= keep[0]) & (t[:, 0] < keep[2]) & (t[:, 1] >= keep[1]) & (t[:, 1] < keep[3])).all()
    assert 20 < len(t) < 90  # about a quarter of 200 for a roughly even prior
    rep = sc.reports
    assert rep.truth.min() >= 0 and rep.truth.max() < len(t)
    assert sc.n_detected == np.unique(rep.truth).size
    # Noise: Mahalanobis² residuals are χ²(2); reports are picked uniformly.
    res = rep.means - t[rep.truth]
    m2 = np.einsum("ki,kij,kj->k", res, np.linalg.inv(rep.covs), res)
    assert stats.kstest(m2, stats.chi2(2).cdf).pvalue > 1e-3
    _, p = stats.chisquare(np.bincount(rep.truth, minlength=len(t)))
    assert p > 1e-3
    np.testing.assert_allclose(rep.covs, AirborneSensor().covariances(sc.platform, t[rep.truth]))


def test_simulate_is_seeded() -> None:
    prior = random_prior(100, 100, 50.0, 8)
    a, b, c = simulate(prior, 3), simulate(prior, 3), simulate(prior, 4)
    np.testing.assert_array_equal(a.reports.means, b.reports.means)
    np.testing.assert_array_equal(a.targets, b.targets)
    assert not np.array_equal(a.reports.means, c.reports.means)


def test_bad_input() -> None:
    prior = random_prior(10, 10, 20.0, 9)
    with pytest.raises(ValueError, match="altitude_m"):
        AirborneSensor(altitude_m=-1.0)
    with pytest.raises(ValueError, match="keep_fraction"):
        simulate(prior, 0, keep_fraction=0.0)
    with pytest.raises(ValueError, match="n_targets"):
        simulate(prior, 0, n_targets=0)
    empty = np.zeros((10, 10))
    empty[0, 0] = 1.0  # all mass in a corner: nothing lands in the keep window
    corner = TerrainPrior.from_array(empty, prior.grid)
    with pytest.raises(ValueError, match="keep window"):
        simulate(corner, 0, n_targets=5)


@pytest.mark.slow
@pytest.mark.realdata
def test_swellendam_scenario(swellendam) -> None:
    """On the real Swellendam prior: 1 km block frequencies of the sampler match the prior's mass
    (chi-square), and every simulated target sits where the prior is positive, inside the window."""
    from pathlib import Path

    from pipeline.build.region import build_region_prior
    from pipeline.config.region import load_config

    config = load_config(Path(__file__).resolve().parents[3] / "terrain_data" / "swellendam.toml")
    prior = build_region_prior(config, progress=False)
    region, keep = central_windows(prior, 14000.0, 0.5)
    n = 50000
    pts = prior.sample(n, np.random.default_rng(12), region)
    u, v = prior.grid.to_pixel(pts[:, 0], pts[:, 1])
    (u0, u1), (v0, v1) = (np.rint(a).astype(int) for a in prior.grid.to_pixel(region[::2], region[3::-2]))
    block = 50  # cells of 20 m: 1 km blocks (the last row/column of blocks may be partial)
    nb = (-(-(v1 - v0) // block), -(-(u1 - u0) // block))
    counts = np.zeros(nb)
    np.add.at(counts, (((v - v0) // block).astype(int), ((u - u0) // block).astype(int)), 1)
    padded = np.zeros((nb[0] * block, nb[1] * block))
    padded[: v1 - v0, : u1 - u0] = prior.density[v0:v1, u0:u1]
    mass = padded.reshape(nb[0], block, nb[1], block).sum(axis=(1, 3))
    pos = mass > 0
    _, p = stats.chisquare(counts[pos], n * mass[pos] / mass[pos].sum())
    assert p > 1e-3
    sc = simulate(prior, 3)
    t = sc.targets
    assert (prior.density_at(t[:, 0], t[:, 1]) > 0).all()
    assert ((t[:, 0] >= keep[0]) & (t[:, 0] < keep[2]) & (t[:, 1] >= keep[1]) & (t[:, 1] < keep[3])).all()
    assert len(sc.reports) == 100 and sc.n_detected <= len(t)


# --- real target locations (issue 16) ---------------------------------------------------------


def _points_prior() -> TerrainPrior:
    return TerrainPrior.uniform(Grid(CRS, Affine(20.0, 0.0, 0.0, 0.0, -20.0, 8000.0), 400, 400))  # 8 km square


def test_simulate_points_picks_distinct_locations_in_the_window() -> None:
    from tracker.study.simulate import simulate_points

    prior = _points_prior()
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 8000, size=(500, 2))
    sc = simulate_points(prior, points, seed=7, n_targets=30, n_reports=60, region_m=None)
    _, keep = central_windows(prior, None, 0.5)
    inside = (points[:, 0] >= keep[0]) & (points[:, 0] < keep[2]) & (points[:, 1] >= keep[1]) & (points[:, 1] < keep[3])
    assert sc.keep == keep and len(sc.targets) == 30
    # Every target is one of the file's locations inside the window, none twice.
    matches = (sc.targets[:, None, :] == points[inside][None, :, :]).all(axis=2)
    assert (matches.sum(axis=1) == 1).all() and len(np.unique(sc.targets, axis=0)) == 30
    assert sc.reports.truth.min() >= 0 and sc.reports.truth.max() < 30 and len(sc.reports) == 60
    # Seeded: the same seed gives the same data set, another seed another one.
    again = simulate_points(prior, points, seed=7, n_targets=30, n_reports=60, region_m=None)
    np.testing.assert_array_equal(again.targets, sc.targets)
    np.testing.assert_array_equal(again.reports.means, sc.reports.means)
    other = simulate_points(prior, points, seed=8, n_targets=30, n_reports=60, region_m=None)
    assert not np.array_equal(other.targets, sc.targets)


def test_simulate_points_takes_all_when_fewer_and_names_an_empty_window() -> None:
    from tracker.study.simulate import simulate_points

    prior = _points_prior()
    points = np.array([[4000.0, 4000.0], [3000.0, 5000.0], [100.0, 100.0]])  # two inside the central half
    sc = simulate_points(prior, points, seed=0, n_targets=10, n_reports=5, region_m=None)
    np.testing.assert_array_equal(sc.targets, points[:2])
    with pytest.raises(ValueError, match=r"buildings.gpkg: none of its 1 locations lies in the window"):
        simulate_points(prior, points[2:], seed=0, n_targets=10, region_m=None, source="buildings.gpkg")


def test_simulate_points_reports_follow_the_sensor_model() -> None:
    """The reports of real locations are the sensor's: mean error zero, whitened by V it is standard normal."""
    from tracker.study.simulate import simulate_points

    prior = _points_prior()
    points = np.random.default_rng(1).uniform(2000, 6000, size=(50, 2))
    sc = simulate_points(prior, points, seed=2, n_targets=50, n_reports=4000, region_m=None)
    err = sc.reports.means - sc.targets[sc.reports.truth]
    white = np.einsum("kij,kj->ki", np.linalg.inv(np.linalg.cholesky(sc.reports.covs)), err)
    assert stats.kstest(white.ravel(), "norm").pvalue > 1e-3
