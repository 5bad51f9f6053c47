"""The batch chain's persistent cluster index and its round-dependency kernel, against brute force
and against gating every cluster (the path they replace): same pairs, same links, same chain."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.association.helpers import random_covs
from tracker.association.batch import BatchAssociator
from tracker.association.batch_kernels import earlier_dependency
from tracker.association.cluster_index import ClusterIndex, lambda_max
from tracker.gating import gate

GAMMA = 41.4



def d2(a: np.ndarray, A: np.ndarray, z: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(n, m) Mahalanobis d² of every z_j − a_i under A_i + V_j (brute force)."""
    r = z[None, :, :] - a[:, None, :]
    S = A[:, None] + V[None, :]
    return np.einsum("nmi,nmij,nmj->nm", r, np.linalg.inv(S), r)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), m=st.integers(1, 40))
def test_candidates_contain_every_gated_cluster(seed: int, n: int, m: int) -> None:
    """After random placements, moves and removals, every live cluster a report gates with is a candidate."""
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
    cand = index.candidates(zc, lambda_max(V))
    assert np.all(np.diff(cand) > 0) and live[cand].all()
    gated = np.flatnonzero(live & (d2(means, covs, zc, V) <= GAMMA).any(axis=1))
    assert np.isin(gated, cand).all()


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
    """The production chain (index candidates) walks the same chain as gating all live clusters."""
    from bench.bench_tracker import scenario, synthetic_prior

    prior = synthetic_prior(4000.0)
    rep = scenario(prior, 150, 1500, seed=2)
    init = np.arange(len(rep))  # all singletons: many reports move
    runs = []
    for all_live in (False, True):
        ba = BatchAssociator(prior, "TT", tau=-1.7)
        ch = ba.chain(rep, init)
        if all_live:
            ch.index.candidates = lambda zc, lam_v, ch=ch: np.flatnonzero(ch.cnt > 0)
        rng = np.random.default_rng(7)
        moved = [ch.sweep(1.0, rng) for _ in range(2)]
        runs.append((ch.labels.copy(), ch.lp, moved))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1] and runs[0][2] == runs[1][2] and runs[0][2][0] > 200
