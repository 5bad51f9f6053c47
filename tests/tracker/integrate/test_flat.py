"""The flat-prior shortcut (tracker.integrate.flat) against the closed form of axis-aligned Gaussians:
∫ G r = Σ_cells r_c ΔΦ_u ΔΦ_v on a piecewise-constant prior."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import ndtr

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.integrate.flat import TILE, FlatIntegrator, tiles
from tracker.integrate.terraces import pixel_gaussians

CELL = 20.0


def field() -> np.ndarray:
    """Flat plateaus (1, 3, nearly 2) with a ramp, a noisy strip and a structural zero."""
    r = np.ones((120, 160))
    r[:, 80:] = 3.0
    r[60:, :40] = 2.0 + 1e-7 * np.random.default_rng(0).random((60, 40))
    r[:20, 100:140] = np.linspace(1.0, 2.0, 40)[None, :]
    r[100:, 60:100] = np.random.default_rng(1).uniform(0.5, 1.5, (20, 40))
    r[30:40, 20:30] = 0.0
    return r


@pytest.fixture(scope="module")
def prior() -> TerrainPrior:
    return TerrainPrior.from_array(field(), Grid.from_bounds((0.0, 0.0, 160 * CELL, 120 * CELL), CELL, "EPSG:32634"))


def closed_form(prior: TerrainPrior, means: np.ndarray, sd: np.ndarray, squared: bool) -> np.ndarray:
    """∫ G r (or r²) per m² for axis-aligned Gaussians, summed over every cell (the prior is 0 off the grid)."""
    r = np.asarray(prior.density, dtype=np.float64)
    r = r * r if squared else r
    uc, vc, cuu, _, cvv = pixel_gaussians(prior, means, np.stack([np.diag(s**2) for s in sd]))
    wu = np.diff(ndtr((np.arange(r.shape[1] + 1)[None, :] - uc[:, None]) / np.sqrt(cuu)[:, None]), axis=1)
    wv = np.diff(ndtr((np.arange(r.shape[0] + 1)[None, :] - vc[:, None]) / np.sqrt(cvv)[:, None]), axis=1)
    return np.einsum("nr,rc,nc->n", wv, r, wu)


def test_tiles_bound_their_cells(prior):
    tb = tiles(prior)
    r = np.asarray(prior.density, dtype=np.float64)
    for (i, j) in [(0, 0), (7, 12), (14, 19), (3, 8)]:
        cells = r[i * TILE : (i + 1) * TILE, j * TILE : (j + 1) * TILE]
        assert tb.lo[i, j] == cells.min() and tb.hi[i, j] == cells.max()
    assert tb.r_max == r.max()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), squared=st.booleans(), tol=st.sampled_from([1e-6, 1e-4, 1e-2]))
def test_flat_values_within_tol_of_the_closed_form(prior, seed, squared, tol):
    rng = np.random.default_rng(seed)
    n = 400
    means = rng.uniform([-100.0, -100.0], [160 * CELL + 100, 120 * CELL + 100], (n, 2))
    sd = rng.uniform(2.0, 150.0, (n, 2))
    covs = np.stack([np.diag(s**2) for s in sd])
    exact = closed_form(prior, means, sd, squared)
    fi = FlatIntegrator(tol, exact=lambda p, m, c, sq: closed_form(p, m, np.sqrt(np.stack([np.diag(x) for x in c])), sq))
    got = fi(prior, means, covs, squared)
    np.testing.assert_allclose(got, exact, rtol=tol, atol=0.0)
    assert fi.n_flat + fi.n_exact == n


def test_flat_only_where_the_prior_is_flat(prior):
    # Centres on the plateaus are flat; on the ramp, the noisy strip, the zero or off the grid they are not.
    fi = FlatIntegrator(1e-4)
    x = np.array([30.0, 120.0, 20.0, 120.0, 80.0, 25.0, -50.0]) * CELL
    y_row = np.array([10.0, 60.0, 90.0, 10.0, 110.0, 35.0, 60.0])
    y = (120.0 - y_row) * CELL
    covs = np.tile(np.diag([25.0, 25.0]), (x.size, 1, 1))
    before = fi.n_flat
    got = fi(prior, np.stack([x, y], 1), covs)
    assert fi.n_flat - before == 3
    np.testing.assert_allclose(got[:3], [1.0 / prior_scale(prior), 3.0 / prior_scale(prior), 2.0 / prior_scale(prior)], rtol=1e-4)


def prior_scale(prior: TerrainPrior) -> float:
    """Raw field value per unit of the prior's normalised density."""
    return float(field()[0, 0] / np.asarray(prior.density, dtype=np.float64)[0, 0])


def test_bad_tol():
    with pytest.raises(ValueError, match="tol"):
        FlatIntegrator(0.0)
