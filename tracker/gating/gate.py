"""Gate position reports against tracks without forming every track/report pair.

A pair (track i, report j) gates when the report lies inside the track's predicted gate:
  d^2 = dX^T (P + R)^-1 dX <= gamma            (threshold / gate probability form), or
  S_ij = exp(-d^2/2) / ((2 pi)^(d/2) sqrt(det(P + R))) >= C   (paper 2, eq. 1-2, score form),
with dX the report minus the track projected to the report's own time and P that projection's
position covariance. A Euclidean coarse gate (radius from the largest eigenvalues, never smaller
than the exact gate) finds the candidates on a bucketed uniform grid; the exact test runs fused
in the same numba kernel. Positions in metres, times in seconds, velocities in m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import chi2

from tracker.gating.costmodel import DEFAULT_CONSTANTS, Choice, CostConstants, choose
from tracker.gating.exact import RADIUS_SLACK, lambda_max_bound, log_det
from tracker.gating.grid import (
    build_grid,
    counting_order,
    query_grid,
    query_radii,
    sorted_pairs,
    spatial_order,
    take_rows,
)
from tracker.gating.reach import ReachBound, max_abs_dt, speed
from tracker.gating.scene import Scene

_MAX_BUCKETS = 6
# Queries sampled (evenly spaced) for the medians that set the buckets and the cell edge.
_SAMPLE = 4096


def gate_threshold(prob: float, dim: int) -> float:
    """gamma such that a d^2 ~ chi^2(dim) variable falls below it with probability ``prob``."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"gate probability must lie in (0, 1), got prob={prob!r}")
    return float(chi2.ppf(prob, dim))


class Gater(Protocol):
    """Anything that returns the gated pairs like :func:`gate`: (track_idx, report_idx) int64
    arrays sorted by (track, report), for static (N, d) or CV (N, 2d) tracks valid at
    ``track_times`` (s) with process noise q (m²/s³), reports (M, d) at ``report_times`` (s), and
    the gate d² <= ``threshold``."""

    def __call__(self, track_means: ArrayLike, track_covs: ArrayLike, report_means: ArrayLike,
                 report_covs: ArrayLike, threshold: float | None = None, *,
                 report_times: ArrayLike | None = None, track_times: ArrayLike | float = 0.0,
                 process_noise: ArrayLike | float = 0.0) -> tuple[np.ndarray, np.ndarray]: ...


def gate(track_means: ArrayLike, track_covs: ArrayLike, report_means: ArrayLike,
         report_covs: ArrayLike, threshold: float | None = None, *, prob: float | None = None,
         min_score: float | None = None, return_d2: bool = False,
         report_times: ArrayLike | None = None, track_times: ArrayLike | float = 0.0,
         process_noise: ArrayLike | float = 0.0, n_projections: int | str = "auto",
         orientation: str = "auto", buckets: int | str = "auto",
         constants: CostConstants = DEFAULT_CONSTANTS):
    """Pairs (track_idx, report_idx) that pass the exact gate, sorted by (track, report).

    Static: track_means (N, d), track_covs (N, d, d), report_means (M, d), report_covs (M, d, d)
    with d in {2, 3}. Moving: track_means (N, 2d) constant-velocity states (x, y[, z], vx, vy[, vz])
    valid at ``track_times`` (scalar or (N,), s), track_covs (N, 2d, 2d), ``report_times`` (M,)
    and white-noise-acceleration density ``process_noise`` q (scalar or (N,), m^2/s^3); each
    pair is tested at the report's own time (static tracks ignore ``report_times``).
    Exactly one of ``threshold`` (gamma on d^2),
    ``prob`` (gate probability, gamma = chi2.ppf(prob, d)) or ``min_score`` (C in S_ij >= C).

    ``n_projections``: number M_D of track-file projections across the scan ("auto": the cost
    model in :mod:`tracker.gating.costmodel`). ``orientation``: "reports" builds the grids on reports
    binned by time and queries them with projected tracks, "tracks" builds one grid per
    projection on the tracks and queries it with reports (paper eq. 5 vs 6); "auto" asks the
    cost model. ``buckets``: radius buckets of the gridded set ("auto": only when radii spread).
    ``constants``: the cost model's seconds per unit of work; the shipped defaults unless you
    measured your machine (``terrain-track calibrate --out costs.json``, then
    ``constants=CostConstants.read("costs.json")``). gate() itself never calibrates.
    Returns (track_idx, report_idx) int64 arrays, plus d^2 when ``return_d2``.
    """
    scene = Scene.validate(track_means, track_covs, report_means, report_covs, report_times,
                           track_times, process_noise)
    return gate_checked(scene, threshold, prob=prob, min_score=min_score, return_d2=return_d2,
                        n_projections=n_projections, orientation=orientation, buckets=buckets,
                        constants=constants)


