"""The scale-space integrator's parts against closed forms and direct sums.

Oracles: f_s = r ⊛ G_s summed directly over cells with scipy's normal CDF; E[Φ(ρξ - c)] =
Φ(-c/√(1+ρ²)) for the quadrature rules; products of normal CDFs for axis-aligned Gaussians; the
dense reference (tracker.integrate.reference) for the hand-over to the terraces.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import correlate1d, spline_filter
from scipy.special import ndtr

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tests.tracker.integrate.test_terraces import (
    CELL,
    GRID,
    ROUGH,
    H,
    W,
    gaussian,
    random_gaussians,
    rough_field,
    thin_gaussians,
)
from tracker.integrate import integrate, scalespace
from tracker.integrate.reference import reference_integrate
from tracker.integrate.terraces import pixel_gaussians


def smoothed(values: np.ndarray, u: np.ndarray, v: np.ndarray, s: float) -> np.ndarray:
    """f_s at points (u, v) by the direct sum Σ_cells value · ΔΦ_u · ΔΦ_v over the whole grid."""
    wu = np.diff(ndtr((np.arange(values.shape[1] + 1)[None, :] - u[:, None]) / s), axis=1)
    wv = np.diff(ndtr((np.arange(values.shape[0] + 1)[None, :] - v[:, None]) / s), axis=1)
    return np.einsum("nj,ji,ni->n", wv, values, wu)


def spline_at(p: scalespace.Packed, k: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    args = (p.coef, p.offset[k], p.nu[k], p.nv[k], p.u0[k], p.v0[k], p.step[k])
    return np.array([scalespace._bspline(*args, a, b) for a, b in zip(u, v, strict=True)])


def test_every_level_matches_the_direct_smoothing() -> None:
    """Level 0 is exact on cells, the others come by recursion; all agree with the direct sum."""
    field = rough_field(seed=3, shape=(40, 56))
    pyr = scalespace.Pyramid(field)
    pyr.levels(4.0)  # grown in two calls: the second starts from the first's top level
    p = pyr.levels(60.0)
    assert p.scale[-1] >= 60.0 and np.allclose(np.diff(np.log(p.scale)), np.log(scalespace.RATIO))
    rng = np.random.default_rng(0)
    for k in range(p.scale.size):
        s = p.scale[k]
        u = rng.uniform(-3 * s, 56 + 3 * s, 60)
        v = rng.uniform(-3 * s, 40 + 3 * s, 60)
        exact = smoothed(field, u, v, s)
        # cubic B-spline on a lattice of s/2: ~1e-4 of the field's jumps, which reach its maximum
        assert np.abs(spline_at(p, k, u, v) - exact).max() <= 3e-4 * field.max(), f"level {k}, s = {s:.2f}"


def test_levels_are_added_on_demand_and_kept() -> None:
    prior = TerrainPrior.from_array(rough_field(seed=5), GRID)
    pyr = scalespace.pyramid(prior, squared=False)
    assert pyr is scalespace.pyramid(prior, squared=False)
    assert pyr is not scalespace.pyramid(prior, squared=True)
    small = pyr.levels(5.0)
    assert pyr.levels(2.0) is small  # nothing to add: the same snapshot
    big = pyr.levels(50.0)
    assert big.scale.size > small.scale.size
    np.testing.assert_array_equal(big.coef[: small.coef.size], small.coef)


def test_levels_do_not_depend_on_how_the_pyramid_grew() -> None:
    field = rough_field(seed=4, shape=(30, 41))
    once = scalespace.Pyramid(field).levels(40.0)
    grown = scalespace.Pyramid(field)
    for top in (1.0, 3.0, 9.0, 40.0):
        stepwise = grown.levels(top)
    np.testing.assert_array_equal(stepwise.coef, once.coef)
    np.testing.assert_array_equal(stepwise.offset, once.offset)


@pytest.mark.parametrize("shape", [(1, 1), (31, 33), (64, 65), (70, 5)])
def test_blocks_round_trip(shape) -> None:
    coef = np.random.default_rng(1).normal(size=shape).astype(np.float32)
    flat = scalespace._tile(coef)
    assert flat.size == -(-shape[0] // scalespace.TILE) * -(-shape[1] // scalespace.TILE) * (scalespace.TILE + 3) ** 2
    np.testing.assert_array_equal(scalespace._untile(flat, shape), coef)


def test_prefilter_and_node_values_match_scipy() -> None:
    """The finite B-spline prefilter against the truncated filter's formula (a zero-padded 2-D
    convolution) and, away from the ends, against scipy.ndimage's exact one; node values against scipy."""
    x = np.random.default_rng(2).normal(size=(67, 82))
    m = np.arange(-scalespace.FIR, scalespace.FIR + 1)
    taps = np.sqrt(3.0) * (np.sqrt(3.0) - 2.0) ** np.abs(m)
    direct = correlate1d(correlate1d(x, taps, 0, mode="constant"), taps, 1, mode="constant")
    got = scalespace._prefilter(x)
    np.testing.assert_allclose(got, direct, rtol=1e-6, atol=1e-6)
    inner = (slice(20, -20), slice(20, -20))  # 20 nodes from the ends: their effect is |z|^20 = 4e-12
    np.testing.assert_allclose(got[inner], spline_filter(x, order=3, mode="mirror")[inner], atol=2e-6)
    c = spline_filter(x, order=3, mode="mirror").astype(np.float32)  # coefficients are stored as float32
    k = np.array([1.0, 4.0, 1.0]) / 6.0
    np.testing.assert_allclose(scalespace._node_values(c), correlate1d(correlate1d(c.astype(np.float64), k, 0, mode="mirror"), k, 1, mode="mirror"), atol=1e-12)


