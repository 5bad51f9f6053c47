"""The batch chain's persistent cluster index, its round kernels and the 2×2 closed forms, against
brute force and against gating every cluster (the path they replace): same pairs, same links, same
chain."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.association.helpers import random_covs
from tracker.association.batch import BatchAssociator
from tracker.association.batch_kernels import (
    earlier_dependency,
    info_gaussians,
    own_without,
    round_options,
)
from tracker.association.cluster_index import ClusterIndex, lambda_max
from tracker.gating import gate
from tracker.gating.gate import gate_unchecked

GAMMA = 41.4



def d2(a: np.ndarray, A: np.ndarray, z: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(n, m) Mahalanobis d² of every z_j − a_i under A_i + V_j (brute force)."""
    r = z[None, :, :] - a[:, None, :]
    S = A[:, None] + V[None, :]
    return np.einsum("nmi,nmij,nmj->nm", r, np.linalg.inv(S), r)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), m=st.integers(1, 40))
def test_gated_pairs_equal_the_gater_on_live_clusters(seed: int, n: int, m: int) -> None:
    """After random placements, moves and removals, the index's gated pairs are exactly the gater's
    pairs against the live clusters (without each report's skipped cluster), and brute force agrees
    away from the threshold."""
    rng = np.random.default_rng(seed)
    span = rng.uniform(200.0, 5000.0)
    zc = rng.uniform(0, span, (m, 2))
    V = random_covs(rng, m)
    cap = n + 5
    index = ClusterIndex.for_reports(zc, lambda_max(V), cap, GAMMA)
    means = rng.uniform(-0.2 * span, 1.2 * span, (cap, 2))  # some outside the reports' box
    covs = random_covs(rng, cap, 1.0, 80.0)
    index.update(np.arange(cap), means, covs)
    live = np.ones(cap, bool)
    gone = rng.choice(cap, cap // 3, replace=False)
    index.remove(gone)
    live[gone] = False
    moved = rng.choice(cap, cap // 2, replace=False)
    means[moved] = rng.uniform(0, span, (moved.size, 2))
    covs[moved] = random_covs(rng, moved.size)
    index.update(moved, means[moved], covs[moved])
    live[moved] = True
    skip = rng.integers(-1, cap, m)
    ptr, cl = index.gated(zc, V, lambda_max(V), skip)
    pos = np.repeat(np.arange(m), np.diff(ptr))
    assert ptr[0] == 0 and ptr[-1] == cl.size and live[cl].all()
    ids = np.flatnonzero(live)
    t_idx, r_idx = gate(means[ids], covs[ids], zc, V, threshold=GAMMA)
    want = sorted((int(r), int(c)) for r, c in zip(r_idx, ids[t_idx], strict=True) if c != skip[r])
    assert list(zip(pos.tolist(), cl.tolist(), strict=True)) == want
    d = d2(means, covs, zc, V).T  # (m, cap)
    inside = np.zeros((m, cap), bool)
    inside[pos, cl] = True
    clear = live[None, :] & (np.arange(cap)[None, :] != skip[:, None]) & (np.abs(d - GAMMA) > 1e-6 * GAMMA)
    np.testing.assert_array_equal(inside[clear], (d <= GAMMA)[clear])


def test_earlier_dependency_matches_gating_the_possible_clusters() -> None:
    """The kernel's links equal gating every possible new cluster against the round's reports."""
    rng = np.random.default_rng(3)
    m, n_cl = 300, 120
    zc = rng.uniform(0, 2000.0, (m, 2))
    V = random_covs(rng, m)
    vinv = np.linalg.inv(V)
    hv = np.einsum("kij,kj->ki", vinv, zc)
    P = np.linalg.inv(random_covs(rng, n_cl, 5.0, 40.0))
    h = np.einsum("nij,nj->ni", P, rng.uniform(0, 2000.0, (n_cl, 2)))
    multi = np.flatnonzero(rng.random(m) < 0.6)
    Bm = random_covs(rng, multi.size, 5.0, 40.0)
    bm = zc[multi] + rng.normal(0, 50.0, (multi.size, 2))
    pos = np.repeat(np.arange(m), rng.integers(0, 3, m))
    cl = rng.integers(0, n_cl, pos.size)
    reps = np.arange(m)
    got = earlier_dependency(zc, V, lambda_max(V), GAMMA, multi, bm, Bm, pos, cl, P, h, reps, vinv, hv)
    Bc = np.linalg.inv(P[cl] + vinv[pos])
    bc = np.einsum("nij,nj->ni", Bc, h[cl] + hv[pos])
    owner = np.concatenate([np.arange(m), multi, pos])
    p_idx, q_idx = gate(np.concatenate([zc, bm, bc]), np.concatenate([V, Bm, Bc]), zc, V, threshold=GAMMA)
    a, b = owner[p_idx], q_idx
    want = np.zeros(m, bool)
    want[np.maximum(a, b)[a != b]] = True
    np.testing.assert_array_equal(got, want)
    assert 0 < want.sum() < m


def test_index_path_gives_the_chain_of_gating_all_clusters() -> None:
    """The production chain (the index's gated pairs) walks the same chain as gating all live clusters."""
    from bench.bench_tracker import scenario, synthetic_prior

    prior = synthetic_prior(4000.0)
    rep = scenario(prior, 150, 1500, seed=2)
    init = np.arange(len(rep))  # all singletons: many reports move
    runs = []
    for gater in (None, gate_unchecked):  # the index, then the gater on all live clusters
        ba = BatchAssociator(prior, "TT", tau=-1.7, gater=gater)
        ch = ba.chain(rep, init)
        rng = np.random.default_rng(7)
        moved = [ch.sweep(1.0, rng) for _ in range(2)]
        runs.append((ch.labels.copy(), ch.lp, moved))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1] and runs[0][2] == runs[1][2] and runs[0][2][0] > 200


def test_round_kernels_match_the_numpy_formulas() -> None:
    """info_gaussians, own_without and round_options against inv / slogdet / einsum / lexsort."""
    rng = np.random.default_rng(4)
    m, n_cl = 200, 60
    P = np.linalg.inv(random_covs(rng, n_cl, 5.0, 40.0))
    h = rng.normal(0, 1.0, (n_cl, 2))
    b, B, det = info_gaussians(P, h)
    np.testing.assert_allclose(B, np.linalg.inv(P), rtol=1e-12)
    np.testing.assert_allclose(b, np.einsum("nij,nj->ni", np.linalg.inv(P), h), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.log(det), np.linalg.slogdet(P)[1], rtol=1e-12)
    # own clusters: sums of a few reports each
    zc = rng.uniform(0, 300.0, (m, 2))
    V = random_covs(rng, m)
    vinv = np.linalg.inv(V)
    hv = np.einsum("kij,kj->ki", vinv, zc)
    lab = rng.integers(0, n_cl, m)
    cnt = np.bincount(lab, minlength=n_cl)
    Ps = np.zeros((n_cl, 2, 2))
    hs = np.zeros((n_cl, 2))
    np.add.at(Ps, lab, vinv)
    np.add.at(hs, lab, hv)
    reps = rng.permutation(m)[: m // 2]
    own = lab[reps]
    multi, mi, bm, Bm, own_gated = own_without(reps, own, cnt, Ps, hs, vinv, hv, zc[reps], V[reps], GAMMA)
    np.testing.assert_array_equal(multi, cnt[own] > 1)
    np.testing.assert_array_equal(mi, np.flatnonzero(cnt[own] > 1))
    Bw = np.linalg.inv(Ps[own[mi]] - vinv[reps[mi]])
    bw = np.einsum("nij,nj->ni", Bw, hs[own[mi]] - hv[reps[mi]])
    np.testing.assert_allclose(Bm, Bw, rtol=1e-9)
    np.testing.assert_allclose(bm, bw, rtol=1e-9, atol=1e-9)
    r = zc[reps[mi]] - bw
    d = np.einsum("ni,nij,nj->n", r, np.linalg.inv(Bw + V[reps[mi]]), r)
    want = np.zeros(reps.size, bool)
    want[mi] = d <= GAMMA
    assert 0 < want.sum() < mi.size
    np.testing.assert_array_equal(own_gated, want)
    # options: gated clusters and (when gated) the own cluster, by cluster id, for the selected
    k = reps.size
    ptr = np.concatenate([[0], np.cumsum(rng.integers(0, 4, k))])
    cl = np.concatenate([np.sort(rng.choice(np.setdiff1d(np.arange(n_cl), [own[p]]), ptr[p + 1] - ptr[p], replace=False))
                         for p in range(k)]).astype(np.int64)
    sel = rng.random(k) < 0.5
    o_ptr, o_cl, o_own, o_pos = round_options(sel, own, ptr, cl, own_gated)
    pos = np.repeat(np.arange(k), np.diff(ptr))
    w_pos = np.concatenate([pos[sel[pos]], np.flatnonzero(sel & own_gated)])
    w_cl = np.concatenate([cl[sel[pos]], own[sel & own_gated]])
    order = np.lexsort((w_cl, w_pos))
    np.testing.assert_array_equal(o_pos, w_pos[order])
    np.testing.assert_array_equal(o_cl, w_cl[order])
    np.testing.assert_array_equal(o_own, o_cl == own[o_pos])
    np.testing.assert_array_equal(np.diff(o_ptr), np.bincount(o_pos, minlength=k)[sel])
