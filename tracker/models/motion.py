"""Motion models of the hypotheses and the tracks: static, and nearly-constant velocity (CV).

The CV model is written once, as the numba element functions :func:`cv_mean_entry` and
:func:`cv_cov_entry` that every CV prediction calls (``ConstantVelocity.predict``, gating's
projections in :mod:`tracker.gating.reach` and the association kernels in
:mod:`tracker.association.walk`). For a state (p, v) of d positions (m) and d velocities (m/s), a
step of dt seconds (either sign) is

    x' = F x,   P' = F P Fᵀ + Q(dt),   F = [[I, dt I], [0, I]],
    Q(dt) = q [[|dt|³/3 I, dt·|dt|/2 I], [dt·|dt|/2 I, |dt| I]],

with q the white-noise acceleration spectral density (m²/s³). The cross term keeps the sign of dt.
Forwards (dt > 0) it is the textbook q dt²/2. For retrodiction by τ = -dt > 0 the errors are
p(t-τ) - (p(t) - τ v(t)) = ∫_{t-τ}^{t} (s - (t-τ)) a(s) ds and v(t-τ) - v(t) = -∫_{t-τ}^{t} a(s) ds, whose
covariance is -q ∫_0^τ u du = -q τ²/2 = q dt·|dt|/2: position and velocity errors are anti-correlated
backwards in time. The diagonal blocks, variances, use |dt|.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

MOTION_STATIC = 0
MOTION_CV = 1


@njit(cache=True, inline="always")
def cv_noise_entry(r, s, dt, q, d):
    """Entry (r, s) of Q(dt) for a (2d, 2d) CV state (m², m²/s or m²/s²)."""
    if r % d != s % d:
        return 0.0
    adt = abs(dt)
    if r < d and s < d:
        return q * adt**3 / 3.0
    if r >= d and s >= d:
        return q * adt
    return q * dt * adt / 2.0


@njit(cache=True, inline="always")
def cv_mean_entry(x, i, r, dt, d):
    """Entry r of F x for state i of the (N, 2d) states x moved by dt seconds."""
    if r < d:
        return x[i, r] + dt * x[i, d + r]
    return x[i, r]


@njit(cache=True, inline="always")
def cv_cov_entry(P, i, r, s, dt, q, d):
    """Entry (r, s) of F P Fᵀ + Q(dt) for covariance i of the (N, 2d, 2d) covariances P.

    F P Fᵀ is formed as rows first (P[r] + dt P[r + d]), then columns: the association's
    posteriors are bitwise those of the matrix-product order it always used.
    """
    v = P[i, r, s]
    if r < d:
        v += dt * P[i, d + r, s]
    if s < d:
        w = P[i, r, d + s]
        if r < d:
            w += dt * P[i, d + r, d + s]
        v += dt * w
    return v + cv_noise_entry(r, s, dt, q, d)


@njit(cache=True)
def cv_predict(means, covs, dt, q, d):
    """F x and F P Fᵀ + Q(dt) for (N, 2d) states, (N, 2d, 2d) covariances, dt (N,) s, q (N,)."""
    n, sd = means.shape
    out_m = np.empty((n, sd))
    out_c = np.empty((n, sd, sd))
    for i in range(n):
        for r in range(sd):
            out_m[i, r] = cv_mean_entry(means, i, r, dt[i], d)
            for s in range(sd):
                out_c[i, r, s] = cv_cov_entry(covs, i, r, s, dt[i], q[i], d)
    return out_m, out_c


@dataclass(frozen=True)
class Static:
    """Targets do not move (paper 1): the state is the position."""

    pos_dim: int = 2

    @property
    def state_dim(self) -> int:
        return self.pos_dim

    @property
    def code(self) -> tuple[int, float, float]:
        """(kind, q, velocity_std) for the numba kernels."""
        return MOTION_STATIC, 0.0, 0.0


@dataclass(frozen=True)
class ConstantVelocity:
    """Nearly-constant velocity (paper 1, section 7): white-noise acceleration of spectral density
    ``q`` (m²/s³); a new hypothesis starts at zero velocity with standard deviation ``velocity_std``
    (m/s) per axis, uncorrelated with its position. The formula is in the module docstring."""

    q: float = 0.1
    velocity_std: float = 10.0
    pos_dim: int = 2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.q) and self.q >= 0):
            raise ValueError(f"ConstantVelocity.q must be finite and >= 0 m^2/s^3, got {self.q}")
        if not (math.isfinite(self.velocity_std) and self.velocity_std > 0):
            raise ValueError(f"ConstantVelocity.velocity_std must be positive m/s, got {self.velocity_std}")

    @property
    def state_dim(self) -> int:
        return 2 * self.pos_dim

    @property
    def code(self) -> tuple[int, float, float]:
        return MOTION_CV, float(self.q), float(self.velocity_std)

    def predict(self, means: np.ndarray, covs: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Kalman time update of (N, 2d) states by dt (N,) seconds: F x and F P Fᵀ + Q(dt), symmetrised."""
        n = means.shape[0]
        dt = np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=np.float64), (n,)))
        m, P = cv_predict(np.ascontiguousarray(means, dtype=np.float64),
                          np.ascontiguousarray(covs, dtype=np.float64), dt, np.full(n, float(self.q)),
                          self.pos_dim)
        return m, 0.5 * (P + P.transpose(0, 2, 1))


MotionModel = Static | ConstantVelocity
