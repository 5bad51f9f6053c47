"""Clusters: pseudotrack moments (eq. 3-4), components against a dense union-find, and no
report that gates with a member track is ever lost by its cluster."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.gating.test_oracle import brute_force, random_covs
from tracker.gating.clusters import cluster_tracks, gate_clusters, pseudotracks


def test_pseudotrack_is_the_mixture_moments():
    """Eq. 3-4 are the mean and covariance of the Gaussian mixture: check by sampling."""
    rng = np.random.default_rng(0)
    means = rng.normal(0, 10, (3, 2))
    covs = random_covs(rng, 3, 2, 1.0, 5.0)
    w = np.array([0.2, 0.5, 0.3])
    mu, s = pseudotracks(means, covs, np.zeros(3, np.int64), w * 7.0)
    comp = rng.choice(3, size=400_000, p=w)
    x = means[comp] + np.einsum("nij,nj->ni", np.linalg.cholesky(covs)[comp],
                                rng.standard_normal((400_000, 2)))
    np.testing.assert_allclose(mu[0], x.mean(axis=0), atol=0.05)
    np.testing.assert_allclose(s[0], np.cov(x.T), rtol=0.02, atol=0.2)


def _union_find_labels(centre, ext, msd):
    n = len(centre)
    parent = list(range(n))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(centre[i] - centre[j]) <= ext[i] + ext[j] + msd:
                parent[find(i)] = find(j)
    return np.array([find(i) for i in range(n)])


def _same_partition(a, b):
    return all(len(set(b[a == k])) == 1 for k in set(a)) and len(set(a)) == len(set(b))


def _scene(seed, nt, nr, dim, moving, scan):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 6000, (nt, dim))
    covs_p = random_covs(rng, nt, dim, 2.0, 40.0)
    if moving:
        tm = np.hstack([pos, rng.uniform(-20, 20, (nt, dim))])
        tc = random_covs(rng, nt, 2 * dim, 1.0, 20.0)
    else:
        tm, tc = pos, covs_p
    times = rng.uniform(0, scan, nr)
    src = rng.integers(0, max(nt, 1), nr)
    rm = rng.uniform(0, 6000, (nr, dim))
    if nt:
        rm[: nr // 2] = (pos[src] + (times[:, None] * tm[src, dim:] if moving else 0.0)
                         + rng.normal(0, 30, (nr, dim)))[: nr // 2]
    rc = random_covs(rng, nr, dim, 2.0, 40.0)
    return tm, tc, rm, rc, times


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), nt=st.integers(1, 25), nr=st.integers(0, 25),
       dim=st.sampled_from([2, 3]), moving=st.booleans(), scan=st.sampled_from([0.0, 5.0]),
       msd=st.sampled_from([0.0, 50.0, 300.0]))
def test_no_gated_report_lost_and_best_score_wins(seed, nt, nr, dim, moving, scan, msd):
    tm, tc, rm, rc, rt = _scene(seed, nt, nr, dim, moving, scan)
    gamma, q = 9.0, 2.0
    cl = cluster_tracks(tm, tc, min_separation=msd, threshold=gamma, scan=(0.0, scan),
                        process_noise=q)
    c_idx, r_idx, assigned = gate_clusters(cl, rm, rc, rt if moving else None)
    d2, limit = brute_force(tm, tc, rm, rc, gamma=gamma, report_times=rt if moving else None,
                            q=q)
    cand = set(zip(c_idx.tolist(), r_idx.tolist(), strict=True))
    for t, r in zip(*np.nonzero(d2 <= limit), strict=True):
        assert (cl.labels[t], r) in cand, f"report {r} gates with track {t} but not its cluster"
    # the assigned cluster has the best score (eq. 1) among the report's candidates
    for r in range(nr):
        cs = c_idx[r_idx == r]
        if cs.size == 0:
            assert assigned[r] == -1
            continue
        dt = rt[r] - cl.t_ref if moving else 0.0
        scores = []
        for c in cs:
            x, p = cl.means[c], cl.covs[c]
            if moving:
                f = np.eye(2 * dim)
                f[:dim, dim:] = dt * np.eye(dim)
                x, p = f @ x, f @ p @ f.T
                p[:dim, :dim] += cl.process_noise[c] * abs(dt) ** 3 / 3 * np.eye(dim)
            v = p[:dim, :dim] + rc[r]
            e = rm[r] - x[:dim]
            scores.append(np.exp(-0.5 * e @ np.linalg.solve(v, e))
                          / np.sqrt(np.linalg.det(2 * np.pi * v)))
        assert scores[list(cs).index(assigned[r])] >= max(scores) * (1 - 1e-9)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), nt=st.integers(0, 30), msd=st.sampled_from([0.0, 100.0]))
def test_components_match_dense_union_find(seed, nt, msd):
    tm, tc, _, _, _ = _scene(seed, nt, 0, 2, False, 0.0)
    cl = cluster_tracks(tm, tc, min_separation=msd, threshold=9.0)
    # independent extent: sqrt(gamma * lambda_max(P)) via numpy eigvalsh
    ext = np.sqrt(9.0 * np.linalg.eigvalsh(tc)[:, -1]) if nt else np.zeros(0)
    want = _union_find_labels(tm, ext, msd)
    assert _same_partition(cl.labels, want)
    assert len(cl.radius) == len(set(want.tolist()))


def test_cluster_errors():
    tm, tc = np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1))
    with pytest.raises(ValueError, match="min_separation"):
        cluster_tracks(tm, tc, min_separation=-1.0, threshold=9.0)
    with pytest.raises(ValueError, match="exactly one"):
        cluster_tracks(tm, tc, min_separation=1.0)
    with pytest.raises(ValueError, match="scan"):
        cluster_tracks(tm, tc, min_separation=1.0, threshold=9.0, scan=(2.0, 1.0))
    with pytest.raises(ValueError, match="track_covs"):
        cluster_tracks(tm, -tc, min_separation=1.0, threshold=9.0)
    with pytest.raises(ValueError, match="weights"):
        cluster_tracks(tm, tc, min_separation=1.0, threshold=9.0, weights=[1.0, -1.0])
