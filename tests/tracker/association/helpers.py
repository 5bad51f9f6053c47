"""Shared test data for the association tests."""

from __future__ import annotations

import numpy as np


def random_covs(rng: np.random.Generator, n: int, lo: float = 5.0, hi: float = 60.0) -> np.ndarray:
    """(n, 2, 2) covariances with uniform random orientation and axis standard deviations in [lo, hi) m."""
    ang = rng.uniform(0, np.pi, n)
    sd = rng.uniform(lo, hi, (n, 2))
    c, s = np.cos(ang), np.sin(ang)
    out = np.empty((n, 2, 2))
    out[:, 0, 0] = c * c * sd[:, 0] ** 2 + s * s * sd[:, 1] ** 2
    out[:, 1, 1] = s * s * sd[:, 0] ** 2 + c * c * sd[:, 1] ** 2
    out[:, 0, 1] = out[:, 1, 0] = c * s * (sd[:, 0] ** 2 - sd[:, 1] ** 2)
    return out
