"""Track clusters and report/cluster gating (paper 2, eq. 3-4).

Tracks whose gate volumes over the scan come within a minimum separation distance (MSD, metres)
of each other are linked; clusters are the connected components. Each cluster is gated as a
pseudotrack: weighted mean and covariance of its members (eq. 3-4) and a search radius covering
every member's gate volume over the scan plus the MSD. Reports inside several clusters' volumes
are settled by their score S (eq. 1) against each pseudotrack.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tracker.gating.exact import lambda_max_bound, log_det
from tracker.gating.gate import gate_threshold
from tracker.gating.reach import ReachBound, project, project_states, speed
from tracker.gating.scene import Scene


@dataclass(frozen=True)
class Clusters:
    """Clusters of tracks: member labels and pseudotracks valid at ``t_ref`` (s).

    ``means`` (C, s) and ``covs`` (C, s, s) are in the tracks' state space (positions, or
    positions then velocities); ``radius`` (C,) metres covers every member's gate over the scan
    [t_lo, t_hi] around the pseudotrack's projected mean, plus the MSD.
    """

    labels: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    radius: np.ndarray
    process_noise: np.ndarray
    t_ref: float
    t_lo: float
    t_hi: float
    dim: int
    gamma: float

    @property
    def moving(self) -> bool:
        return self.means.shape[1] == 2 * self.dim


def pseudotracks(means: np.ndarray, covs: np.ndarray, labels: np.ndarray,
                 weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3-4: mu = sum w_j mu_j, S = sum w_j (S_j + (mu_j - mu)(mu_j - mu)^T), with the
    weights normalised to sum to one within each cluster (uniform when None)."""
    n_c = int(labels.max()) + 1 if labels.size else 0
    w = np.ones(len(labels)) if weights is None else np.asarray(weights, float)
    if w.shape != labels.shape or not np.all(np.isfinite(w) & (w > 0)):
        raise ValueError("weights must be finite, positive and one per track")
    total = np.bincount(labels, w, minlength=n_c)
    wn = w / total[labels]
    mu = np.zeros((n_c, means.shape[1]))
    np.add.at(mu, labels, wn[:, None] * means)
    dev = means - mu[labels]
    s = np.zeros((n_c, means.shape[1], means.shape[1]))
    np.add.at(s, labels, wn[:, None, None] * (covs + dev[:, :, None] * dev[:, None, :]))
    return mu, s


def cluster_tracks(track_means, track_covs, *, min_separation: float,
                   threshold: float | None = None, prob: float | None = None,
                   scan: tuple[float, float] = (0.0, 0.0), track_times=0.0, process_noise=0.0,
                   weights=None) -> Clusters:
    """Cluster tracks (static (N, d) or CV (N, 2d) states) over the scan [t_lo, t_hi] (s).

    Each track's gate over the scan lies in a ball around its mid-scan position of radius
    e = sqrt(gamma) sigma_max + |v| tau / 2 (sigma_max: bound on its position std dev over the
    scan); two tracks are linked when their balls come within ``min_separation`` metres.
    """
    tm = np.ascontiguousarray(track_means, dtype=float)
    if tm.ndim != 2 or tm.shape[1] not in (2, 3, 4, 6):
        raise ValueError(f"track_means must be (N, d) or (N, 2d), d in {{2, 3}}; got {tm.shape}")
    dim = tm.shape[1] if tm.shape[1] in (2, 3) else tm.shape[1] // 2
    t_lo, t_hi = map(float, scan)
    if not (np.isfinite(t_lo) and np.isfinite(t_hi) and t_hi >= t_lo):
        raise ValueError(f"scan must be finite (t_lo, t_hi) with t_hi >= t_lo, got {scan!r}")
    if not (np.isfinite(min_separation) and min_separation >= 0):
        raise ValueError(f"min_separation must be finite and >= 0, got {min_separation!r}")
    if (threshold is None) == (prob is None):
        raise ValueError("give exactly one of threshold= or prob=")
    gamma = gate_threshold(prob, dim) if prob is not None else float(threshold)
    if not (np.isfinite(gamma) and gamma >= 0):
        raise ValueError(f"threshold must be finite and >= 0, got {threshold!r}")
    # gate()'s validation of the tracks, with an empty report set
    sc = Scene.validate(tm, track_covs, np.zeros((0, dim)), np.zeros((0, dim, dim)),
                        np.zeros(0) if tm.shape[1] == 2 * dim else None, track_times, process_noise)
    n = tm.shape[0]
    t_mid = 0.5 * (t_lo + t_hi)
    reach = ReachBound.from_covs(sc.tcov, sc.tq, dim, sc.moving)
    dt_max = np.maximum(np.abs(t_lo - sc.ttime), np.abs(t_hi - sc.ttime))
    spd = speed(tm, dim) if sc.moving else np.zeros(n)
    ext = np.sqrt(gamma) * reach.sigma(dt_max) + spd * 0.5 * (t_hi - t_lo)
    centre = sc.tpos + (t_mid - sc.ttime)[:, None] * sc.tvel
    labels = _components(centre, ext, float(min_separation))
    if sc.moving:  # bring every member to t_mid before averaging
        state, cov = project_states(tm, sc.tcov, t_mid - sc.ttime, sc.tq, dim)
    else:
        state, cov = sc.tpos, sc.tcov
    mu, s = pseudotracks(state, cov, labels, weights)
    q_c = np.zeros(len(mu))
    np.maximum.at(q_c, labels, sc.tq)
    radius = _cluster_radius(labels, mu, state, reach, sc, gamma, t_lo, t_hi, t_mid, dim)
    return Clusters(labels, mu, s, radius + min_separation, q_c, t_mid, t_lo, t_hi, dim, gamma)


