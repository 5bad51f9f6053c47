"""Metrics against independent oracles: brute-force GOSPA/OSPA over all assignments, purity by counting,
and the paper's Score (eq. 18) against dense numerical integration of the squared mixture difference."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest
from affine import Affine
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.integrate.reference import reference_integrate
from tracker.study.metrics import ScoreGram, gospa, ospa, purity, score


def _injections(n_from: int, n_to: int):
    """Every partial injective map {0..n_from-1} -> {0..n_to-1} ∪ {None}."""
    for image in itertools.product([None, *range(n_to)], repeat=n_from):
        used = [j for j in image if j is not None]
        if len(used) == len(set(used)):
            yield image


def _gospa_brute(x: np.ndarray, y: np.ndarray, c: float, p: float) -> float:
    best = np.inf
    for image in _injections(len(x), len(y)):
        pairs = [(i, j) for i, j in enumerate(image) if j is not None]
        cost = sum(np.linalg.norm(x[i] - y[j]) ** p for i, j in pairs)
        cost += c**p / 2 * (len(x) + len(y) - 2 * len(pairs))
        best = min(best, cost)
    return best ** (1 / p)


def _ospa_brute(x: np.ndarray, y: np.ndarray, c: float, p: float) -> float:
    if len(x) > len(y):
        x, y = y, x
    m, n = len(x), len(y)
    if n == 0:
        return 0.0
    best = min(
        sum(min(np.linalg.norm(x[i] - y[j]), c) ** p for i, j in enumerate(perm))
        for perm in itertools.permutations(range(n), m)
    )
    return ((best + c**p * (n - m)) / n) ** (1 / p)


points = st.integers(0, 4).flatmap(
    lambda n: st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=n, max_size=n)
)


@settings(max_examples=60, deadline=None)
@given(points, points, st.floats(1.0, 80.0), st.sampled_from([1.0, 2.0, 3.0]))
def test_gospa_and_ospa_match_brute_force(xs, ys, c, p) -> None:
    x = np.array(xs, dtype=float).reshape(-1, 2)
    y = np.array(ys, dtype=float).reshape(-1, 2)
    g = gospa(x, y, c, p)
    assert g["gospa"] == pytest.approx(_gospa_brute(x, y, c, p), rel=1e-9, abs=1e-9)
    assert g["localisation"] + c**p / 2 * (g["missed"] + g["false"]) == pytest.approx(g["gospa"] ** p, rel=1e-9, abs=1e-9)
    assert g["missed"] - g["false"] == len(y) - len(x)
    assert ospa(x, y, c, p) == pytest.approx(_ospa_brute(x, y, c, p), rel=1e-9, abs=1e-9)


def test_gospa_ospa_simple_cases() -> None:
    x = np.array([[0.0, 0.0], [10.0, 0.0]])
    assert gospa(x, x, 5.0)["gospa"] == 0.0
    assert ospa(x, x, 5.0) == 0.0
    # One missed target far from everything: GOSPA² = c²/2, OSPA = c·sqrt(1/3).
    y = np.vstack([x, [[100.0, 100.0]]])
    assert gospa(x, y, 5.0)["gospa"] == pytest.approx(np.sqrt(12.5))
    assert ospa(x, y, 5.0) == pytest.approx(5.0 * np.sqrt(1 / 3))
    assert ospa(np.empty((0, 2)), np.empty((0, 2)), 5.0) == 0.0
    with pytest.raises(ValueError, match="c > 0"):
        gospa(x, y, 0.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 5)), min_size=1, max_size=40))
def test_purity_matches_counting(pairs) -> None:
    assign = np.array([a for a, _ in pairs])
    truth = np.array([t for _, t in pairs])
    expected = sum(max(Counter(t for a2, t in pairs if a2 == a).values()) for a in set(assign)) / len(pairs)
    assert purity(assign, truth) == pytest.approx(expected)


def test_purity_bounds_and_errors() -> None:
    assert purity(np.array([0, 0, 1, 1]), np.array([5, 5, 7, 7])) == 1.0
    assert purity(np.array([0, 0, 0, 0]), np.array([1, 2, 3, 4])) == 0.25
    with pytest.raises(ValueError, match="equal-length"):
        purity(np.array([0, 1]), np.array([0]))


# --- the paper's Score (eq. 18) against dense numerical integration ------------------------------

CELL = 20.0


def _score_prior() -> TerrainPrior:
    rng = np.random.default_rng(21)
    r = 0.2 + rng.random((60, 60)) ** 2
    r[20:26, :] = 0.0  # a structural-zero band (a river)
    r[:, 40:44] *= 6.0  # a bright ridge (a road side)
    grid = Grid("EPSG:32633", Affine(CELL, 0.0, 400000.0, 0.0, -CELL, 5001200.0), 60, 60)
    return TerrainPrior.from_array(r, grid)


def _gaussians(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    means = np.column_stack([400000.0 + rng.uniform(350, 850, n), 5000000.0 + rng.uniform(350, 850, n)])
    sd = rng.uniform(25.0, 70.0, size=(n, 2))
    rot = rng.uniform(0, np.pi, n)
    R = np.stack([np.stack([np.cos(rot), -np.sin(rot)], 1), np.stack([np.sin(rot), np.cos(rot)], 1)], 1)
    covs = R @ (sd[:, :, None] * np.eye(2) * sd[:, None, :]) @ R.transpose(0, 2, 1)
    return means, covs


def _dense_mixture_l2(prior, est, est_terrain, ref, ref_terrain, h: float = 2.0) -> float:
    """sqrt ∫ (E − P)² dx by the midpoint rule on an h-metre lattice reaching 600 m beyond the grid
    (plain Gaussians live on all of space); terrain normalisers summed on the same lattice."""
    xmin, ymin, xmax, ymax = prior.grid.bounds
    xs = np.arange(xmin - 600 + h / 2, xmax + 600, h)
    ys = np.arange(ymin - 600 + h / 2, ymax + 600, h)
    X, Y = np.meshgrid(xs, ys)
    r = prior.density_at(X.ravel(), Y.ravel())
    pts = np.column_stack([X.ravel(), Y.ravel()])

    def mixture(gauss, terrain, sign):
        means, covs = gauss
        out = np.zeros(pts.shape[0])
        for a, A in zip(means, covs, strict=True):
            d = pts - a
            q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(A), d)
            g = np.exp(-0.5 * q) / (2 * np.pi * np.sqrt(np.linalg.det(A)))
            f = g * r / (np.sum(g * r) * h * h) if terrain else g
            out += sign * f / len(means)
        return out

    diff = mixture(est, est_terrain, 1.0) + mixture(ref, ref_terrain, -1.0)
    return float(np.sqrt(np.sum(diff**2) * h * h))


@pytest.mark.parametrize("est_terrain", [True, False])
def test_score_matches_dense_integration(est_terrain: bool) -> None:
    prior = _score_prior()
    rng = np.random.default_rng(22)
    est = _gaussians(rng, 4)
    ref = _gaussians(rng, 3)
    expected = _dense_mixture_l2(prior, est, est_terrain, ref, True)
    # The Gram algebra with an accurate integrator...
    exact = score(prior, *est, est_terrain, *ref, True, integrator=reference_integrate)
    assert exact == pytest.approx(expected, rel=2e-3)
    # ...and with the terrace integration the tracker uses.
    assert score(prior, *est, est_terrain, *ref, True) == pytest.approx(expected, rel=3e-2)


def test_score_is_zero_for_identical_mixtures_and_symmetric() -> None:
    prior = _score_prior()
    rng = np.random.default_rng(23)
    a, b = _gaussians(rng, 3), _gaussians(rng, 2)
    assert score(prior, *a, True, *a, True) == 0.0
    # Swapping the mixtures reorders the Gaussian products' rounding; Score² cancels large terms.
    assert score(prior, *a, True, *b, True) == pytest.approx(score(prior, *b, True, *a, True), rel=1e-9)
    assert score(prior, *a, False, *b, True) > 0


def test_score_gram_skips_only_negligible_pairs() -> None:
    prior = _score_prior()
    means = np.array([[400300.0, 5000300.0], [400900.0, 5000900.0], [400310.0, 5000290.0]])
    covs = np.tile(np.eye(2) * 20.0**2, (3, 1, 1))
    gram = ScoreGram(prior, means, covs, np.ones(3, bool), integrator=reference_integrate)
    assert gram.K[0, 1] == 0.0 and gram.skipped_bound[0, 1] > 0  # 850 m apart at σ = 20 m
    assert gram.K[0, 2] > 0 and gram.skipped_bound[0, 2] == 0
    w = np.array([1.0, -1.0, 0.5])
    s, err = gram.score(w)
    assert err < 1e-9 * s**2


def test_score_gram_needed_pairs() -> None:
    prior = _score_prior()
    rng = np.random.default_rng(24)
    means, covs = _gaussians(rng, 4)
    needed = np.zeros((4, 4), bool)
    needed[np.ix_([0, 1], [0, 1])] = True
    needed[np.ix_([2, 3], [2, 3])] = True
    full = ScoreGram(prior, means, covs, np.ones(4, bool), integrator=reference_integrate)
    part = ScoreGram(prior, means, covs, np.ones(4, bool), integrator=reference_integrate, needed=needed)
    w = np.array([0.5, -0.5, 0.0, 0.0])
    assert part.score(w)[0] == pytest.approx(full.score(w)[0], rel=1e-12)
    with pytest.raises(ValueError, match="outside `needed`"):
        part.score(np.array([0.5, 0.0, -0.5, 0.0]))


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 10_000), st.booleans())
def test_score_is_a_metric_on_mixtures(seed: int, uniform_middle: bool) -> None:
    """Score is the L2 distance between mixture densities: symmetric, zero on itself, triangle inequality."""
    prior = _score_prior()
    rng = np.random.default_rng(seed)
    a, b, c = _gaussians(rng, 2), _gaussians(rng, 3), _gaussians(rng, 2)

    def d(x, tx, y, ty):
        return score(prior, *x, tx, *y, ty, integrator=reference_integrate)

    ab, bc, ac = d(a, True, b, not uniform_middle), d(b, not uniform_middle, c, True), d(a, True, c, True)
    assert ac <= ab + bc + 1e-9 * ac
    assert d(b, not uniform_middle, a, True) == pytest.approx(ab, rel=1e-9)


def test_posterior_means_match_dense_integration() -> None:
    """Stein's-identity means against Σ x·G·r / Σ G·r on a 2 m lattice."""
    from tracker.study.metrics import posterior_means

    prior = _score_prior()
    rng = np.random.default_rng(25)
    means, covs = _gaussians(rng, 5)
    got = posterior_means(prior, means, covs)
    xmin, ymin, xmax, ymax = prior.grid.bounds
    xs, ys = np.meshgrid(np.arange(xmin + 1, xmax, 2.0), np.arange(ymin + 1, ymax, 2.0))
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    r = prior.density_at(pts[:, 0], pts[:, 1])
    shifts = []
    for a, A, m in zip(means, covs, got, strict=True):
        d = pts - a
        w = np.exp(-0.5 * np.einsum("ni,ij,nj->n", d, np.linalg.inv(A), d)) * r
        expected = (pts * w[:, None]).sum(axis=0) / w.sum()
        np.testing.assert_allclose(m, expected, atol=1.0)  # metres
        shifts.append(np.abs(expected - a).max())
    assert max(shifts) > 10.0  # the prior moves some means by tens of metres (river band, ridge)