def gate_unchecked(track_means: np.ndarray, track_covs: np.ndarray, report_means: np.ndarray,
                   report_covs: np.ndarray, threshold: float | None = None, *,
                   report_times: np.ndarray | None = None, track_times: np.ndarray | float = 0.0,
                   process_noise: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A :class:`Gater` for arrays the caller has validated already (the tracker's hypotheses and
    checked reports): :func:`gate`'s pairs without checking the arrays again."""
    return gate_checked(Scene.assume_valid(track_means, track_covs, report_means, report_covs, report_times,
                                           track_times, process_noise), threshold)


def gate_checked(sc: Scene, threshold: float | None = None, *, prob: float | None = None,
                 min_score: float | None = None, return_d2: bool = False,
                 n_projections: int | str = "auto", orientation: str = "auto",
                 buckets: int | str = "auto", constants: CostConstants = DEFAULT_CONSTANTS):
    """:func:`gate` on a scene whose arrays were validated already (:meth:`Scene.validate`, or
    :meth:`Scene.assume_valid` for arrays the caller checked itself): the same pairs, without
    checking the arrays again. Options as in :func:`gate`."""
    if orientation not in ("auto", "reports", "tracks"):
        raise ValueError(f"orientation must be 'auto', 'reports' or 'tracks', got {orientation!r}")
    if n_projections != "auto" and not (isinstance(n_projections, int | np.integer)
                                        and n_projections >= 1):
        raise ValueError(f"n_projections must be an int >= 1 or 'auto', got {n_projections!r}")
    if buckets != "auto" and not (isinstance(buckets, int | np.integer) and buckets >= 1):
        raise ValueError(f"buckets must be an int >= 1 or 'auto', got {buckets!r}")
    gamma, w_logdet = _threshold(threshold, prob, min_score, sc.dim)
    nt, nr = sc.tpos.shape[0], sc.rpos.shape[0]
    if nt == 0 or nr == 0:
        return _result(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), return_d2)
    static_on_reports = not sc.moving and orientation != "tracks"
    if static_on_reports:  # tracks query in spatial order: permute them before any per-track work
        t_perm = spatial_order(sc.tpos)
        sc = replace(sc, tpos=take_rows(sc.tpos, t_perm), tcov=take_rows(sc.tcov, t_perm))
    plan = _plan(sc, gamma, w_logdet, n_projections, orientation, constants)
    by_bin, bin_start = (counting_order(plan.bin_of_report, plan.m) if plan.m > 1
                         else (None, np.array([0, nr])))
    if plan.on_reports and not static_on_reports:  # at mid-scan, a permuted copy
        t_mid = 0.5 * (sc.rtime.min() + sc.rtime.max())
        t_perm = spatial_order(sc.tpos + (t_mid - sc.ttime)[:, None] * sc.tvel)
        sc = replace(sc, tpos=take_rows(sc.tpos, t_perm), tcov=take_rows(sc.tcov, t_perm),
                     tvel=take_rows(sc.tvel, t_perm), ttime=sc.ttime[t_perm], tq=sc.tq[t_perm])
        plan = replace(plan, speed=plan.speed[t_perm], reach=plan.reach.take(t_perm),
                       gamma_t=plan.gamma_t[t_perm])
    elif not plan.on_reports:  # each bin's reports query in spatial order: a copy permuted so that bins are slices
        r_order = spatial_order(sc.rpos)
        r_perm = (r_order if plan.m == 1 else
                  r_order[counting_order(plan.bin_of_report[r_order], plan.m)[0]])
        rank = np.empty(nr, np.int64)  # position of a report among its bin's ids, ascending
        rank[np.arange(nr) if by_bin is None else by_bin] = (
            np.arange(nr) - np.repeat(bin_start[:-1], np.diff(bin_start)))
        sc = replace(sc, rpos=take_rows(sc.rpos, r_perm), rcov=take_rows(sc.rcov, r_perm),
                     rtime=sc.rtime[r_perm])
        plan = replace(plan, lam_r=plan.lam_r[r_perm], gamma_r=plan.gamma_r[r_perm])
    parts = []
    for k in range(plan.m):
        s, e = bin_start[k], bin_start[k + 1]
        if s == e:
            continue
        if plan.on_reports:  # one bin: its reports are every report, in order
            queries = (slice(0, nr) if by_bin is None else by_bin[s:e], t_perm, t_perm)
        else:
            queries = (slice(s, e), r_perm[s:e], rank[r_perm[s:e]])
        parts.append(_gate_bin(sc, plan, k, *queries, gamma, w_logdet, buckets))
    if not parts:
        return _result(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), return_d2)
    if len(parts) == 1 and plan.on_reports:  # one grid queried by tracks: sorted already
        return _result(*parts[0], return_d2)
    t_idx, r_idx, d2 = (parts[0] if len(parts) == 1 else
                        [np.concatenate([p[c] for p in parts]) for c in range(3)])
    return _result(*sorted_pairs(t_idx, r_idx, d2, nt, nr), return_d2)


