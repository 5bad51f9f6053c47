"""S(n, k), the target-count factor of the association scores (paper 1, eq. 16), in log space.

    S(n, k) = sum_{i >= n} i! p(N_T = i) / (i^k (i - n)!)

is, up to a factor common to every hypothesis, the probability that k reports drawn uniformly with
replacement from i targets show exactly n distinct, labelled targets, averaged over the prior on the
number of targets N_T. The association step compares S(N_D, k+1) with S(N_D + 1, k+1), so only

    log S(n + 1, k) - log S(n, k)

matters. Two models:

* ``ExpS(tau)``: the paper's working form S(n, k) = exp(-n tau); the log ratio is the constant -tau.
* ``PoissonS(mu)``: eq. 16 exactly under N_T ~ Poisson(mu). Term i is
  t_i = exp(-mu + i log mu - k log i - lgamma(i - n + 1)) (the i = 0 term is 0 for k >= 1: no target
  cannot make a report). Terms are summed in log space from i = max(n, 1) upwards. Because
  t_{i+1} / t_i = mu / (i + 1 - n) * (i / (i + 1))^k <= mu / (i + 1 - n) and that bound falls with i,
  once rho = mu / (I + 1 - n) < 1 the remaining tail obeys sum_{i > I} t_i <= t_I rho / (1 - rho)
  (a geometric series). Summation stops when this bound is below 2^-60 of the partial sum, so the
  returned log S is low by at most 2^-60 (absolute, in log units) plus rounding. The cost is about
  max(mu, terms to the peak) evaluations of lgamma.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numba import njit

KIND_EXP = 0
KIND_POISSON = 1
_LOG_EPS = -60.0 * math.log(2.0)
_MAX_TERMS = 50_000_000


class SModel(Protocol):
    """An S(n, k) model as the association uses it: ``code`` = (kind, parameter) selects the
    formula in the numba kernels (:func:`log_s_code`, :func:`log_s_ratio_code`)."""

    @property
    def code(self) -> tuple[int, float]:
        """(KIND_EXP or KIND_POISSON, the model's parameter)."""
        ...


@dataclass(frozen=True)
class ExpS:
    """The paper's S(n, k) = exp(-n tau); tau is dimensionless (the paper's best TT value is -1.7)."""

    tau: float

    def __post_init__(self) -> None:
        if not math.isfinite(self.tau):
            raise ValueError(f"ExpS: tau must be finite, got {self.tau}")

    @property
    def code(self) -> tuple[int, float]:
        """(kind, parameter) for the numba kernels."""
        return KIND_EXP, float(self.tau)


@dataclass(frozen=True)
class PoissonS:
    """Eq. 16 exactly with N_T ~ Poisson(mu), mu > 0 the expected number of targets."""

    mu: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mu) and self.mu > 0):
            raise ValueError(f"PoissonS: mu must be positive and finite, got {self.mu}")

    @property
    def code(self) -> tuple[int, float]:
        return KIND_POISSON, float(self.mu)



@njit(cache=True, inline="always")
def lgamma_int(x: int) -> float:
    return math.lgamma(float(x))


@njit(cache=True)
def poisson_log_s(n: int, k: int, mu: float) -> float:
    """log S(n, k) of eq. 16 under Poisson(mu) (see the module docstring for the tail bound)."""
    log_mu = math.log(mu)
    i = n
    if i == 0 and k >= 1:
        i = 1  # t_0 = 0: zero targets make no reports
    m = -np.inf  # running max of log terms
    s = 0.0  # sum of exp(log t - m)
    for _ in range(_MAX_TERMS):
        log_t = -mu + i * log_mu - lgamma_int(i - n + 1)
        if k > 0:
            log_t -= k * math.log(i)
        if log_t > m:
            s = s * math.exp(m - log_t) + 1.0
            m = log_t
        else:
            s += math.exp(log_t - m)
        rho = mu / (i + 1 - n)
        if rho < 1.0:
            tail = log_t + math.log(rho / (1.0 - rho))
            if tail - (m + math.log(s)) < _LOG_EPS:
                return m + math.log(s)
        i += 1
    raise ValueError("PoissonS: eq. 16 did not converge within 5e7 terms (mu too large)")


@njit(cache=True)
def log_s_code(kind: int, param: float, n: int, k: int) -> float:
    """log S(n, k) for a model given as (kind, parameter) (see ``ExpS.code``)."""
    if kind == KIND_EXP:
        return -n * param
    return poisson_log_s(n, k, param)


@njit(cache=True)
def log_s_ratio_code(kind: int, param: float, n: int, k: int) -> float:
    """log S(n + 1, k) - log S(n, k): previouslyUnseen's factor over bestPrevious's."""
    if kind == KIND_EXP:
        return -param
    return poisson_log_s(n + 1, k, param) - poisson_log_s(n, k, param)


def _check_nk(n: np.ndarray, k: np.ndarray) -> None:
    if np.any(n < 0) or np.any(k < 0):
        raise ValueError(f"S(n, k) needs n >= 0 and k >= 0, got n={n.ravel()[:5].tolist()}, k={k.ravel()[:5].tolist()}")


def _over_nk(code_fn, model: SModel, n, k) -> np.ndarray:
    """``code_fn(kind, param, n, k)`` over broadcast integer arrays n, k."""
    n, k = np.broadcast_arrays(np.asarray(n, dtype=np.int64), np.asarray(k, dtype=np.int64))
    _check_nk(n, k)
    kind, param = model.code
    out = np.array([code_fn(kind, param, int(a), int(b)) for a, b in zip(n.ravel(), k.ravel(), strict=True)])
    return out.reshape(n.shape)


def log_s(model: SModel, n, k) -> np.ndarray:
    """log S(n, k), vectorised over integer arrays n, k (numbers of detected targets and of reports)."""
    return _over_nk(log_s_code, model, n, k)


def log_s_ratio(model: SModel, n, k) -> np.ndarray:
    """log S(n + 1, k) - log S(n, k), vectorised over integer arrays n, k."""
    return _over_nk(log_s_ratio_code, model, n, k)
