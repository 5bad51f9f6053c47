"""Constant-velocity motion for gating: project track states (x, y[, z], vx, vy[, vz]) in metres
and m/s, with white-noise-acceleration process noise of spectral density q (m^2/s^3), to other
times (seconds), and bound how far a track's gate can reach within a time window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from tracker.gating.exact import lambda_max_bound
from tracker.models.motion import cv_cov_entry, cv_predict


@njit(cache=True, inline="always")
def projected_cov_entry(tcov, i, r, s, dt, q, dim, moving):
    """Entry (r, s) of track i's position covariance projected by dt seconds: the position block
    of F P Fᵀ + Q(dt) (:func:`tracker.models.motion.cv_cov_entry`), or P itself for static tracks."""
    if moving:
        return cv_cov_entry(tcov, i, r, s, dt, q, dim)
    return tcov[i, r, s]


def _cv_arrays(means, covs, dt, q) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n = means.shape[0]
    return (np.ascontiguousarray(means, dtype=float), np.ascontiguousarray(covs, dtype=float),
            np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=float), (n,))),
            np.ascontiguousarray(np.broadcast_to(np.asarray(q, dtype=float), (n,))))


def project(means: np.ndarray, covs: np.ndarray, dt: np.ndarray | float,
            q: np.ndarray | float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, dim) and position covariances (N, dim, dim) of CV states moved by dt (s)."""
    pos, cov = cv_predict(*_cv_arrays(means, covs, dt, q), dim)
    return np.ascontiguousarray(pos[:, :dim]), np.ascontiguousarray(cov[:, :dim, :dim])


def project_states(means: np.ndarray, covs: np.ndarray, dt: np.ndarray | float,
                   q: np.ndarray | float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Full CV states (N, 2d) and covariances (N, 2d, 2d) moved by dt (s): F x and F P Fᵀ + Q(dt),
    Q's cross term signed (see :mod:`tracker.models.motion`)."""
    return cv_predict(*_cv_arrays(means, covs, dt, q), dim)


@dataclass(frozen=True)
class ReachBound:
    """Per-track bound on the gate's spatial spread after |dt| seconds (metres).

    sqrt(lambda_max(P_pos(dt))) <= s_p + |dt| s_v + sqrt(q |dt|^3 / 3): the standard deviation
    along any direction is a norm, so it obeys the triangle inequality over the summands of
    p + dt v, and the process noise adds its own eigenvalue.
    """

    s_p: np.ndarray
    s_v: np.ndarray
    q: np.ndarray

    @classmethod
    def from_covs(cls, covs: np.ndarray, q, dim: int, moving: bool) -> ReachBound:
        """From state covariances (N, d, d) static or (N, 2d, 2d) CV, and q (scalar or (N,))."""
        s_p = np.sqrt(lambda_max_bound(np.ascontiguousarray(covs[:, :dim, :dim])))
        s_v = (np.sqrt(lambda_max_bound(np.ascontiguousarray(covs[:, dim:, dim:])))
               if moving else np.zeros_like(s_p))
        return cls(s_p, s_v, np.broadcast_to(np.asarray(q, dtype=float), s_p.shape))

    def take(self, rows: np.ndarray) -> ReachBound:
        """The bounds of tracks ``rows``."""
        return ReachBound(self.s_p[rows], self.s_v[rows], self.q[rows])

    def sigma(self, abs_dt: np.ndarray | float, rows=slice(None)) -> np.ndarray:
        """Upper bound on sqrt(lambda_max) of the position covariance of tracks ``rows`` after
        |dt| seconds."""
        abs_dt = np.asarray(abs_dt, dtype=float)
        return (self.s_p[rows] + abs_dt * self.s_v[rows]
                + np.sqrt(self.q[rows] * abs_dt ** 3 / 3.0))


def speed(means: np.ndarray, dim: int) -> np.ndarray:
    """Speed |v| (m/s) of each CV state."""
    return np.sqrt(np.einsum("ij,ij->i", means[:, dim:], means[:, dim:]))


def max_abs_dt(track_times: np.ndarray, t_lo: float, t_hi: float) -> np.ndarray:
    """Largest |t - t_track| over t in [t_lo, t_hi], per track (seconds)."""
    return np.maximum(np.abs(t_lo - track_times), np.abs(t_hi - track_times))


def ball_volume(dim: int) -> float:
    """Volume of the unit ball in ``dim`` dimensions (the paper's gamma(l))."""
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1)
