"""S(n, k) against exact rational summation of eq. 16 (no floating point in the oracle)."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tracker.models.sfunc import ExpS, PoissonS, log_s, log_s_ratio


def exact_log_s(n: int, k: int, mu: Fraction, terms: int = 400) -> float:
    """log S(n, k) by exact rational summation of mu^i / (i^k (i-n)!) for i in [max(n,1), n+terms),
    times exp(-mu); the neglected tail is checked to be negligible with the same geometric bound."""
    total = Fraction(0)
    start = max(n, 1) if k >= 1 else n
    last = None
    for i in range(start, n + terms):
        ik = Fraction(i) ** k if i > 0 else Fraction(1)
        last = mu**i / (ik * math.factorial(i - n))
        total += last
    rho = mu / (n + terms - n)
    assert rho < Fraction(1, 2) and last * rho / (1 - rho) < total * Fraction(1, 10**30)
    return math.log(total.numerator) - math.log(total.denominator) - float(mu)


@pytest.mark.parametrize(
    ("n", "k", "mu"),
    [(0, 0, Fraction(3)), (1, 1, Fraction(7, 2)), (3, 5, Fraction(10)), (5, 5, Fraction(1, 3)), (2, 40, Fraction(25)), (20, 30, Fraction(12))],
)
def test_poisson_matches_exact_rational_sum(n, k, mu):
    got = log_s(PoissonS(float(mu)), n, k)
    assert got == pytest.approx(exact_log_s(n, k, mu), rel=1e-12, abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(0, 12), k=st.integers(1, 25), mu_num=st.integers(1, 60))
def test_poisson_ratio_matches_exact(n, k, mu_num):
    mu = Fraction(mu_num, 2)
    want = exact_log_s(n + 1, k, mu) - exact_log_s(n, k, mu)
    got = log_s_ratio(PoissonS(float(mu)), n, k)
    assert got == pytest.approx(want, rel=1e-10, abs=1e-10)


def test_k_zero_is_tail_probability():
    # S(n, 0) = sum_{i>=n} i!/(i-n)! p(i) = mu^n (the n-th factorial moment of a Poisson).
    mu = 6.5
    for n in range(6):
        assert log_s(PoissonS(mu), n, 0) == pytest.approx(n * math.log(mu), abs=1e-12)


def test_large_arguments_stay_finite():
    # exp(-mu) alone underflows for mu = 2000; the log-space sum must not.
    v = log_s(PoissonS(2000.0), np.array([10, 500, 1999]), np.array([3000, 3000, 3000]))
    assert np.all(np.isfinite(v))
    # More reports with the same number of distinct targets favour fewer targets: S decreases in k.
    assert log_s(PoissonS(2000.0), 500, 3001) < log_s(PoissonS(2000.0), 500, 3000)


def test_exp_model():
    assert log_s(ExpS(-1.7), 4, 99) == pytest.approx(6.8)
    assert np.all(log_s_ratio(ExpS(0.3), np.arange(5), 10) == -0.3)


def test_bad_arguments():
    with pytest.raises(ValueError, match="mu"):
        PoissonS(0.0)
    with pytest.raises(ValueError, match="tau"):
        ExpS(float("nan"))
    with pytest.raises(ValueError, match="n >= 0"):
        log_s(ExpS(1.0), -1, 3)
