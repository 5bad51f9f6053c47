"""Bearing-only (subdimensional) gating: 2-D tracks against bearing reports from one sensor at a
known position, as 1-D range queries in the sensor's angle coordinate (paper 2).

Each track is mapped to its bearing beta = atan2(y - s_y, x - s_x) (radians, counter-clockwise
from +x) with the linearised variance J P J^T, J = (-dy, dx) / r^2. A pair gates when
wrap(theta - beta)^2 / (sigma_beta^2 + sigma_theta^2) <= gamma (chi-square with one degree of
freedom). Tracks are bucketed by angular sigma and sorted by bearing; each report searches the
interval its own sigma and the bucket's largest sigma allow, wrapping across +-pi.
"""

from __future__ import annotations

import numpy as np

from tracker.gating.exact import RADIUS_SLACK
from tracker.gating.gate import gate_threshold
from tracker.types.reports import check_gaussians

_BUCKET_RATIO = 2.0


def track_bearings(track_means, track_covs, sensor) -> tuple[np.ndarray, np.ndarray]:
    """Bearing (rad) and linearised bearing variance (rad^2) of 2-D tracks seen from ``sensor``."""
    tm = np.asarray(track_means, float)
    tc = np.asarray(track_covs, float)
    d = tm - np.asarray(sensor, float)[None, :]
    r2 = np.einsum("ij,ij->i", d, d)
    bad = ~(r2 > 0)
    if bad.any():
        raise ValueError(f"tracks at the sensor position have no bearing: indices "
                         f"{np.flatnonzero(bad)[:10]}")
    j = np.stack([-d[:, 1], d[:, 0]], axis=1) / r2[:, None]
    var = np.einsum("ni,nij,nj->n", j, tc, j)
    return np.arctan2(d[:, 1], d[:, 0]), var


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def gate_bearings(track_means, track_covs, sensor, bearings, bearing_sigmas, *,
                  threshold: float | None = None, prob: float | None = None,
                  return_d2: bool = False):
    """Pairs (track_idx, report_idx) whose bearing residual passes the 1-D gate, sorted.

    track_means (N, 2) metres, track_covs (N, 2, 2), sensor (2,), bearings (M,) rad,
    bearing_sigmas (M,) rad. Exactly one of ``threshold`` (gamma) or ``prob``.
    """
    tm = np.asarray(track_means, float)
    tc = np.asarray(track_covs, float)
    sensor = np.asarray(sensor, float)
    theta = np.asarray(bearings, float)
    sig = np.asarray(bearing_sigmas, float)
    if tm.ndim != 2 or tm.shape[1] != 2 or tc.shape != (len(tm), 2, 2):
        raise ValueError(f"track_means must be (N, 2) and track_covs (N, 2, 2); got {tm.shape},"
                         f" {tc.shape}")
    if sensor.shape != (2,) or not np.all(np.isfinite(sensor)):
        raise ValueError(f"sensor must be a finite (2,) position, got {sensor!r}")
    if theta.ndim != 1 or sig.shape != theta.shape:
        raise ValueError(f"bearings and bearing_sigmas must be (M,), got {theta.shape}, "
                         f"{sig.shape}")
    for name, a in (("bearings", theta), ("bearing_sigmas", sig)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} has non-finite values at {np.flatnonzero(~np.isfinite(a))[:10]}")
    if np.any(sig <= 0):
        raise ValueError(f"bearing_sigmas must be > 0; bad at {np.flatnonzero(sig <= 0)[:10]}")
    if (threshold is None) == (prob is None):
        raise ValueError("give exactly one of threshold= or prob=")
    gamma = gate_threshold(prob, 1) if prob is not None else float(threshold)
    if not (np.isfinite(gamma) and gamma >= 0):
        raise ValueError(f"threshold must be finite and >= 0, got {threshold!r}")
    check_gaussians(tm, tc, "gate_bearings", means_name="track_means", covs_name="track_covs")
    beta, var = track_bearings(tm, tc, sensor)
    out_t, out_r = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for members in _buckets(var):
        t, r = _bucket_candidates(beta[members], var[members], theta, sig, gamma)
        out_t.append(members[t])
        out_r.append(r)
    t_idx, r_idx = np.concatenate(out_t), np.concatenate(out_r)
    d2 = _wrap(theta[r_idx] - beta[t_idx]) ** 2 / (var[t_idx] + sig[r_idx] ** 2)
    keep = d2 <= gamma
    t_idx, r_idx, d2 = t_idx[keep], r_idx[keep], d2[keep]
    o = np.lexsort((r_idx, t_idx))
    return (t_idx[o], r_idx[o], d2[o]) if return_d2 else (t_idx[o], r_idx[o])


def _buckets(var: np.ndarray) -> list[np.ndarray]:
    """Track indices grouped so that angular sigmas within a group differ by <= 2x."""
    s = np.sqrt(var)
    pos = s > 0
    groups = [np.flatnonzero(~pos)] if (~pos).any() else []
    if pos.any():
        k = np.floor(np.log(s[pos] / s[pos].min()) / np.log(_BUCKET_RATIO)).astype(np.int64)
        idx = np.flatnonzero(pos)
        groups += [idx[k == b] for b in np.unique(k)]
    return groups


def _bucket_candidates(beta, var, theta, sig, gamma):
    """Candidate (local track, report) pairs: tracks sorted by bearing, one interval per report
    (two when it wraps across +-pi; all tracks when it spans the circle)."""
    order = np.argsort(beta)
    b_sorted = beta[order]
    n = len(b_sorted)
    half = np.sqrt(gamma * (var.max() + sig**2)) * (1 + RADIUS_SLACK) + 1e-12
    theta = _wrap(theta)
    lo, hi = theta - half, theta + half
    starts, stops, reps = [], [], []
    full = half >= np.pi
    for shift in (-2 * np.pi, 0.0, 2 * np.pi):
        a = np.searchsorted(b_sorted, lo + shift, side="left")
        b = np.searchsorted(b_sorted, hi + shift, side="right")
        use = ~full & (b > a)
        starts.append(a[use])
        stops.append(b[use])
        reps.append(np.flatnonzero(use))
    whole = np.flatnonzero(full)
    starts.append(np.zeros(whole.size, np.int64))
    stops.append(np.full(whole.size, n, np.int64))
    reps.append(whole)
    start, stop, rep = (np.concatenate(x) for x in (starts, stops, reps))
    counts = stop - start
    r = np.repeat(rep, counts)
    pos = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) \
        + np.repeat(start, counts)
    return order[pos], r
