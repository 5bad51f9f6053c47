"""The tracker's reported estimate: one position density per detected target, as arrays.

Positions in metres in the prior's CRS, covariances in m², normalisers as ln of per m².
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Estimate:
    """Reported position densities p̂_q(y) = exp(-log_c_q) G(y; means_q, covs_q) r(y) when ``terrain``,
    else the Gaussians G(y; means_q, covs_q) alone (UU). ``means`` (N, 2) m, ``covs`` (N, 2, 2) m²,
    ``log_c`` (N,) ln of per m², ``counts`` (N,) reports per hypothesis, ``labels`` (N,) the truth
    label of each density for perfect association (else -1)."""

    means: np.ndarray
    covs: np.ndarray
    log_c: np.ndarray
    counts: np.ndarray
    terrain: bool
    labels: np.ndarray