def _dense(start: np.ndarray, weights: np.ndarray, n_src: int) -> np.ndarray:
    """Banded (start, weights) as a dense (nodes, n_src) matrix."""
    out = np.zeros((start.size, n_src))
    for j, (a, w) in enumerate(zip(start.tolist(), weights, strict=True)):
        out[j, a : a + w.size] += w
    return out


@settings(max_examples=40, deadline=None)
@given(k=st.integers(0, scalespace.FUSED_LEVELS - 1), n_cells=st.integers(1, 90), lo=st.floats(0, 1), span=st.floats(0, 1))
def test_fused_weights_are_the_prefilter_times_the_cell_masses(k, n_cells, lo, span) -> None:
    """Cells straight to coefficients: the banded fused weights of any run of nodes equal the dense
    product (prefilter matrix) @ (cell-mass matrix) of the two passes they replace, on axes shorter
    and longer than the bands."""
    s, h, origin, n_nodes, _ = scalespace.lattice(k, (n_cells, n_cells))
    first = int(lo * (n_nodes - 1))
    last = min(first + 1 + int(span * n_nodes), n_nodes)
    fs, fw = scalespace._fir_weights(first, last, n_nodes)
    bs, bw = scalespace._box_weights(origin + h * np.arange(n_nodes), n_cells, s)
    expected = _dense(fs, fw, n_nodes) @ _dense(bs, bw, n_cells)
    start, weights = scalespace._fused_weights(first, last, n_nodes, origin, h, s, n_cells)
    assert weights.shape[1] <= n_cells and start.min() >= 0 and (start + weights.shape[1]).max() <= n_cells
    np.testing.assert_allclose(_dense(start, weights, n_cells), expected, rtol=0, atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 70), w=st.integers(1, 70), bu=st.integers(1, 9), bv=st.integers(1, 9), nu=st.integers(1, 60),
       nv=st.integers(1, 60), seed=st.integers(0, 2**16))
def test_separable_is_the_dense_double_sum(h, w, bu, bv, nu, nv, seed) -> None:
    """The banded two-pass kernel against Wv @ values @ Wu.T with the bands as dense matrices, on any
    shapes (bands as wide as the axis, one node, more nodes than cells)."""
    rng = np.random.default_rng(seed)
    bu, bv = min(bu, w), min(bv, h)
    values = rng.normal(size=(h, w))
    su, sv = rng.integers(0, w - bu + 1, nu), rng.integers(0, h - bv + 1, nv)
    wu, wv = rng.normal(size=(nu, bu)), rng.normal(size=(nv, bv))
    got = scalespace._separable(values, su, wu, sv, wv)
    want = _dense(sv, wv, h) @ values @ _dense(su, wu, w).T
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(values).sum())


@settings(max_examples=30, deadline=None)
@given(k=st.integers(0, scalespace.FUSED_LEVELS - 1), n_cells=st.integers(1, 400), lo=st.floats(0, 1), span=st.floats(0, 1))
def test_fold_taps_is_the_numpy_formula_bit_for_bit(k, n_cells, lo, span) -> None:
    """The numba loop of the fused weights against the same sum in numpy (one fancy-indexed add per
    tap, in order): equal to the last bit, so the lazy and whole pyramids agree whichever builds them."""
    s, h, origin, n_nodes, _ = scalespace.lattice(k, (n_cells, n_cells))
    first = int(lo * (n_nodes - 1))
    last = min(first + 1 + int(span * n_nodes), n_nodes)
    fs, fw = scalespace._fir_weights(first, last, n_nodes)
    src0 = int(fs[0])
    bs, bw = scalespace._box_weights(origin + h * np.arange(src0, int(fs[-1]) + fw.shape[1]), n_cells, s)
    start, weights = scalespace._fused_weights(first, last, n_nodes, origin, h, s, n_cells)
    expected = np.zeros_like(weights)
    rows = np.arange(fs.size)[:, None]
    for t in range(fw.shape[1]):
        m = fs - src0 + t
        expected[rows, (bs[m] - start)[:, None] + np.arange(bw.shape[1])] += fw[:, t, None] * bw[m]
    np.testing.assert_array_equal(weights, expected)


