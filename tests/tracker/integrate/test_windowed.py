"""Integrals and TT decisions on a prior read window by window (a prior larger than memory) equal those on
the same file read into memory.

Oracles: the in-memory read of the same GeoTIFF (``windowed=False``) through the same integrators, bit for
bit (the windowed path reads the same cells from windows); and the dense reference integration."""

from __future__ import annotations

import numpy as np
import pytest

from bench import bench_terrace
from pipeline.prior import TerrainPrior
from tests.tracker.integrate.test_terraces import GRID, ROUGH
from tracker.association.greedy import Tracker
from tracker.integrate import cell_integrals, integrate, lazy, reference_integrate, scalespace
from tracker.integrate.terraces import pixel_gaussians
from tracker.integrate.tiny import FEW, TINY, few_cell_integrals, tiny_integrals
from tracker.types.reports import Reports


@pytest.fixture(scope="module")
def priors(tmp_path_factory) -> tuple[TerrainPrior, TerrainPrior]:
    path = ROUGH.write(tmp_path_factory.mktemp("rough") / "prior.tif")
    return TerrainPrior.read(path, windowed=False), TerrainPrior.read(path, windowed=True)


def gaussians(n: int, seed: int, lo: float, hi: float, margin: float = 3.0):
    """``n`` Gaussians (metres) with major σ log-uniform in [lo, hi] cells, eccentricity up to 4, any
    angle (bench_terrace's), centres over the grid and ``margin`` cells beyond it."""
    rng = np.random.default_rng(seed)
    _, covs = bench_terrace.gaussians(GRID, n, np.exp(rng.uniform(np.log(lo), np.log(hi), n)), rng, max_ecc=4.0)
    x0, y0, x1, y1 = GRID.bounds
    pad = margin * GRID.dx
    return np.column_stack([rng.uniform(x0 - pad, x1 + pad, n), rng.uniform(y0 - pad, y1 + pad, n)]), covs


@pytest.mark.parametrize("squared", [False, True])
@pytest.mark.parametrize(("lo", "hi"), [(0.005, TINY), (0.2, FEW)])
def test_per_cell_integrals_read_windows_and_equal_the_in_memory_ones(priors, squared, lo, hi) -> None:
    """Tiny (closed form) and few-cell (exact per cell) Gaussians, on and off the grid: the windows read
    hold every cell their Gaussians touch, so the sums are the same numbers."""
    mem, win = priors
    means, covs = gaussians(3000, seed=int(hi * 100), lo=lo, hi=hi)
    want = integrate(mem, means, covs, squared)
    got = integrate(win, means, covs, squared)
    np.testing.assert_array_equal(got, want)
    assert (want > 0).mean() > 0.5


@pytest.mark.parametrize("squared", [False, True])
@pytest.mark.parametrize(("kernel", "hi"), [(tiny_integrals, TINY), (few_cell_integrals, FEW)])
def test_each_kernel_on_windows_equals_it_on_the_whole_field(priors, kernel, hi, squared) -> None:
    mem, win = priors
    px = pixel_gaussians(mem, *gaussians(3000, seed=9, lo=0.2 * hi, hi=hi, margin=40.0))
    want = cell_integrals(mem, kernel, squared, *px)
    np.testing.assert_array_equal(cell_integrals(win, kernel, squared, *px), want)
    assert (want > 0).mean() > 0.2 and (want == 0).any()  # some Gaussians lie wholly off the grid


def test_the_lazy_pyramid_on_a_windowed_prior(priors, monkeypatch) -> None:
    """Above MAX_CELLS both reads take the lazy pyramid: the same integrals bit for bit, from the same
    cells read from the file window by window, Gaussians finer than the pyramid included (smoothed from
    windows around them instead of the in-memory field)."""
    mem, win = priors
    monkeypatch.setattr(scalespace, "MAX_CELLS", GRID.height * GRID.width - 1)
    means, covs = gaussians(3000, seed=5, lo=0.2, hi=40.0)
    minor = np.sqrt(np.linalg.eigvalsh(covs)[:, 0]) / GRID.dx
    assert (minor < scalespace.S0).sum() > 500 and (minor > 2 * scalespace.S0).sum() > 500
    for squared in (False, True):
        np.testing.assert_array_equal(integrate(win, means, covs, squared), integrate(mem, means, covs, squared))
    assert lazy.lazy_pyramid(win, False).tiles_built > 0 and lazy.lazy_pyramid(win, False).field is None
    assert lazy.lazy_pyramid(mem, False).field is not None
    want = reference_integrate(win, means[:200], covs[:200])  # and both are the integrals
    np.testing.assert_allclose(integrate(win, means[:200], covs[:200]), want, rtol=2e-3, atol=1e-6 * want.max())


def test_tt_decides_alike_on_both_reads(priors, monkeypatch) -> None:
    """The tracker knows the prior only through its integrals and max density: TT on the windowed read
    (lazy pyramid, per-cell windows) makes the in-memory read's decisions, report by report."""
    mem, win = priors
    monkeypatch.setattr(scalespace, "MAX_CELLS", GRID.height * GRID.width - 1)
    rng = np.random.default_rng(2)
    x0, y0, x1, y1 = GRID.bounds
    targets = np.column_stack([rng.uniform(x0, x1, 60), rng.uniform(y0, y1, 60)])
    truth = rng.integers(0, 60, 400)
    _, covs = gaussians(400, seed=7, lo=1.5, hi=6.0)
    noise = np.einsum("kij,kj->ki", np.linalg.cholesky(covs), rng.standard_normal((400, 2)))
    reports = Reports.create(targets[truth] + noise, covs, np.arange(400.0), truth)
    got = [Tracker(p, "TT", tau=-1.7, off_prior="skip").update(reports) for p in (mem, win)]
    np.testing.assert_array_equal(got[1], got[0])
    assert len(np.unique(got[0])) > 30
    assert win.max_density == mem.max_density
