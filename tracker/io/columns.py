"""The one mapping between (N, 2, 2) covariances (m²) and the ``cov_xx``, ``cov_xy``, ``cov_yy`` columns of files."""

from __future__ import annotations

import numpy as np

COV_COLUMNS = ("cov_xx", "cov_xy", "cov_yy")
"""Column names of a 2-D covariance in report and track files (m²; the xy/yx pair is one column)."""


def cov_columns(covs: np.ndarray) -> dict[str, np.ndarray]:
    """The :data:`COV_COLUMNS` of covariances ``covs`` (N, 2, 2), as a name -> (N,) mapping in that order."""
    return {"cov_xx": covs[:, 0, 0], "cov_xy": covs[:, 0, 1], "cov_yy": covs[:, 1, 1]}


def covs_from_columns(cov_xx: np.ndarray, cov_xy: np.ndarray, cov_yy: np.ndarray) -> np.ndarray:
    """Symmetric covariances (N, 2, 2) float64 from their :data:`COV_COLUMNS` (each (N,))."""
    covs = np.empty((len(cov_xx), 2, 2))
    covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 0], covs[:, 1, 1] = cov_xx, cov_xy, cov_xy, cov_yy
    return covs
