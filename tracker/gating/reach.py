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


@njit(cache=True, inline="always")
def projected_cov_entry(tcov, i, r, s, dt, q, dim, moving):
    """Entry (r, s) of track i's position covariance projected by dt seconds.

    P_pos(dt) = Ppp + dt (Ppv + Ppv^T) + dt^2 Pvv + q |dt|^3 / 3 I (white-noise acceleration).
    """
    v = tcov[i, r, s]
    if moving:
        v += dt * (tcov[i, r, dim + s] + tcov[i, s, dim + r]) + dt * dt * tcov[i, dim + r, dim + s]
        if r == s:
            v += q * abs(dt) ** 3 / 3.0
    return v


def project(means: np.ndarray, covs: np.ndarray, dt: np.ndarray | float,
            q: np.ndarray | float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, dim) and position covariances (N, dim, dim) of CV states moved by dt (s)."""
    dt = np.broadcast_to(np.asarray(dt, dtype=float), (means.shape[0],))
    q = np.broadcast_to(np.asarray(q, dtype=float), (means.shape[0],))
    pos = means[:, :dim] + dt[:, None] * means[:, dim:]
    ppv = covs[:, :dim, dim:]
    cov = (covs[:, :dim, :dim] + dt[:, None, None] * (ppv + ppv.transpose(0, 2, 1))
           + (dt * dt)[:, None, None] * covs[:, dim:, dim:])
    cov = cov + (q * np.abs(dt) ** 3 / 3.0)[:, None, None] * np.eye(dim)
    return pos, cov


def project_states(means: np.ndarray, covs: np.ndarray, dt: np.ndarray | float,
                   q: np.ndarray | float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Full CV states (N, 2d) and covariances (N, 2d, 2d) moved by dt (s): F x, F P F^T + Q with
    Q = q [[|dt|^3/3, |dt|^2/2], [|dt|^2/2, |dt|]] (x) I_d."""
    n = means.shape[0]
    dt = np.broadcast_to(np.asarray(dt, dtype=float), (n,))
    a = np.abs(dt)
    q = np.broadcast_to(np.asarray(q, dtype=float), (n,))
    eye = np.eye(dim)
    f = np.tile(np.eye(2 * dim), (n, 1, 1))
    f[:, :dim, dim:] = dt[:, None, None] * eye
    qm = np.zeros((n, 2 * dim, 2 * dim))
    qm[:, :dim, :dim] = (q * a**3 / 3)[:, None, None] * eye
    qm[:, :dim, dim:] = qm[:, dim:, :dim] = (q * a**2 / 2)[:, None, None] * eye
    qm[:, dim:, dim:] = (q * a)[:, None, None] * eye
    return (np.einsum("nij,nj->ni", f, means),
            np.einsum("nij,njk,nlk->nil", f, covs, f) + qm)


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
