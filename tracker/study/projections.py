"""Studying the gate's cost against the number M_D of track-file projections (paper 2, appendix A):
a brute-force baseline that tests every track/report pair, the cost model's predicted cost curve
for a scene, and measured gate() times per (orientation, M_D).

Positions in metres, times in seconds, velocities in m/s; scenes as :func:`tracker.gating.gate.gate`
takes them (static (N, d) or constant-velocity (N, 2d) tracks).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import pandas as pd

from tracker.gating.costmodel import DEFAULT_CONSTANTS, Choice, CostConstants
from tracker.gating.gate import gate, plan_choice
from tracker.gating.reach import project
from tracker.gating.scene import Scene


def brute_force_pairs(track_means, track_covs, report_means, report_covs, report_times=None, *,
                      threshold: float, track_times: float = 0.0, process_noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Every (track, report) pair with d² ≤ ``threshold``, each track projected to the report's time
    (one numpy pass over all tracks per report); sorted by (track, report) like gate()."""
    tm = np.asarray(track_means, dtype=np.float64)
    tc = np.asarray(track_covs, dtype=np.float64)
    rm = np.asarray(report_means, dtype=np.float64)
    rc = np.asarray(report_covs, dtype=np.float64)
    dim = rm.shape[1]
    moving = tm.shape[1] == 2 * dim
    if moving and report_times is None:
        raise ValueError("brute_force_pairs: constant-velocity tracks need report_times")
    times = np.zeros(len(rm)) if report_times is None else np.asarray(report_times, dtype=np.float64)
    t_out, r_out = [], []
    for j in range(len(rm)):
        if moving:
            pos, cov = project(tm, tc, times[j] - track_times, process_noise, dim)
        else:
            pos, cov = tm, tc
        dx = rm[j] - pos
        d2 = np.einsum("ni,ni->n", dx, np.linalg.solve(cov + rc[j], dx[:, :, None])[:, :, 0])
        hits = np.flatnonzero(d2 <= threshold)
        t_out.append(hits)
        r_out.append(np.full(hits.size, j, dtype=np.int64))
    t_idx = np.concatenate(t_out).astype(np.int64) if t_out else np.zeros(0, np.int64)
    r_idx = np.concatenate(r_out) if r_out else np.zeros(0, np.int64)
    order = np.lexsort((r_idx, t_idx))
    return t_idx[order], r_idx[order]


def predicted_choice(track_means, track_covs, report_means, report_covs, report_times, *,
                     threshold: float, track_times: float = 0.0, process_noise: float = 0.0,
                     constants: CostConstants = DEFAULT_CONSTANTS) -> Choice:
    """The cost model's pick for a moving scene, through the same planning path gate() takes:
    ``m``, ``on_reports`` and the predicted seconds per M = 1, 2, ... for both orientations, with
    the cost ``constants`` gate() is given."""
    return plan_choice(Scene.validate(track_means, track_covs, report_means, report_covs, report_times,
                                      track_times, process_noise), threshold, constants)


def measure_projections(track_means, track_covs, report_means, report_covs, report_times, *,
                        threshold: float, ms: Sequence[int], orientations: Sequence[str] = ("reports", "tracks"),
                        process_noise: float = 0.0, repeats: int = 2) -> pd.DataFrame:
    """Fastest wall time (s) of ``repeats`` gate() calls per (orientation, M_D), with the pair count."""
    rows = []
    for orientation in orientations:
        for m in ms:
            best, n_pairs = np.inf, -1
            for _ in range(repeats):
                t0 = time.perf_counter()
                t_idx, _ = gate(track_means, track_covs, report_means, report_covs, threshold=threshold,
                                report_times=report_times, process_noise=process_noise,
                                n_projections=int(m), orientation=orientation)
                best = min(best, time.perf_counter() - t0)
                n_pairs = int(t_idx.size)
            rows.append({"orientation": orientation, "m": int(m), "seconds": best, "pairs": n_pairs})
    return pd.DataFrame(rows)
