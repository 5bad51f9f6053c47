"""The static hypotheses' grid of the walk (walk.grid_place, walk.grid_gate) and the block's report grid
(walk.build_report_grid, walk.fresh_pairs) against brute force; the pairs' Kalman products on threads."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.association.helpers import random_covs
from tracker.association.greedy import _HypothesisGrid
from tracker.association.walk import (
    REPORT_CELLS,
    build_report_grid,
    fresh_pairs,
    grid_gate,
    grid_place,
    half_log_det,
    least_k,
    needed_pairs,
    pair_geometry,
    pair_geometry_parallel,
    pair_scores,
    widened_gate,
)
from tracker.models.motion import ConstantVelocity, Static
from tracker.models.sfunc import ExpS


def _brute(Hm, Hc, z, V, gamma):
    """Pairs (report, hypothesis) with d² <= gamma, every pair tested (numpy)."""
    r = z[:, None, :] - Hm[None, :, :]
    S = Hc[None] + V[:, None]
    d2 = np.einsum("kni,knij,knj->kn", r, np.linalg.inv(S), r)
    return {(int(k), int(h)) for k, h in zip(*np.nonzero(d2 <= gamma), strict=True)}


def _pairs(ptr, p_h):
    return {(k, int(h)) for k in range(ptr.size - 1) for h in p_h[ptr[k] : ptr[k + 1]]}


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 300), m=st.integers(1, 200), spread=st.sampled_from([0.1, 1.0, 30.0]),
       gamma=st.sampled_from([3.0, 41.4, 400.0]), outside=st.booleans())
def test_grid_gate_equals_brute_force(seed, n, m, spread, gamma, outside):
    # Hypotheses and reports anywhere (also off the grid's bounds: border cells), covariances over 2+ decades;
    # hypotheses are moved after placement, so relinking is exercised too.
    rng = np.random.default_rng(seed)
    lo, hi = (-2000.0, 12000.0) if outside else (0.0, 10000.0)
    Hm = rng.uniform(lo, hi, (n, 2))
    Hc = random_covs(rng, n, 2.0, 60.0 * spread)
    z = rng.uniform(lo, hi, (m, 2))
    V = random_covs(rng, m, 2.0, 60.0)
    grid = _HypothesisGrid((0.0, 0.0, 10000.0, 10000.0), gamma)
    grid.reserve(V, max(n, 1))
    grid_place(np.arange(n), Hm, Hc, grid.arrays)
    moved = rng.random(n) < 0.5
    Hm[moved] += rng.normal(0, 800.0, (int(moved.sum()), 2))
    Hc[moved] *= 0.5  # fusion only shrinks a static covariance
    grid_place(np.flatnonzero(moved), Hm, Hc, grid.arrays)
    ptr, p_h = grid_gate(z, V, gamma, Hm, Hc, grid.arrays)
    assert _pairs(ptr, p_h) == _brute(Hm, Hc, z, V, gamma)
    for k in range(m):
        assert np.all(np.diff(p_h[ptr[k] : ptr[k + 1]]) > 0)  # ascending, each once


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), placed=st.integers(0, 300), new=st.integers(0, 20), extra=st.integers(0, 20),
       gamma=st.sampled_from([3.0, 41.4, 400.0, 1e5, 1e9]))
def test_widened_gate_equals_brute_force(seed, placed, new, extra, gamma):
    # A block mid-walk at report j: the grid holds the `placed` hypotheses where they were at the block's
    # start; the reports before j were assigned to some of them (which then moved and shrank), to the
    # `new` hypotheses made in the block (not in the grid), or to none. Every hypothesis at d² <= gamma
    # must come back, ascending, once (brute force over all of them); the widest gammas take the
    # every-hypothesis branch.
    rng = np.random.default_rng(seed)
    n = placed + new
    if n == 0:
        return
    Hm = rng.uniform(0.0, 10000.0, (n, 2))
    Hc = random_covs(rng, n, 2.0, 60.0)
    grid = _HypothesisGrid((0.0, 0.0, 10000.0, 10000.0), 41.4)
    old = rng.integers(0, placed, extra) if placed else np.zeros(0, np.int64)
    before = rng.permutation(np.concatenate([np.arange(placed, n), old, np.full(int(rng.integers(0, 5)), -1)]))
    j = before.size
    m = j + int(rng.integers(1, 10))
    z = rng.uniform(-500.0, 10500.0, (m, 2))
    V = random_covs(rng, m, 2.0, 60.0)
    grid.reserve(V, n)
    grid_place(np.arange(placed), Hm, Hc, grid.arrays)
    assign = np.full(m, -1, np.int64)
    assign[:j] = before
    moved = np.unique(old)
    Hm[moved] += rng.normal(0, 800.0, (moved.size, 2))
    Hc[moved] *= 0.5  # fusion only shrinks a static covariance
    z[j] = Hm[rng.integers(0, n)] + rng.normal(0.0, 100.0, 2)  # near one, moved or new or neither
    got = widened_gate(j, gamma, z, V, np.zeros(m), Hm, Hc, np.zeros(n), n, assign, grid.arrays)
    assert got.tolist() == sorted(h for _, h in _brute(Hm, Hc, z[j : j + 1], V[j : j + 1], gamma))


def test_grid_lists_hold_each_hypothesis_once():
    rng = np.random.default_rng(3)
    n = 500
    Hm = rng.uniform(0, 5000, (n, 2))
    Hc = random_covs(rng, n, 5.0, 50.0)
    grid = _HypothesisGrid((0.0, 0.0, 5000.0, 5000.0), 41.4)
    grid.reserve(Hc, n)
    for _ in range(5):
        idx = rng.choice(n, 200)  # repeats: placing twice changes nothing
        Hm[idx] = rng.uniform(0, 5000, (idx.size, 2))
        grid_place(idx, Hm, Hc, grid.arrays)
    grid_place(np.arange(n), Hm, Hc, grid.arrays)
    geo, head, nxt, prv, cell_of, _ = grid.arrays
    seen = []
    for c in range(head.size):
        h, back = head[c], -1
        while h >= 0:
            assert cell_of[h] == c and prv[h] == back
            seen.append(h)
            back, h = h, nxt[h]
    assert sorted(seen) == list(range(n))


def test_half_log_det_within_its_rounding_bound():
    """Against the exact determinant (rational arithmetic on the float entries): the error of ½ ln det
    is within the formula's cancellation bound, eps·(|V00 V11| + |V01 V10|)/det, at 1:10^4 elongation too."""
    rng = np.random.default_rng(5)
    V = np.concatenate([random_covs(rng, 500, 5.0, 60.0), random_covs(rng, 500, 0.01, 100.0)])
    got = half_log_det(V)
    eps = np.finfo(float).eps
    for k in range(V.shape[0]):
        a, b, c, d = (Fraction(float(v)) for v in V[k].ravel())
        exact = a * d - b * c
        want = 0.5 * math.log(exact)
        bound = 2.0 * eps * float(abs(a * d) + abs(b * c)) / float(exact) + 4.0 * eps * max(1.0, abs(want))
        assert abs(got[k] - want) <= bound


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 200), m=st.integers(1, 300), spread=st.sampled_from([0.01, 1.0, 100.0]),
       gamma=st.sampled_from([3.0, 41.4, 400.0]), after=st.integers(0, 299))
