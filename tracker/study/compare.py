"""Appendix B of paper 1: the posterior probability that algorithm A1 is better than A2, each at its
best τ (the τ with the lowest mean score over the data sets; lower scores are better).

With M_i = Score(A1 on w_i at τ1*) − Score(A2 on w_i at τ2*), s̄ and S the sample mean and standard
deviation of the L values M_i and a flat prior on the mean μ:

* ``normal``: σ taken as known (= S), μ | data ~ N(s̄, S²/L), so P(μ < 0) = Φ(−s̄ √L / S)  (eq. 31);
* ``t``: σ integrated out under p(μ, σ) ∝ 1/σ, μ | data ~ s̄ + (S/√L)·t_{L−1}, so
  P(μ < 0) = T_{L−1}(−s̄ √L / S) — the "more proper" form the paper mentions.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from scipy import stats


def best_tau_index(scores: np.ndarray) -> int:
    """Index of the τ column with the lowest mean score; ``scores`` is (L data sets, n τ values)."""
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2 or not scores.size:
        raise ValueError(f"scores must be a non-empty (datasets, taus) array, got shape {scores.shape}")
    mean = scores.mean(axis=0)
    if not np.isfinite(mean).any():
        raise ValueError("scores: every τ column has a non-finite mean")
    return int(np.nanargmin(np.where(np.isfinite(mean), mean, np.nan)))


def prob_better(differences: np.ndarray, form: str = "normal") -> float:
    """P(E[M] < 0) from the L samples M_i (A1 minus A2; negative means A1 scored lower, i.e. better)."""
    m = np.asarray(differences, dtype=np.float64).ravel()
    if m.size < 2 or not np.isfinite(m).all():
        raise ValueError(f"prob_better needs at least 2 finite differences, got {m.size} ({np.count_nonzero(~np.isfinite(m))} non-finite)")
    if form not in ("normal", "t"):
        raise ValueError(f"form must be 'normal' or 't', got {form!r}")
    mean = m.mean()
    sd = m.std(ddof=1)
    if sd == 0:
        # Degenerate posterior: a point mass at the sample mean.
        return 1.0 if mean < 0 else (0.0 if mean > 0 else 0.5)
    z = -mean * np.sqrt(m.size) / sd
    return float(stats.norm.cdf(z) if form == "normal" else stats.t.cdf(z, df=m.size - 1))


def compare(scores_a: np.ndarray, scores_b: np.ndarray, form: str = "normal") -> float:
    """P(A better than B), each at its own best τ; ``scores_*`` are (L, n_τ) with the same data-set rows."""
    scores_a = np.asarray(scores_a, dtype=np.float64)
    scores_b = np.asarray(scores_b, dtype=np.float64)
    if scores_a.ndim != 2 or scores_b.ndim != 2 or scores_a.shape[0] != scores_b.shape[0]:
        raise ValueError(f"scores must be (datasets, taus) with the same data sets; got {scores_a.shape} and {scores_b.shape}")
    diff = scores_a[:, best_tau_index(scores_a)] - scores_b[:, best_tau_index(scores_b)]
    return prob_better(diff, form)


def comparison_table(scores: Mapping[str, np.ndarray], form: str = "normal", order: Sequence[str] | None = None) -> dict[str, dict[str, float | None]]:
    """Table 1: entry [row][column] = P(row better than column); None on the diagonal."""
    names = list(order or scores)
    return {a: {b: None if a == b else compare(scores[a], scores[b], form) for b in names} for a in names}
