"""Hypothesised targets p̂_q(y) = c_q⁻¹ G(a_q, A_q, y) r(Hy) kept as growable arrays, and their motion models.

State vectors are positions (x, y) in metres for the static model, (x, y, vx, vy) in metres and m/s
for constant velocity; covariances are in the matching units (m², m²/s, m²/s²). ``log_c`` is
ln c_q, the normaliser of the Gaussian part against the prior at the hypothesis's time (ln of a
density per m²). Only positions meet the prior: r applies to H y = (x, y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MOTION_STATIC = 0
MOTION_CV = 1


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
    (m/s) per axis, uncorrelated with its position."""

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
        """Kalman time update of (N, 2d) states by dt (N,) seconds: x' = F x, P' = F P Fᵀ + Q(dt),
        F = [[I, dt I], [0, I]], Q = q [[dt³/3 I, dt²/2 I], [dt²/2 I, dt I]]."""
        d = self.pos_dim
        dt = np.asarray(dt, dtype=np.float64)
        n = means.shape[0]
        F = np.broadcast_to(np.eye(2 * d), (n, 2 * d, 2 * d)).copy()
        F[:, :d, d:] = dt[:, None, None] * np.eye(d)
        eye = np.eye(d)
        Q = np.empty((n, 2 * d, 2 * d))
        adt = np.abs(dt)[:, None, None]
        Q[:, :d, :d] = adt**3 / 3.0 * eye
        Q[:, :d, d:] = Q[:, d:, :d] = np.sign(dt)[:, None, None] * adt**2 / 2.0 * eye
        Q[:, d:, d:] = adt * eye
        m = np.einsum("nij,nj->ni", F, means)
        P = F @ covs @ F.transpose(0, 2, 1) + self.q * Q
        return m, 0.5 * (P + P.transpose(0, 2, 1))


MotionModel = Static | ConstantVelocity


class Hypotheses:
    """N hypotheses as arrays with spare capacity: ``means`` (N, D), ``covs`` (N, D, D), ``log_c`` (N,),
    ``counts`` (N,) reports fused into each, ``times`` (N,) seconds of the last update. Append and fuse
    work in place; capacity doubles when needed, so streaming costs amortised O(1) per report."""

    def __init__(self, state_dim: int, capacity: int = 64) -> None:
        capacity = max(int(capacity), 1)
        self.state_dim = int(state_dim)
        self.n = 0
        self._means = np.zeros((capacity, state_dim))
        self._covs = np.zeros((capacity, state_dim, state_dim))
        self._log_c = np.zeros(capacity)
        self._counts = np.zeros(capacity, dtype=np.int64)
        self._times = np.zeros(capacity)

    def __len__(self) -> int:
        return self.n

    @property
    def means(self) -> np.ndarray:
        return self._means[: self.n]

    @property
    def covs(self) -> np.ndarray:
        return self._covs[: self.n]

    @property
    def log_c(self) -> np.ndarray:
        return self._log_c[: self.n]

    @property
    def counts(self) -> np.ndarray:
        return self._counts[: self.n]

    @property
    def times(self) -> np.ndarray:
        return self._times[: self.n]

    @property
    def capacity(self) -> int:
        return self._log_c.shape[0]

    def reserve(self, extra: int) -> None:
        """Make room for ``extra`` more hypotheses without reallocating later."""
        need = self.n + int(extra)
        if need <= self.capacity:
            return
        cap = max(need, 2 * self.capacity)
        for name in ("_means", "_covs", "_log_c", "_counts", "_times"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)

    def append(self, means: np.ndarray, covs: np.ndarray, log_c: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Add hypotheses (one report each); returns their indices."""
        k = means.shape[0]
        self.reserve(k)
        sl = slice(self.n, self.n + k)
        self._means[sl], self._covs[sl], self._log_c[sl], self._times[sl] = means, covs, log_c, times
        self._counts[sl] = 1
        self.n += k
        return np.arange(sl.start, sl.stop)

    def fuse(self, idx: np.ndarray, means: np.ndarray, covs: np.ndarray, log_c: np.ndarray, times: np.ndarray) -> None:
        """Replace hypotheses ``idx`` (distinct) by their posteriors after one more report each."""
        idx = np.asarray(idx, dtype=np.intp)
        self._means[idx], self._covs[idx], self._log_c[idx], self._times[idx] = means, covs, log_c, times
        self._counts[idx] += 1

    def copy(self) -> Hypotheses:
        out = Hypotheses(self.state_dim, self.n)
        out.append(self.means, self.covs, self.log_c, self.times)
        out._counts[: self.n] = self.counts
        return out

    def position(self, pos_dim: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Position marginals (N, d) and (N, d, d) of the Gaussian parts."""
        return self.means[:, :pos_dim], self.covs[:, :pos_dim, :pos_dim]