def test_fresh_pairs_equal_brute_force(seed, n, m, spread, gamma, after):
    # Changed hypotheses inside and far outside the block's extent (off its rows and columns); blocks
    # spread up to 10^4 times their reports' gate radius, where the report grid's cell is enlarged.
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.0, 1000.0 * spread, (m, 2))
    V = random_covs(rng, m, 0.5, 20.0)
    Hm = rng.uniform(-500.0 * spread, 1500.0 * spread, (n, 2))
    Hc = random_covs(rng, n, 1.0, 200.0)
    order, starts, grid = build_report_grid(z, V, gamma)
    nx, ny = int(grid[4]), int(grid[5])
    assert starts.size == nx * ny + 1 and nx * ny <= max(REPORT_CELLS * m, 65536)
    keys = np.floor((z[order] - grid[:2]) / grid[2]).astype(np.int64) @ np.array([ny, 1])
    assert np.all(np.diff(keys) >= 0) and np.array_equal(np.searchsorted(keys, np.arange(nx * ny + 1)), starts)
    dirty = rng.choice(n, max(1, n // 2), replace=False)
    blk = (z, V, np.zeros(m), np.zeros(m), half_log_det(V), np.zeros(m, bool), np.full(m, -1), order, starts, grid,
           np.zeros(m, np.int64))
    hyp = (Hm, Hc, np.zeros(n), np.ones(n, np.int64), np.zeros(n), np.zeros(n, bool), dirty, np.zeros(1, np.int64),
           np.zeros(n, bool))
    istate = np.array([n, dirty.size, 0, 0, 0], np.int64)
    s_kind, s_param = ExpS(-1.7).code
    m_kind, q, vel_std = Static().code
    j = min(after, m - 1)
    rep, h = fresh_pairs(j, blk, hyp, istate, (gamma, True, 0.0, s_kind, s_param, m_kind, q, vel_std))
    want = {(k, int(d)) for k, d in _brute(Hm[dirty], Hc[dirty], z, V, gamma) if k >= j}
    got = {(int(k), int(d)) for k, d in zip(rep, h, strict=True)}
    assert len(got) == rep.size and got == {(k, int(dirty[i])) for k, i in want}


def test_pair_geometry_parallel_is_the_serial_one():
    # Bit for bit, static and constant velocity (predicted to each report's time first).
    rng = np.random.default_rng(11)
    m, n, k = 300, 120, 5000
    z = rng.uniform(0, 5000, (m, 2))
    V = random_covs(rng, m, 2.0, 60.0)
    blk = (z, V, rng.uniform(10.0, 20.0, m), *([None] * 8))
    rep, h = rng.integers(0, m, k), rng.integers(0, n, k)
    for motion, D in ((Static(), 2), (ConstantVelocity(0.5, 5.0), 4)):
        Hm = rng.uniform(0, 5000, (n, D))
        L = rng.normal(0, 10.0, (n, D, D))
        Hc = L @ L.transpose(0, 2, 1) + 25.0 * np.eye(D)
        hyp = (Hm, Hc, None, None, rng.uniform(0.0, 10.0, n), *([None] * 4))
        m_kind, q, vel_std = motion.code
        cfg = (41.4, True, 0.0, 0, 0.0, m_kind, q, vel_std)
        for a, b in zip(pair_geometry(rep, h, blk, hyp, cfg), pair_geometry_parallel(rep, h, blk, hyp, cfg), strict=True):
            assert np.array_equal(a, b)


def test_needed_pairs_and_scores_are_the_numpy_formulas():
    # Tracker._score's numpy steps (bound, gathers, scores), bit for bit, with bounds on both sides of the
    # threshold, zero integrals (ln = -inf) and no pair needed at all.
    rng = np.random.default_rng(12)
    m, n, k = 200, 90, 4000
    rep, h = rng.integers(0, m, k), rng.integers(0, n, k)
    log_g = rng.normal(-10.0, 3.0, k)
    log_c_all = rng.normal(-12.0, 2.0, n + 7)  # spare capacity beyond the n hypotheses
    log_unseen = rng.normal(-11.0, 3.0, m)
    post_m = rng.uniform(0, 5000, (k, 2))
    post_c = random_covs(rng, k, 2.0, 60.0)
    for log_rmax, tau in ((2.5, -1.7), (-30.0, -1.7)):
        log_c, need, n_need, means, covs = needed_pairs(log_g, log_c_all, h, rep, log_unseen, log_rmax, tau, post_m, post_c)
        want_c = log_c_all[:n][h]
        want_need = (log_g - want_c) + log_rmax >= log_unseen[rep] - tau
        assert np.array_equal(log_c, want_c) and np.array_equal(need, want_need) and n_need == want_need.sum()
        assert np.array_equal(means, post_m[want_need, :2]) and np.array_equal(covs, np.ascontiguousarray(post_c[want_need, :2, :2]))
        assert means.flags.c_contiguous and covs.flags.c_contiguous
        with np.errstate(divide="ignore"):
            log_needed = np.log(np.where(rng.random(n_need) < 0.1, 0.0, rng.random(n_need)))
        score, log_i = pair_scores(log_g, log_c, need, log_needed)
        want_i = np.zeros(k)
        want_i[want_need] = log_needed
        want_s = np.full(k, -np.inf)
        ok = want_need & np.isfinite(want_i)
        want_s[ok] = log_g[ok] + want_i[ok] - want_c[ok]
        assert np.array_equal(log_i, want_i) and np.array_equal(score, want_s)
    assert n_need == 0  # ln r_max = -30: no bound reaches previouslyUnseen


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6) | st.sampled_from([-np.inf, 0.0, 1.0]), min_size=1, max_size=400), st.data())
def test_least_k_is_argpartition(values, data) -> None:
    """The k least (as a multiset) and the least of the rest, against numpy's sort; ties included."""
    values = np.array(values)
    k = data.draw(st.integers(1, values.size))
    idx, floor = least_k(values, k)
    assert idx.size == k and np.unique(idx).size == k and np.all(np.diff(idx) > 0)
    ordered = np.sort(values)
    np.testing.assert_array_equal(np.sort(values[idx]), ordered[:k])
    assert floor == (ordered[k] if k < values.size else np.inf)
