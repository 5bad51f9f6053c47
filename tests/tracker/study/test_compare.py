"""Appendix B comparisons against numerical integration of the stated posteriors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from tracker.study.compare import best_tau_index, compare, comparison_table, prob_better


def _normal_posterior_mass_below_zero(m: np.ndarray) -> float:
    """∫_{-∞}^0 G(μ; s̄, S²/L) dμ by quadrature of the density written out (eq. 31)."""
    s, var = m.mean(), m.var(ddof=1) / m.size
    pdf = lambda mu: math.exp(-0.5 * (mu - s) ** 2 / var) / math.sqrt(2 * math.pi * var)  # noqa: E731
    return integrate.quad(pdf, -np.inf, 0.0, epsabs=1e-13)[0]


def _t_posterior_mass_below_zero(m: np.ndarray) -> float:
    """Integrate σ² out: σ² | data ~ scaled-inverse-χ²(L−1, S²), μ | σ², data ~ N(s̄, σ²/L)."""
    L, s, S2 = m.size, m.mean(), m.var(ddof=1)
    a, b = (L - 1) / 2, (L - 1) * S2 / 2
    log_norm = a * math.log(b) - math.lgamma(a)

    def integrand(v: float) -> float:
        dens = math.exp(log_norm - (a + 1) * math.log(v) - b / v)
        return dens * 0.5 * math.erfc(s * math.sqrt(L / v) / math.sqrt(2))

    return integrate.quad(integrand, 0, np.inf, limit=200, epsabs=1e-12)[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_prob_better_matches_quadrature(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = rng.normal(-0.3 + 0.3 * seed, 1.0, size=28)
    assert prob_better(m, "normal") == pytest.approx(_normal_posterior_mass_below_zero(m), abs=1e-9)
    assert prob_better(m, "t") == pytest.approx(_t_posterior_mass_below_zero(m), abs=1e-7)


def test_t_form_is_wider_than_normal() -> None:
    m = np.array([-1.0, -0.5, 0.2, -0.8, -0.1])
    # Heavier tails pull the probability towards 1/2.
    assert 0.5 < prob_better(m, "t") < prob_better(m, "normal")


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-10, 10), min_size=3, max_size=30), st.sampled_from(["normal", "t"]))
def test_swapping_algorithms_complements(values: list[float], form: str) -> None:
    m = np.array(values)
    assert prob_better(m, form) + prob_better(-m, form) == pytest.approx(1.0, abs=1e-12)


def test_best_tau_index_is_lowest_mean_column() -> None:
    rng = np.random.default_rng(3)
    scores = rng.random((7, 11))
    means = [sum(scores[i, j] for i in range(7)) / 7 for j in range(11)]
    assert best_tau_index(scores) == means.index(min(means))


def test_compare_uses_each_algorithms_own_best_tau() -> None:
    rng = np.random.default_rng(4)
    a = rng.random((10, 5)) + np.array([3, 2, 0, 2, 3])
    b = rng.random((10, 6)) + np.array([0, 1, 2, 3, 4, 5]) + 0.5
    diff = a[:, 2] - b[:, 0]
    assert compare(a, b) == pytest.approx(_normal_posterior_mass_below_zero(diff), abs=1e-9)


def test_table_layout() -> None:
    rng = np.random.default_rng(5)
    scores = {name: rng.random((6, 4)) + off for name, off in (("TT", 0.0), ("UT", 0.1), ("UU", 2.0))}
    table = comparison_table(scores)
    assert [table[n][n] for n in scores] == [None, None, None]
    for a in scores:
        for b in scores:
            if a != b:
                assert table[a][b] + table[b][a] == pytest.approx(1.0)
    assert table["TT"]["UU"] > 0.99


def test_degenerate_and_bad_input() -> None:
    assert prob_better(np.array([-1.0, -1.0])) == 1.0
    assert prob_better(np.array([0.0, 0.0])) == 0.5
    with pytest.raises(ValueError, match="at least 2"):
        prob_better(np.array([1.0]))
    with pytest.raises(ValueError, match="non-finite"):
        prob_better(np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="form"):
        prob_better(np.array([1.0, 2.0]), "cauchy")
    with pytest.raises(ValueError, match="same data sets"):
        compare(np.ones((3, 2)), np.ones((4, 2)))
