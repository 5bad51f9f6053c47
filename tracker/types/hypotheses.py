"""Hypothesised targets p̂_q(y) = c_q⁻¹ G(a_q, A_q, y) r(Hy) kept as growable arrays (their motion models
are in :mod:`tracker.models.motion`).

State vectors are positions (x, y) in metres for the static model, (x, y, vx, vy) in metres and m/s
for constant velocity; covariances are in the matching units (m², m²/s, m²/s²). ``log_c`` is
ln c_q, the normaliser of the Gaussian part against the prior at the hypothesis's time (ln of a
density per m²). Only positions meet the prior: r applies to H y = (x, y).
"""

from __future__ import annotations

import numpy as np


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