def _result(t_idx, r_idx, d2, return_d2):
    return (t_idx, r_idx, d2) if return_d2 else (t_idx, r_idx)


def _threshold(threshold, prob, min_score, dim) -> tuple[float, float]:
    """(gamma, w): a pair passes when d^2 <= gamma - w * ln det V."""
    given = [x is not None for x in (threshold, prob, min_score)]
    if sum(given) != 1:
        raise ValueError("give exactly one of threshold=, prob= or min_score=")
    if threshold is not None:
        if not (np.isfinite(threshold) and threshold >= 0.0):
            raise ValueError(f"threshold must be finite and >= 0, got threshold={threshold!r}")
        return float(threshold), 0.0
    if prob is not None:
        return gate_threshold(prob, dim), 0.0
    if not (np.isfinite(min_score) and min_score > 0.0):
        raise ValueError(f"min_score must be finite and > 0, got min_score={min_score!r}")
    return -2.0 * math.log(min_score) - dim * math.log(2.0 * math.pi), 1.0


@dataclass(frozen=True)
class _Plan:
    """Time partition of the scan: m bins of half-width w (s), centre times, bin of each report."""

    m: int
    t_lo: float
    width: float
    bin_of_report: np.ndarray
    on_reports: bool
    reach: ReachBound
    speed: np.ndarray
    lam_r: np.ndarray
    gamma_r: np.ndarray   # per-report bound on the pair's gamma (score form), else gamma
    gamma_t: np.ndarray   # per-track bound on the pair's gamma (static score form), else inf
    coord_slack: float
    choice: Choice | None = None  # the cost model's prediction, when asked


def plan_choice(sc: Scene, threshold: float,
                constants: CostConstants = DEFAULT_CONSTANTS) -> Choice:
    """The cost model's pick (M_D, orientation, predicted seconds per M) for a moving scene gated
    at d² <= ``threshold``, as ``gate(..., n_projections="auto", orientation="auto")`` makes it."""
    if not sc.moving:
        raise ValueError("plan_choice: static tracks have a single projection; pass (N, 2d) CV tracks")
    return _plan(sc, threshold, 0.0, "auto", "auto", constants).choice


