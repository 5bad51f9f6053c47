"""Paper 2's cost model (eq. A8) for choosing the number M_D of track-file projections across a
scan, and whether to build the search grids on tracks (one per projection, eq. 5) or on reports
binned by time (eq. 6). Its constants (seconds per unit of work) ship as :data:`DEFAULT_CONSTANTS`;
:func:`tracker.gating.calibrate.calibrate` (``terrain-track calibrate``) measures them on another
machine by timing gate() itself, and :meth:`CostConstants.read` loads the result for ``gate(...,
constants=...)``. Nothing here reads or writes files on its own.

With a grid hash the paper's log N factors (tree build and descent) become constants, and the
terms of eq. A8 group by what is measurable:

  tracks  : C = M N_T b_t + N_R r_t + C_c N_cand,tracks(M)     b_t = C_e + C_d,  r_t ~ C_s
  reports : C = M N_T b_r + N_R r_r + C_c N_cand,reports(M)    b_r = C_e + C_s,  r_r ~ C_d

(b: per track and projection; r: per report, including the per-object work common to every M).
N_cand(M) = N_T N_R / V_region * <ball volume of the search radius>: when reports query a
deflated track grid ("tracks"), radius R0_max + a_max |dT| with |dT| uniform on [0, tau/(2M)]
(eq. A4); when tracks query a bin of reports ("reports"), each track's own R0 + a tau/(2M).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from common.atomic import atomic_paths
from tracker.gating.grid import bounding_box
from tracker.gating.reach import ReachBound, ball_volume, max_abs_dt
from tracker.gating.scene import Scene

_M_MAX = 128
_SAMPLE = 500


@dataclass(frozen=True)
class CostConstants:
    """Seconds per track and projection (b_tracks, b_reports), per report (r_tracks,
    r_reports) for grids on tracks / on reports, and per expected candidate pair (c_c)."""

    b_tracks: float
    b_reports: float
    r_tracks: float
    r_reports: float
    c_c: float

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"CostConstants.{f.name} must be a positive number of seconds, got {v!r}")

    @classmethod
    def read(cls, path: str | os.PathLike) -> CostConstants:
        """Constants from a JSON file written by :meth:`write` (``terrain-track calibrate``)."""
        return cls(**json.loads(Path(path).read_text(encoding="utf-8")))

    def write(self, path: str | os.PathLike) -> None:
        """Write the constants as JSON, atomically (a failed write leaves the old file)."""
        with atomic_paths(path) as (tmp,):
            tmp.write_text(json.dumps(asdict(self), indent=1) + "\n", encoding="utf-8")


DEFAULT_CONSTANTS = CostConstants(b_tracks=1.82e-7, b_reports=1.63e-7, r_tracks=6.31e-7,
                                  r_reports=5.46e-7, c_c=2.70e-8)
"""Measured by :func:`tracker.gating.calibrate.calibrate` on the development machine (2 cores,
2 numba threads, numba 0.68.1; quiet run of 2026-12-03, C_c within 1.5 % over three runs). Only the choice of M_D and orientation depends on them, never the
gated pairs; a machine whose costs differ a lot gates faster with its own (``terrain-track calibrate``)."""


@dataclass(frozen=True)
class Choice:
    """The cost model's pick and its predicted costs (s) per M = 1.. for both orientations."""

    m: int
    on_reports: bool
    cost_tracks: np.ndarray
    cost_reports: np.ndarray


def expected_volume(m: np.ndarray, r0: np.ndarray, a: np.ndarray, tau: float,
                    dim: int) -> np.ndarray:
    """Mean search-ball volume (m^dim) per track/report pair for each M in ``m`` (eq. A4)."""
    w = (tau / (2.0 * np.asarray(m, float)))[:, None]
    aw = a[None, :] * w
    lin = np.where(aw > 1e-12 * np.maximum(r0[None, :], 1e-300),
                   ((r0 + aw) ** (dim + 1) - r0 ** (dim + 1)) / ((dim + 1) * np.maximum(aw, 1e-300)),
                   r0[None, :] ** dim)
    return ball_volume(dim) * lin.mean(axis=1)


def predict(n_t: int, n_r: int, n_cand_tracks: np.ndarray, n_cand_reports: np.ndarray,
            m: np.ndarray, c: CostConstants) -> tuple[np.ndarray, np.ndarray]:
    """Predicted seconds per M for (grids on tracks, grids on reports)."""
    on_tracks = m * n_t * c.b_tracks + n_r * c.r_tracks + c.c_c * n_cand_tracks
    on_reports = m * n_t * c.b_reports + n_r * c.r_reports + c.c_c * n_cand_reports
    return on_tracks, on_reports


