"""Static gating against an independent dense brute force (hypothesis scenes) and input checks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from tests.tracker.gating.test_oracle import assert_same_pairs, brute_force, random_covs
from tracker.gating.gate import gate, gate_threshold


def _scene(seed, nt, nr, dim, cond, spread):
    rng = np.random.default_rng(seed)
    side = 300.0 * spread
    tm = rng.uniform(0, side, (nt, dim))
    rm = rng.uniform(0, side, (nr, dim))
    tc = random_covs(rng, nt, dim, 3.0, 100.0, cond)
    rc = random_covs(rng, nr, dim, 3.0, 100.0, cond)
    return tm, tc, rm, rc


scenes = dict(
    seed=st.integers(0, 2**31),
    nt=st.integers(0, 30),
    nr=st.integers(0, 30),
    dim=st.sampled_from([2, 3]),
    cond=st.sampled_from([1.0, 10.0, 1e3, 1e6]),
    spread=st.sampled_from([0.3, 1.0, 4.0]),
)


@settings(max_examples=60, deadline=None)
@given(**scenes, gamma=st.floats(0.0, 30.0), orientation=st.sampled_from(["auto", "tracks"]),
       buckets=st.sampled_from(["auto", 1, 3]))
def test_static_threshold_matches_brute_force(seed, nt, nr, dim, cond, spread, gamma,
                                              orientation, buckets):
    tm, tc, rm, rc = _scene(seed, nt, nr, dim, cond, spread)
    t_idx, r_idx, d2 = gate(tm, tc, rm, rc, threshold=gamma, return_d2=True,
                            orientation=orientation, buckets=buckets)
    want_d2, limit = brute_force(tm, tc, rm, rc, gamma=gamma)
    assert_same_pairs(t_idx, r_idx, want_d2, limit)
    np.testing.assert_allclose(d2, want_d2[t_idx, r_idx], rtol=1e-6 * cond, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(**scenes, log_c=st.floats(-30.0, -5.0), orientation=st.sampled_from(["auto", "tracks"]))
def test_static_score_form_matches_brute_force(seed, nt, nr, dim, cond, spread, log_c,
                                               orientation):
    tm, tc, rm, rc = _scene(seed, nt, nr, dim, cond, spread)
    t_idx, r_idx = gate(tm, tc, rm, rc, min_score=float(np.exp(log_c)), orientation=orientation)
    want_d2, limit = brute_force(tm, tc, rm, rc, min_score=float(np.exp(log_c)))
    assert_same_pairs(t_idx, r_idx, want_d2, limit)


@pytest.mark.parametrize("dim", [2, 3])
def test_pairs_on_the_coarse_radius_are_kept(dim):
    """Elongated covariances aligned with dX make d^2 = |dX|^2 / lambda_max: the coarse radius
    is tight, so any missing slack would drop these pairs."""
    rng = np.random.default_rng(3)
    n, gamma = 200, 9.21
    lam_t, lam_r = rng.uniform(1, 1e4, n), rng.uniform(1, 1e4, n)
    tm = rng.uniform(-1e6, 1e6, (n, dim))
    direction = np.eye(dim)[0]
    frac = 1.0 - np.where(np.arange(n) % 2 == 0, 1e-9, -1e-9)  # just inside / just outside
    rm = tm + (np.sqrt(gamma * (lam_t + lam_r)) * frac)[:, None] * direction
    tc = np.tile(np.eye(dim) * 1e-6, (n, 1, 1))
    rc = tc.copy()
    tc[:, 0, 0] = lam_t
    rc[:, 0, 0] = lam_r
    t_idx, r_idx = gate(tm, tc, rm, rc, threshold=gamma)
    own = t_idx == r_idx
    assert np.array_equal(np.sort(t_idx[own]), np.arange(0, n, 2))


def test_single_objects_and_empty_sets():
    tc = np.eye(2)[None] * 4.0
    t, r, d2 = gate(np.zeros((1, 2)), tc, np.array([[2.0, 0.0]]), tc, threshold=1.0,
                    return_d2=True)
    assert t.tolist() == [0] and r.tolist() == [0] and d2[0] == pytest.approx(0.5)
    t, r = gate(np.zeros((1, 2)), tc, np.array([[20.0, 0.0]]), tc, threshold=1.0)
    assert t.size == 0 and r.size == 0
    for nt, nr in ((0, 3), (3, 0), (0, 0)):
        t, r = gate(np.zeros((nt, 3)), np.tile(np.eye(3), (nt, 1, 1)), np.zeros((nr, 3)),
                    np.tile(np.eye(3), (nr, 1, 1)), prob=0.99)
        assert t.size == 0 and r.size == 0 and t.dtype == np.int64


@pytest.mark.parametrize("dim", [1, 2, 3, 4])
def test_gate_threshold_is_chi2_quantile(dim):
    p = 0.95
    g = gate_threshold(p, dim)
    if dim == 2:
        assert g == pytest.approx(-2 * np.log(1 - p))
    # independent check: Monte Carlo fraction of chi^2 draws below gamma
    x = np.random.default_rng(0).standard_normal((200_000, dim))
    assert np.mean((x**2).sum(axis=1) <= g) == pytest.approx(p, abs=3e-3)
    assert g == pytest.approx(chi2.ppf(p, dim))


def _ok():
    c = np.tile(np.eye(2), (3, 1, 1))
    return np.zeros((3, 2)), c, np.ones((4, 2)), np.tile(np.eye(2), (4, 1, 1))


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda a: a[0].__setitem__((1, 0), np.nan), r"track_means.*\[1\]"),
        (lambda a: a[2].__setitem__((3, 1), np.inf), r"report_means.*\[3\]"),
        (lambda a: a[1].__setitem__((2, 0, 0), -1.0), r"track_covs.*\[2\]"),
        (lambda a: a[3].__setitem__((1, 0, 1), 0.5), r"report_covs.*\[1\]"),  # asymmetric
        (lambda a: a[3].__setitem__((0, 1, 1), np.nan), r"report_covs.*\[0\]"),
    ],
)
def test_bad_values_name_argument_and_index(mutate, match):
    args = list(_ok())
    mutate(args)
    with pytest.raises(ValueError, match=match):
        gate(*args, threshold=9.0)


def test_bad_shapes_and_thresholds():
    tm, tc, rm, rc = _ok()
    with pytest.raises(ValueError, match="report_covs"):
        gate(tm, tc, rm, rc[:3], threshold=1.0)
    with pytest.raises(ValueError, match="track_means"):
        gate(np.zeros((3, 5)), tc, rm, rc, threshold=1.0)
    with pytest.raises(ValueError, match="track_covs"):
        gate(tm, np.tile(np.eye(3), (3, 1, 1)), rm, rc, threshold=1.0)
    with pytest.raises(ValueError, match="report_means"):
        gate(tm, tc, np.zeros((4, 4)), np.tile(np.eye(4), (4, 1, 1)), threshold=1.0)
    with pytest.raises(ValueError, match="threshold"):
        gate(tm, tc, rm, rc, threshold=-1.0)
    with pytest.raises(ValueError, match="exactly one"):
        gate(tm, tc, rm, rc, threshold=1.0, prob=0.9)
    with pytest.raises(ValueError, match="exactly one"):
        gate(tm, tc, rm, rc)
    with pytest.raises(ValueError, match="prob"):
        gate(tm, tc, rm, rc, prob=1.0)
    with pytest.raises(ValueError, match="min_score"):
        gate(tm, tc, rm, rc, min_score=0.0)
    with pytest.raises(ValueError, match="orientation"):
        gate(tm, tc, rm, rc, threshold=1.0, orientation="sideways")
    with pytest.raises(ValueError, match="n_projections"):
        gate(tm, tc, rm, rc, threshold=1.0, n_projections=0)
    with pytest.raises(ValueError, match="buckets"):
        gate(tm, tc, rm, rc, threshold=1.0, buckets=0)