def test_fused_levels_equal_the_two_pass_coefficients_to_float32_rounding() -> None:
    """Levels below FUSED_LEVELS of a rough field: the one-pass coefficients against the cell sums
    prefiltered (the two passes every other cell level takes), over the whole lattice and on a window."""
    field = rough_field(seed=3)
    for k in range(scalespace.FUSED_LEVELS):
        s, h, origin, nu, nv = scalespace.lattice(k, field.shape)
        two = scalespace._prefilter(scalespace._exact_level(field, origin + h * np.arange(nu), origin + h * np.arange(nv), s))
        cells = lambda r0, r1, c0, c1: field[r0:r1, c0:c1]  # noqa: E731
        got = scalespace.fused_coefficients(cells, k, field.shape, (0, nv), (0, nu))
        np.testing.assert_allclose(got, two, rtol=0, atol=2e-7 * np.abs(two).max())
        part = scalespace.fused_coefficients(cells, k, field.shape, (5, nv // 2), (nu // 3, nu - 4))
        np.testing.assert_array_equal(part, got[5 : nv // 2, nu // 3 : nu - 4])


def test_threads_sharing_a_prior_get_the_same_integrals() -> None:
    """Eight threads asking one new prior for different spreads at once (levels built concurrently)."""
    prior = TerrainPrior.from_array(rough_field(seed=6), GRID)
    means, covs = random_gaussians(GRID, 64, seed=9)
    with ThreadPoolExecutor(8) as pool:
        parts = list(pool.map(lambda i: integrate(prior, means[i::8], covs[i::8]), range(8)))
    alone = integrate(TerrainPrior.from_array(rough_field(seed=6), GRID), means, covs)
    for i in range(8):
        np.testing.assert_array_equal(parts[i], alone[i::8])


@settings(max_examples=20, deadline=None)
@given(
    shape=st.tuples(st.integers(1, 6), st.integers(1, 6)),
    sigma=st.floats(np.log(0.5), np.log(50.0)).map(np.exp),
    ecc=st.floats(1.0, 5.0),
    angle=st.floats(0.0, np.pi),
    fu=st.floats(0.0, 1.0),
    fv=st.floats(0.0, 1.0),
)
def test_tiny_grids_match_the_reference(shape, sigma, ecc, angle, fu, fv) -> None:
    grid = Grid("EPSG:32734", Affine(CELL, 0.0, 300_000.0, 0.0, -CELL, 6_200_000.0), *shape)
    prior = TerrainPrior.from_array(rough_field(seed=1, shape=shape) + 0.1, grid)
    mean, cov = gaussian(grid, sigma, ecc, angle, fu, fv)
    ref = reference_integrate(prior, mean[None], cov[None])[0]
    assert integrate(prior, mean[None], cov[None])[0] == pytest.approx(ref, rel=0.01)


@pytest.mark.parametrize("rho", [0.0, 0.01, 0.2, 0.5, 0.64, 1.0, 1.59, 1.61, 3.0, 10.0, 60.0])
def test_rules_average_smoothed_steps(rho: float) -> None:
    """E[Φ(ρξ - c)], ξ ~ N(0,1): the step smoothed at the level's σ, every offset c."""
    xs, ws = np.empty(scalespace.MAX_POINTS), np.empty(scalespace.MAX_POINTS)
    n = scalespace._rule(rho, xs, ws)
    assert n >= 1
    c = np.linspace(-12.0, 12.0, 1201)
    est = ndtr(xs[:n][None, :] - c[:, None]) @ ws[:n]
    assert np.abs(est - ndtr(-c / np.sqrt(1.0 + rho * rho))).max() <= 2 * scalespace.TOL
    assert ws[:n].sum() == pytest.approx(1.0, abs=1e-12)


def test_rules_give_up_beyond_their_size() -> None:
    xs, ws = np.empty(64), np.empty(64)
    assert scalespace._rule(100.0, xs, ws) == 0


@settings(max_examples=30, deadline=None)
@given(
    su=st.floats(np.log(0.05), np.log(0.99)).map(np.exp),
    ratio=st.floats(1.0, 30.0),
    uc=st.floats(-2.0, W + 2.0),
    vc=st.floats(-2.0, H + 2.0),
    transpose=st.booleans(),
)
def test_sub_cell_gaussians_match_the_closed_form(su, ratio, uc, vc, transpose) -> None:
    """Smaller σ under one cell (exact smoothing on the fly): axis-aligned, ΔΦ_vᵀ r ΔΦ_u exactly."""
    sv = su * ratio
    if transpose:
        su, sv = sv, su
    exact = float(np.diff(ndtr((np.arange(H + 1) - vc) / sv)) @ ROUGH.density @ np.diff(ndtr((np.arange(W + 1) - uc) / su)))
    if exact < 1e-3 * ROUGH.density.mean():
        return  # on the lake or off the grid: nothing to compare relatively
    got, counts = scalespace.integrate_pixels(ROUGH, *(np.array([x]) for x in (uc, vc, su * su, 0.0, sv * sv)), False)
    assert counts[0] > 0
    assert got[0] == pytest.approx(exact, rel=2e-3)


def test_cost_is_the_same_at_every_spread() -> None:
    """The same shape at spreads from 2 to ~10,000 cells costs the same number of look-ups."""
    scale = np.array([1.3 * scalespace.S0 * scalespace.RATIO**k for k in range(0, 52, 4)])
    angle = 0.6
    c, s = np.cos(angle), np.sin(angle)
    major, minor = 2.2 * scale, scale
    cuu = c * c * major**2 + s * s * minor**2
    cvv = s * s * major**2 + c * c * minor**2
    cuv = c * s * (major**2 - minor**2)
    n = scale.size
    _, counts = scalespace.integrate_pixels(ROUGH, np.full(n, W / 2), np.full(n, H / 2), cuu, cuv, cvv, False)
    assert np.all(counts == counts[0]) and counts[0] > 0


def test_needle_gaussians_are_handed_to_the_terraces() -> None:
    """2,000:1 needs more points than the rules have: the terraces integrate it, still to 1 %."""
    cov = np.diag([(400.0 * CELL) ** 2, (0.2 * CELL) ** 2])
    angle = 0.3
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    cov = rot @ cov @ rot.T
    cov = 0.5 * (cov + cov.T)
    mean = np.array([GRID.transform.c + 0.4 * W * CELL, GRID.transform.f - 0.6 * H * CELL])
    assert scalespace.integrate_pixels(ROUGH, *(np.atleast_1d(a) for a in pixel_gaussians(ROUGH, mean[None], cov[None])), False)[1][0] == 0
    ref = reference_integrate(ROUGH, mean[None], cov[None])[0]
    assert integrate(ROUGH, mean[None], cov[None])[0] == pytest.approx(ref, rel=0.01)


def test_small_batches_equal_the_general_path() -> None:
    """:func:`scalespace.integrate_small` (batches under SMALL_BATCH) gives the general path's values bit
    for bit, and leaves every batch with a Gaussian it does not take (tiny, off the grid, a needle, a level
    not built yet) to the general path."""
    prior = TerrainPrior.from_array(rough_field(seed=4), GRID)
    means, covs = random_gaussians(GRID, 300, seed=5, max_sigma=30.0)
    centre, thin = thin_gaussians(200, seed=6)  # smaller σ under one cell, as most tracker reports
    means, covs = np.concatenate([means, centre]), np.concatenate([covs, thin])
    assert scalespace.integrate_small(prior, means[:5], covs[:5], False, 0.5, 4.0) is None  # no level built yet
    for squared in (False, True):
        whole = integrate(prior, means, covs, squared)  # >= SMALL_BATCH: the general path (builds the levels)
        taken = 0
        for i in range(0, means.shape[0], 7):
            part = scalespace.integrate_small(prior, means[i : i + 7], covs[i : i + 7], squared, 0.5, 4.0)
            if part is not None:
                taken += 1
                np.testing.assert_array_equal(part, whole[i : i + 7])
            np.testing.assert_array_equal(integrate(prior, means[i : i + 7], covs[i : i + 7], squared), whole[i : i + 7])
        assert taken >= 20  # the thin ones, seven at a time
    tiny = np.diag([(0.01 * CELL) ** 2, (0.02 * CELL) ** 2])[None]
    off = means[-1:] + np.array([[-10 * W * CELL, 0.0]])
    needle = np.diag([(400.0 * CELL) ** 2, (0.2 * CELL) ** 2])[None]
    wide = np.diag([(200.0 * CELL) ** 2, (150.0 * CELL) ** 2])[None]  # above the levels built so far
    for m, cv in ((means[-1:], tiny), (off, covs[-1:]), (means[-1:], needle), (means[-1:], wide)):
        assert scalespace.integrate_small(prior, np.concatenate([means[-3:], m]), np.concatenate([covs[-3:], cv]), False, 0.5, 4.0) is None