def _components(centre: np.ndarray, ext: np.ndarray, msd: float) -> np.ndarray:
    """Connected components of 'balls within msd of each other' (labels 0..C-1)."""
    n = centre.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    pairs = cKDTree(centre).query_pairs(2 * float(ext.max()) + msd, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    keep = np.linalg.norm(centre[i] - centre[j], axis=1) <= ext[i] + ext[j] + msd
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _cluster_radius(labels, mu, state, reach, sc, gamma, t_lo, t_hi, t_mid, dim):
    """Max over members and over the scan of |p_j(t) - mu(t)| + sqrt(gamma) sigma_j(t).

    Both terms are convex in t, so the maximum over [t_lo, t_hi] sits at an end of the scan.
    """
    dev = state - mu[labels]
    worst = np.zeros(len(labels))
    for t in (t_lo, t_hi):
        off = dev[:, :dim] + (t - t_mid) * dev[:, dim:] if sc.moving else dev
        sig = reach.sigma(np.abs(t - sc.ttime))
        worst = np.maximum(worst, np.linalg.norm(off, axis=1) + np.sqrt(gamma) * sig)
    radius = np.zeros(len(mu))
    np.maximum.at(radius, labels, worst)
    return radius * (1 + 1e-9)


def gate_clusters(clusters: Clusters, report_means, report_covs, report_times=None):
    """Reports against cluster pseudotracks.

    Candidates: report j is in cluster c's volume when |z_j - mu_c(t_j)| <= radius_c +
    sqrt(gamma lambda_max(R_j)); this never misses a report that passes the exact gate with a
    member track. Returns (cluster_idx, report_idx) candidate pairs sorted by (cluster, report)
    and ``assigned`` (M,): the candidate cluster with the highest score S (eq. 1) per report,
    or -1 when none.
    """
    dim = clusters.dim
    rm = np.ascontiguousarray(report_means, dtype=float)
    rc = np.ascontiguousarray(report_covs, dtype=float)
    moving = clusters.moving
    rt = np.zeros(len(rm)) if report_times is None else np.asarray(report_times, float)
    s = 2 * dim if moving else dim
    Scene.validate(np.zeros((0, s)), np.zeros((0, s, s)), rm, rc, rt if moving else None)
    if moving and (rt.min(initial=clusters.t_lo) < clusters.t_lo - 1e-9
                   or rt.max(initial=clusters.t_hi) > clusters.t_hi + 1e-9):
        raise ValueError("report_times must lie inside the scan the clusters were built for")
    n_c, n_r = len(clusters.radius), len(rm)
    assigned = np.full(n_r, -1, np.int64)
    if n_c == 0 or n_r == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), assigned
    mu = clusters.means
    spd = speed(mu, dim) if moving else np.zeros(n_c)
    half = 0.5 * (clusters.t_hi - clusters.t_lo)
    ball = clusters.radius + spd * half  # covers the cluster over the whole scan
    reach_r = np.sqrt(clusters.gamma * lambda_max_bound(rc)) * (1 + 1e-9)
    lists = cKDTree(mu[:, :dim]).query_ball_point(rm, ball.max() + reach_r)
    counts = np.fromiter(map(len, lists), np.int64, n_r)
    r_idx = np.repeat(np.arange(n_r), counts)
    c_idx = np.concatenate(lists).astype(np.int64) if counts.sum() else np.zeros(0, np.int64)
    dt = rt[r_idx] - clusters.t_ref
    if moving:
        pos, pcov = project(mu[c_idx], clusters.covs[c_idx], dt, clusters.process_noise[c_idx],
                            dim)
    else:
        pos, pcov = mu[c_idx], clusters.covs[c_idx]
    dist = np.linalg.norm(rm[r_idx] - pos, axis=1)
    keep = dist <= clusters.radius[c_idx] + reach_r[r_idx]
    c_idx, r_idx, pos, pcov = c_idx[keep], r_idx[keep], pos[keep], pcov[keep]
    v = pcov + rc[r_idx]
    dx = rm[r_idx] - pos
    d2 = np.einsum("ni,ni->n", dx, np.linalg.solve(v, dx[:, :, None])[:, :, 0])
    log_s = -0.5 * d2 - 0.5 * dim * np.log(2 * np.pi) - 0.5 * log_det(np.ascontiguousarray(v))
    order = np.lexsort((-log_s, r_idx))  # per report, best score first
    first = np.ones(order.size, bool)
    first[1:] = r_idx[order][1:] != r_idx[order][:-1]
    assigned[r_idx[order][first]] = c_idx[order][first]
    o = np.lexsort((r_idx, c_idx))
    return c_idx[o], r_idx[o], assigned
