"""The grid module's pair sort against numpy's lexsort, and gating scenes whose output is dense
or dominated by one track (the pair sort's and the kernel's worst cases) against the brute force."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.gating.test_oracle import assert_same_pairs, brute_force, random_covs
from tracker.gating import grid
from tracker.gating.gate import gate
from tracker.gating.grid import counting_order, sort_pairs, sorted_pairs


@st.composite
def pair_sets(draw):
    """Distinct (t, r) pairs: runs per track from empty to long, sorted, reversed or shuffled."""
    n_t, n_r = draw(st.integers(1, 40)), draw(st.integers(1, 300))
    seed = draw(st.integers(0, 2**31))
    rng = np.random.default_rng(seed)
    sizes = rng.integers(0, draw(st.sampled_from([3, 40, 300])), n_t)
    t = np.repeat(np.arange(n_t), np.minimum(sizes, n_r))
    r = np.concatenate([rng.choice(n_r, min(k, n_r), replace=False) for k in sizes])
    r = r.astype(np.int64)
    style = draw(st.sampled_from(["shuffled", "sorted_runs", "reversed_runs", "grouped"]))
    if style == "sorted_runs":
        o = np.lexsort((r, t))
        t, r = t[o], r[o]
    elif style == "reversed_runs":
        o = np.lexsort((-r, t))
        t, r = t[o], r[o]
    perm = rng.permutation(t.size) if style == "shuffled" else np.arange(t.size)
    if style == "grouped":  # tracks in a random order, each run contiguous
        perm = np.argsort(rng.permutation(n_t)[t], kind="stable")
    return t[perm], r[perm], n_t, n_r


@settings(max_examples=80, deadline=None)
@given(pair_sets())
def test_sort_pairs_is_lexsort(pairs):
    t, r, n_t, n_r = pairs
    want = np.lexsort((r, t))
    assert np.array_equal(sort_pairs(t, r, n_t, n_r), want)
    d2 = np.random.default_rng(1).random(t.size)
    ts, rs, ds = sorted_pairs(t, r, d2, n_t, n_r)
    assert np.array_equal(ts, t[want]) and np.array_equal(rs, r[want])
    assert np.array_equal(ds, d2[want])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 3000), st.integers(1, 200_000), st.sampled_from(["uniform", "few", "top"]),
       st.integers(0, 2**31))
def test_counting_order_is_a_stable_sort(n, n_keys, spread, seed):
    """Both digit schemes (flat, and two digits above _FLAT_KEYS keys and values) give numpy's
    stable argsort and the offsets searchsorted finds."""
    rng = np.random.default_rng(seed)
    hi = {"uniform": n_keys, "few": min(n_keys, 5), "top": n_keys}[spread]
    keys = rng.integers(n_keys - hi if spread == "top" else 0, hi if spread != "top" else n_keys, n)
    flat = grid._FLAT_KEYS
    try:
        for small in (flat, 0):  # the production threshold, then two digits whatever the size
            grid._FLAT_KEYS = small
            order, start = counting_order.py_func(keys, n_keys)
            assert np.array_equal(order, np.argsort(keys, kind="stable"))
            assert np.array_equal(start, np.searchsorted(keys[order], np.arange(n_keys + 1)))
    finally:
        grid._FLAT_KEYS = flat
    for chunks in (2, 3, 7):  # the multi-threaded two-digit sort, however the input is sliced
        order, start = grid._counting_order_split(keys, n_keys, chunks)
        assert np.array_equal(order, np.argsort(keys, kind="stable"))
        assert np.array_equal(start, np.searchsorted(keys[order], np.arange(n_keys + 1)))


def test_counting_order_two_digits_compiled():
    """The compiled two-digit path on a grid-sized input (millions of cells), on several
    threads (more than _SORT_PER_THREAD keys)."""
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 3_000_001, 2 * grid._SORT_PER_THREAD + 1)
    order, start = counting_order(keys, 3_000_001)
    assert np.array_equal(order, np.argsort(keys, kind="stable"))
    assert np.array_equal(start, np.searchsorted(keys[order], np.arange(3_000_002)))


def test_sort_pairs_of_one_long_reversed_run():
    """One track with 300,000 pairs in reverse order: the insertion sort's worst case (~45 G
    moves, minutes), a fraction of a second for the merge sort of long runs."""
    k = 300_000
    t, r = np.zeros(k, np.int64), np.arange(k, dtype=np.int64)[::-1].copy()
    assert np.array_equal(sort_pairs(t, r, 1, k), np.arange(k)[::-1])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("orientation", ["auto", "tracks"])
def test_one_track_gating_every_report(dim, orientation):
    """The issue's repro, smaller: one track's gate holds every report."""
    rng = np.random.default_rng(0)
    n, m = 41, 3000
    tm = rng.uniform(0, 1e4, (n, dim))
    tc = random_covs(rng, n, dim, 10.0, 30.0)
    tm[0], tc[0] = 5000.0, np.eye(dim) * 1e10
    rm = rng.uniform(0, 1e4, (m, dim))
    rc = random_covs(rng, m, dim, 3.0, 10.0)
    t_idx, r_idx = gate(tm, tc, rm, rc, threshold=9.21, orientation=orientation)
    want_d2, limit = brute_force(tm, tc, rm, rc, gamma=9.21)
    assert np.count_nonzero(t_idx == 0) == m
    assert_same_pairs(t_idx, r_idx, want_d2, limit)


@pytest.mark.parametrize("orientation", ["auto", "tracks"])
def test_everything_at_one_point(orientation):
    """Every pair gates (dense output): tracks and reports at one point."""
    n, m = 150, 200
    tc, rc = np.tile(np.eye(2), (n, 1, 1)), np.tile(np.eye(2) * 2.0, (m, 1, 1))
    t_idx, r_idx, d2 = gate(np.zeros((n, 2)), tc, np.zeros((m, 2)), rc, threshold=1.0,
                            orientation=orientation, return_d2=True)
    assert np.array_equal(t_idx, np.repeat(np.arange(n), m))
    assert np.array_equal(r_idx, np.tile(np.arange(m), n)) and np.all(d2 == 0.0)


def test_radii_over_four_decades():
    """Gate sigmas from 1 m to 10 km on both sides (radius buckets, huge queries)."""
    rng = np.random.default_rng(7)
    n, m = 300, 400
    tm, rm = rng.uniform(0, 2e5, (n, 2)), rng.uniform(0, 2e5, (m, 2))
    tc, rc = random_covs(rng, n, 2, 1.0, 1e4), random_covs(rng, m, 2, 1.0, 1e4)
    for orientation in ("auto", "tracks"):
        t_idx, r_idx = gate(tm, tc, rm, rc, threshold=9.21, orientation=orientation)
        assert t_idx.size > 100
        assert_same_pairs(t_idx, r_idx, *brute_force(tm, tc, rm, rc, gamma=9.21))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 50), st.integers(1, 6), st.integers(0, 2**31))
def test_query_radii_follow_the_numpy_formula(nq, nb, seed):
    """The fused radius kernel against the numpy expression it replaced (bit for bit), with
    negative and infinite gamma bounds skipping their buckets."""
    rng = np.random.default_rng(seed)
    s2_q, s2_b = rng.uniform(0, 1e4, nq), rng.uniform(0, 1e4, nb)
    u_q, u_b = rng.uniform(0, 300, nq), rng.uniform(0, 5, nb)
    g_q = rng.choice([-1.0, 9.21, 20.0, np.inf], nq)
    g_b = rng.choice([-2.0, 9.21, 15.0], nb)
    got = grid.query_radii(s2_q, s2_b, u_q, u_b, g_q, g_b, 1e-9)
    g = np.minimum(g_b[None, :], g_q[:, None])
    with np.errstate(invalid="ignore"):
        want = np.sqrt(np.maximum(g, 0.0) * (s2_q[:, None] + s2_b[None, :])) + u_q[:, None] * u_b[None, :]
        want = want * (1.0 + grid.RADIUS_SLACK) + 1e-9
    want[(g < 0.0) | ~np.isfinite(want)] = -1.0
    assert np.array_equal(got, want)


@pytest.mark.parametrize("shape", [(0, 2), (7, 2), (5, 2, 2), (9, 4, 4), (3, 6)])
def test_take_rows_is_fancy_indexing(shape):
    rng = np.random.default_rng(0)
    a = rng.random(shape)
    rows = rng.integers(0, max(shape[0], 1), 11) if shape[0] else np.zeros(0, np.int64)
    assert np.array_equal(grid.take_rows(a, rows), a[rows])