def _plan(sc: Scene, gamma: float, w_logdet: float, n_projections, orientation,
          constants: CostConstants) -> _Plan:
    lam_r = lambda_max_bound(sc.rcov)
    reach = ReachBound.from_covs(sc.tcov, sc.tq, sc.dim, sc.moving)
    spd = speed(np.hstack([sc.tpos, sc.tvel]), sc.dim) if sc.moving else np.zeros(len(sc.tpos))
    gamma_r = gamma - w_logdet * log_det(sc.rcov) if w_logdet else np.full(len(lam_r), gamma)
    if w_logdet and not sc.moving:
        # det(P + R) >= det P as well, so the track side bounds the pair's gamma too.
        gamma_t = gamma - log_det(np.ascontiguousarray(sc.tcov))
    else:
        gamma_t = np.full(len(spd), np.inf)
    scale = max(float(np.abs(sc.tpos).max()), float(np.abs(sc.rpos).max()), 1.0)
    if sc.moving:
        t_lo, t_hi = float(sc.rtime.min()), float(sc.rtime.max())
        scale += float(spd.max()) * (t_hi - t_lo + np.abs(sc.ttime - t_lo).max())
    coord_slack = 64.0 * np.finfo(float).eps * scale
    if not sc.moving:
        return _Plan(1, 0.0, 0.0, np.zeros(len(lam_r), np.int64), orientation != "tracks",
                     reach, spd, lam_r, gamma_r, gamma_t, coord_slack)
    tau = t_hi - t_lo
    choice = None
    if n_projections == "auto" or orientation == "auto":
        choice = choose(sc, reach, spd, lam_r, float(np.max(gamma_r)), tau, constants)
        m = choice.m if n_projections == "auto" else int(n_projections)
        on_reports = choice.on_reports if orientation == "auto" else orientation == "reports"
    else:
        m, on_reports = int(n_projections), orientation == "reports"
    m = min(m, max(1, len(sc.rtime)))
    width = tau / (2 * m)
    bins = np.minimum(((sc.rtime - t_lo) / (2 * width)).astype(np.int64), m - 1) if tau > 0 \
        else np.zeros(len(sc.rtime), np.int64)
    return _Plan(m, t_lo, width, bins, on_reports, reach, spd, lam_r, gamma_r, gamma_t,
                 coord_slack, choice)