def md0_closed_form(n_t: int, n_r: int, rho: float, a: float, tau: float, dim: int,
                    c: CostConstants) -> float:
    """Eq. A9 for this model (long-scan limit a tau >> R0, grid on tracks):
    C(M) ~ M K1 + K2 M^-l is least at M_D0 = (l K2 / K1)^(1/(l+1)), with K1 = N_T b_tracks
    (= N_T (C_e + C_d)) and K2 = C_c N_R rho gamma(l) (a tau / 2)^l / (l + 1)."""
    k1 = n_t * c.b_tracks
    k2 = c.c_c * n_r * rho * ball_volume(dim) * (a * tau / 2.0) ** dim / (dim + 1)
    return float((dim * k2 / k1) ** (1.0 / (dim + 1)))


def expected_candidates(sc: Scene, reach: ReachBound, spd: np.ndarray, lam_r: np.ndarray, gamma: float,
                        tau: float, m: np.ndarray, deflate: bool) -> np.ndarray:
    """Expected candidate pairs for each M in ``m`` (from a sample of tracks)."""
    return _candidates(_sampled_reach(sc, reach, spd, lam_r, gamma, tau), sc.dim, tau, m, deflate)


def _sampled_reach(sc: Scene, reach: ReachBound, spd: np.ndarray, lam_r: np.ndarray, gamma: float,
                   tau: float) -> tuple[np.ndarray, np.ndarray, int, float]:
    """What :func:`expected_candidates` needs of a scene for any M and either orientation: a sample
    of tracks' gate radii R0 and speeds a, N_T N_R, and the scene's volume (padded by the mean R0)."""
    n_t, n_r = sc.tpos.shape[0], sc.rpos.shape[0]
    t_mid = float(sc.rtime.min()) + tau / 2
    t_lo, t_hi = bounding_box(sc.tpos + (t_mid - sc.ttime)[:, None] * sc.tvel)
    r_lo, r_hi = bounding_box(sc.rpos)
    extent = np.maximum(np.maximum(t_hi, r_hi) - np.minimum(t_lo, r_lo), 1e-9)
    pick = np.random.default_rng(0).choice(n_t, size=min(n_t, _SAMPLE), replace=False)
    sig = reach.sigma(max_abs_dt(sc.ttime[pick], t_mid - tau / 2, t_mid + tau / 2), pick)
    r0 = np.sqrt(gamma * (sig**2 + float(np.mean(lam_r))))
    return r0, spd[pick], n_t * n_r, float(np.prod(extent + 2 * r0.mean()))


def _candidates(sampled: tuple[np.ndarray, np.ndarray, int, float], dim: int, tau: float, m: np.ndarray,
                deflate: bool) -> np.ndarray:
    """:func:`expected_candidates` from :func:`_sampled_reach`'s terms."""
    r0, a, pairs, volume = sampled
    if deflate:  # reports query with their own |dT| but the track bucket's largest R0 and a
        vol = expected_volume(m, np.full(1, r0.max()), np.full(1, a.max()), tau, dim)
    else:  # tracks query a whole bin: their own R0 and a, but the bin's largest |dT|
        w = tau / (2.0 * np.asarray(m, float))[:, None]
        vol = ball_volume(dim) * np.mean((r0[None, :] + a[None, :] * w) ** dim, axis=1)
    return pairs * vol / volume


def choose(sc: Scene, reach: ReachBound, spd: np.ndarray, lam_r: np.ndarray, gamma: float, tau: float,
           constants: CostConstants) -> Choice:
    """Pick M_D and the orientation minimising the predicted cost for a validated scene."""
    n_t, n_r = sc.tpos.shape[0], sc.rpos.shape[0]
    if tau <= 0.0:
        return Choice(1, True, np.zeros(1), np.zeros(1))
    m = np.arange(1, min(_M_MAX, n_r) + 1).astype(float)
    sampled = _sampled_reach(sc, reach, spd, lam_r, gamma, tau)  # once: a third of a 100k scene's choice
    cand_t = _candidates(sampled, sc.dim, tau, m, deflate=True)
    cand_r = _candidates(sampled, sc.dim, tau, m, deflate=False)
    on_tracks, on_reports = predict(n_t, n_r, cand_t, cand_r, m, constants)
    i_t, i_r = int(np.argmin(on_tracks)), int(np.argmin(on_reports))
    if on_reports[i_r] <= on_tracks[i_t]:
        return Choice(int(m[i_r]), True, on_tracks, on_reports)
    return Choice(int(m[i_t]), False, on_tracks, on_reports)