def _bucket_ids(key: np.ndarray, buckets) -> tuple[np.ndarray, int]:
    """Buckets of equal width in log(key) (a radius); one when the spread is small ("auto")."""
    if key.size == 0:
        return np.zeros(0, np.int64), 1
    lo, hi = float(key.min()), float(key.max())
    if buckets == "auto":
        # the median of an evenly spaced sample: only the speed depends on it, and an exact one
        # costs a full partition (~10 ms per 1 M keys)
        med = float(np.median(key[::max(1, key.size // _SAMPLE)]))
        k = 1 if hi <= 4.0 * med or lo <= 0.0 else min(_MAX_BUCKETS, int(np.log2(hi / lo)) + 1)
    else:
        k = int(buckets)
    if k == 1 or lo <= 0.0 or hi <= lo * (1.0 + 1e-9):
        return np.zeros(key.size, np.int64), 1
    ids = np.floor(np.log(key / lo) / np.log(hi / lo) * k).astype(np.int64)
    return np.minimum(ids, k - 1), k


def _gate_bin(sc: Scene, plan: _Plan, k: int, reports: np.ndarray | slice, q_ids: np.ndarray,
              q_rank: np.ndarray, gamma: float, w_logdet: float, buckets):
    """Exact pairs between every track and the reports of time bin k (rows ``reports`` of the
    scene), as (track id, report id, d²) grouped by the querying object's id, ascending.

    The queries (every track when ``plan.on_reports``, else the bin's reports) are the
    scene's rows in order (the caller put them in spatial order: the kernel is bound by memory
    latency, and neighbouring queries then touch neighbouring cells); ``q_ids`` are their ids,
    ``q_rank`` their ranks among them. Grid points are identified by their scene row, which
    is their id (the gridded side is never permuted)."""
    t_mid = plan.t_lo + (2 * k + 1) * plan.width
    w = plan.width * (1.0 + RADIUS_SLACK)
    if sc.moving:
        dt_max = max_abs_dt(sc.ttime, t_mid - w, t_mid + w)
        sig = plan.reach.sigma(dt_max)
        tpos_k = sc.tpos + (t_mid - sc.ttime)[:, None] * sc.tvel
    else:  # sigma(0) is s_p itself
        sig, tpos_k = plan.reach.s_p, sc.tpos
    lam_r = plan.lam_r[reports]
    g_r = plan.gamma_r[reports]
    if plan.on_reports:
        bid, nb = _bucket_ids(np.sqrt(lam_r), buckets)
        lam_b = _bucket_max(lam_r, bid, nb)
        g_b = _bucket_max(g_r, bid, nb)
        rad = query_radii(sig * sig, lam_b, plan.speed, np.full(nb, w), plan.gamma_t, g_b,
                          plan.coord_slack)
        cell = _bucket_cell(rad)
        grid = build_grid(sc.rpos[reports], None if isinstance(reports, slice) else reports,
                          bid, nb, cell)
        rows = grid.members
        return query_grid(
            np.ascontiguousarray(tpos_k), rad, True, q_ids, q_rank, rows, *_grid_args(grid),
            sc.tpos, sc.tvel, sc.tcov, sc.ttime, sc.tq, take_rows(sc.rpos, rows),
            take_rows(sc.rcov, rows), sc.rtime[rows] if sc.moving else sc.rtime[:rows.size],
            sc.moving, gamma, w_logdet)
    reach = sig + w * plan.speed
    bid, nb = _bucket_ids(reach, buckets)
    sig_b = _bucket_max(sig, bid, nb)
    spd_b = _bucket_max(plan.speed, bid, nb)
    g_t = _bucket_max(plan.gamma_t, bid, nb)  # loosest track-side bound per bucket
    delta = np.abs(sc.rtime[reports] - t_mid) if sc.moving else np.zeros(lam_r.size)
    rad = query_radii(lam_r, sig_b * sig_b, delta, spd_b, g_r, g_t, plan.coord_slack)
    cell = _bucket_cell(rad)
    grid = build_grid(tpos_k, None, bid, nb, cell)
    rows = grid.members
    return query_grid(
        sc.rpos[reports], rad, False, q_ids, q_rank, rows, *_grid_args(grid),
        take_rows(sc.tpos, rows), take_rows(sc.tvel, rows), take_rows(sc.tcov, rows),
        sc.ttime[rows], sc.tq[rows], sc.rpos[reports], sc.rcov[reports], sc.rtime[reports],
        sc.moving, gamma, w_logdet)


def _grid_args(grid):
    return (grid.origin, grid.cell, grid.dims, grid.seg, grid.keys, grid.dense, grid.table_seg,
            grid.table)


def _bucket_max(x: np.ndarray, bid: np.ndarray, nb: int) -> np.ndarray:
    """Max of x per bucket; 0 for empty buckets (the grid skips those)."""
    if nb == 1:
        return np.array([float(x.max())]) if x.size else np.zeros(1)
    out = np.full(nb, -np.inf)
    np.maximum.at(out, bid, x)
    out[np.isneginf(out)] = 0.0
    return out


def _bucket_cell(rad: np.ndarray) -> np.ndarray:
    """Cell edge per bucket: the median query radius (cells visited vs candidates scanned),
    from an evenly spaced sample of the queries."""
    cells = np.empty(rad.shape[1])
    step = max(1, rad.shape[0] // _SAMPLE)
    for b in range(rad.shape[1]):
        r = rad[::step, b][rad[::step, b] > 0.0]
        cells[b] = float(np.median(r)) if r.size else 1.0
    return cells
