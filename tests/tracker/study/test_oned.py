"""tracker.study.oned against scipy.integrate.quad on integrands written out here, and limit properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, stats

from tracker.study import oned

L = oned.HALF_WIDTH
QUAD = dict(limit=4000, epsabs=1e-13, epsrel=1e-11)


def quad(f, a=-L, b=L, peak=None) -> float:
    """quad over [a, b]; `peak` marks a narrow feature (the report) so wide intervals do not miss it."""
    points = [peak] if peak is not None and a < peak < b else None
    return integrate.quad(f, a, b, points=points, **QUAD)[0]


def raw_terrain(x, lam, delta):
    return 1 + np.cos(2 * np.pi * x / lam + delta)


def oracle_unseen(lam, delta, z=0.0, sigma=1.0, half_width=L) -> float:
    """int G p by quadrature, p normalised by quadrature too."""
    norm = quad(lambda x: raw_terrain(x, lam, delta), -half_width, half_width)
    return quad(
        lambda x: stats.norm.pdf(x, z, sigma) * raw_terrain(x, lam, delta) / norm,
        -half_width,
        half_width,
        peak=z,
    )


def oracle_gain(lam, delta, z=0.0, sigma=1.0, half_width=L) -> float:
    uniform = quad(lambda x: stats.norm.pdf(x, z, sigma), -half_width, half_width, z) / (2 * half_width)
    return oracle_unseen(lam, delta, z, sigma, half_width) - uniform


# --- closed forms vs quadrature -------------------------------------------------------------


@pytest.mark.parametrize(
    "k, phase, lo, hi, z, sigma",
    [
        (2 * np.pi, 0.0, -4, 4, 0.0, 1.0),
        (0.0, 0.3, -4, 4, 0.5, 2.0),
        (1.0, np.pi, -1.0, 3.0, 0.2, 0.7),
        (50.0, 1.0, -4, 4, 0.0, 1.0),  # wavelength 0.13 sigma: huge exp(k^2) factors cancel
        (300.0, -2.0, 2.5, 3.0, 2.7, 0.05),
        (0.5, 2.0, 5.0, 9.0, -3.0, 1.0),  # interval far in the tail
    ],
)
def test_gauss_cos_integral_matches_quad(k, phase, lo, hi, z, sigma):
    expected = integrate.quad(
        lambda x: stats.norm.pdf(x, z, sigma) * np.cos(k * x + phase), lo, hi, **QUAD
    )[0]
    got = oned.gauss_cos_integral(k, phase, lo, hi, z, sigma)
    assert got == pytest.approx(expected, rel=1e-8, abs=1e-13)


@settings(max_examples=40, deadline=None)
@given(
    k=st.floats(0, 20),
    phase=st.floats(-np.pi, np.pi),
    lo=st.floats(-6, 6),
    width=st.floats(0.01, 8),
    z=st.floats(-3, 3),
    sigma=st.floats(0.2, 3),
)
def test_gauss_cos_integral_property(k, phase, lo, width, z, sigma):
    hi = lo + width
    expected = integrate.quad(
        lambda x: stats.norm.pdf(x, z, sigma) * np.cos(k * x + phase), lo, hi, **QUAD
    )[0]
    assert oned.gauss_cos_integral(k, phase, lo, hi, z, sigma) == pytest.approx(
        expected, rel=1e-7, abs=1e-12
    )


def test_gauss_cos_integral_broadcasts():
    k = np.array([0.5, 1.0, 3.0])[:, None]
    phase = np.array([0.0, 1.0])[None, :]
    got = oned.gauss_cos_integral(k, phase, -2.0, 1.5, 0.3, 0.9)
    assert got.shape == (3, 2)
    for i in range(3):
        for j in range(2):
            assert got[i, j] == pytest.approx(
                oned.gauss_cos_integral(k[i, 0], phase[0, j], -2.0, 1.5, 0.3, 0.9), rel=1e-14
            )


@pytest.mark.parametrize("lam, delta", [(1.0, 0.0), (3.0, np.pi), (0.3, 1.0), (50.0, np.pi)])
def test_terrain_density_is_normalised_and_matches_eq17(lam, delta):
    assert quad(lambda x: oned.terrain_density(x, lam, delta)) == pytest.approx(1.0, rel=1e-9)
    norm = quad(lambda x: raw_terrain(x, lam, delta))
    assert oned.terrain_norm(lam, delta) == pytest.approx(norm, rel=1e-9)
    x = np.linspace(-L, L, 17)
    np.testing.assert_allclose(
        oned.terrain_density(x, lam, delta), raw_terrain(x, lam, delta) / norm, rtol=1e-9, atol=1e-15
    )
    assert np.all(oned.terrain_density(np.array([-4.01, 4.01, 10.0]), lam, delta) == 0)


@settings(max_examples=30, deadline=None)
@given(
    lam=st.floats(0.2, 40),
    delta=st.floats(-np.pi, np.pi),
    z=st.floats(-3, 3),
    sigma=st.floats(0.3, 2.5),
)
def test_previously_unseen_matches_quad(lam, delta, z, sigma):
    assert oned.previously_unseen(lam, delta, z, sigma) == pytest.approx(
        oracle_unseen(lam, delta, z, sigma), rel=1e-7, abs=1e-12
    )
    assert oned.unseen_gain(lam, delta, z, sigma) == pytest.approx(
        oracle_gain(lam, delta, z, sigma), rel=1e-6, abs=1e-11
    )


def test_uniform_density():
    assert quad(oned.uniform_density, -10, 10, peak=0.0) == pytest.approx(1.0, rel=1e-9)
    np.testing.assert_array_equal(
        oned.uniform_density(np.array([-4.5, -4.0, 0.0, 4.0, 4.5])), [0, 1 / 8, 1 / 8, 1 / 8, 0]
    )


def test_uniform_unseen_is_truncated_mass_over_width():
    expected = quad(lambda x: stats.norm.pdf(x, 0.4, 1.3) / (2 * L))
    assert oned.previously_unseen_uniform(0.4, 1.3) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("lam, delta, z", [(1.0, 0.0, 0.0), (1.0, np.pi, 0.0), (6.5, 0.0, 1.0)])
def test_posteriors_integrate_to_one_and_match_normalised_product(lam, delta, z):
    post = lambda x: oned.posterior_density(x, lam, delta, z)  # noqa: E731
    assert quad(post) == pytest.approx(1.0, rel=1e-9)
    product = lambda x: stats.norm.pdf(x, z) * raw_terrain(x, lam, delta)  # noqa: E731
    c = quad(product)
    x = np.linspace(-L, L, 33)
    np.testing.assert_allclose(post(x), product(x) / c, rtol=1e-9, atol=1e-14)
    uni = lambda x: oned.uniform_posterior_density(x, z)  # noqa: E731
    assert quad(uni) == pytest.approx(1.0, rel=1e-10)
    assert oned.uniform_posterior_density(np.array([-5.0, 5.0]), z).tolist() == [0.0, 0.0]


@settings(max_examples=25, deadline=None)
@given(lam=st.floats(0.3, 30), delta=st.floats(-np.pi, np.pi), z=st.floats(-2, 2))
def test_posterior_ise_matches_quad(lam, delta, z):
    c = quad(lambda x: stats.norm.pdf(x, z) * raw_terrain(x, lam, delta))
    m = quad(lambda x: stats.norm.pdf(x, z))
    expected = quad(
        lambda x: (stats.norm.pdf(x, z) * (raw_terrain(x, lam, delta) / c - 1 / m)) ** 2
    )
    assert oned.posterior_ise(lam, delta, z) == pytest.approx(expected, rel=1e-6, abs=1e-12)


# --- limits and symmetries -------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(delta=st.floats(-2.5, 2.5), z=st.floats(-2, 2))
def test_long_wavelength_gives_the_uniform_posterior(delta, z):
    """lambda -> inf: 1 + cos(2 pi x/lambda + delta) -> 1 + cos(delta), a constant (delta != pi)."""
    x = np.linspace(-L, L, 41)
    uniform = oned.uniform_posterior_density(x, z)
    for lam in (1e3, 1e4, 1e5):
        # Taylor in kL (k = 2 pi/lambda): the prior's relative variation on [-L, L] is at most
        # eps = tan(|delta|/2) kL + (kL)^2 / (2 (1 + cos delta)), so posterior / uniform posterior
        # and previouslyUnseen / uniform lie within 1 +- 2 eps (1 + eps) (+ O(eps^2)).
        kl = 2 * np.pi / lam * L
        eps = np.tan(abs(delta) / 2) * kl + kl**2 / (2 * (1 + np.cos(delta)))
        err = np.max(np.abs(oned.posterior_density(x, lam, delta, z) - uniform))
        assert err <= 2.5 * eps * np.max(uniform) + 1e-15
        gain = abs(float(oned.unseen_gain(lam, delta, z)))
        assert gain <= 2.5 * eps * oned.previously_unseen_uniform(z) + 1e-15
    assert np.max(np.abs(oned.posterior_density(x, 1e5, delta, z) - uniform)) < 1e-3 * np.max(uniform)
    assert oned.posterior_ise(1e5, delta, z) < 1e-8


@settings(max_examples=30, deadline=None)
@given(delta=st.floats(-np.pi, np.pi), z=st.floats(-2, 2))
def test_short_wavelength_gain_vanishes(delta, z):
    """lambda -> 0: the cosine averages out against the report, so the gain -> 0 like lambda.

    Integrating by parts, |int_{-L}^{L} G cos(kx + delta)| <= (G(-L) + G(L) + int |G'|) / k
    <= 4 G_max / k, and |N - 2L| <= 2/k, which bounds |gain| below.
    """
    mass = stats.norm.cdf(L, z) - stats.norm.cdf(-L, z)
    for lam in (1e-2, 1e-3, 1e-4):
        k = 2 * np.pi / lam
        i_bound, n_bound = 4 * stats.norm.pdf(0.0) / k, 2 / k
        bound = (i_bound + mass * n_bound / (2 * L)) / (2 * L - n_bound)
        assert abs(float(oned.unseen_gain(lam, delta, z))) <= bound


def test_delta_pi_long_wavelength_tends_to_quadratic_prior():
    """delta = pi: 1 - cos(2 pi x/lambda) ~ x^2 shape, so p -> 3 x^2 / (2 L^3) (paper's remark)."""
    expected = quad(lambda x: stats.norm.pdf(x) * 3 * x**2 / (2 * L**3))
    assert oned.previously_unseen(1e3, np.pi) == pytest.approx(expected, rel=1e-4)


@pytest.mark.parametrize("lam", [0.7, 2.0, 6.0, 25.0])
def test_quarter_phase_gain_is_zero_for_centred_report(lam):
    """delta = pi/2 and z = 0: the terrain is 1 - sin(kx), odd part integrates to 0 (Fig. 9 dotted)."""
    assert oracle_gain(lam, np.pi / 2) == pytest.approx(0.0, abs=1e-12)
    assert oned.unseen_gain(lam, np.pi / 2) == pytest.approx(0.0, abs=1e-14)


@settings(max_examples=30, deadline=None)
@given(
    lam=st.floats(0.3, 30),
    delta=st.floats(-np.pi, np.pi),
    z=st.floats(-2, 2),
    scale=st.floats(0.1, 10),
)
def test_gain_scales_as_a_density(lam, delta, z, scale):
    """Stretching every length by c divides every density (and so the gain) by c."""
    assert oned.unseen_gain(lam * scale, delta, z * scale, scale, L * scale) == pytest.approx(
        oned.unseen_gain(lam, delta, z) / scale, rel=1e-9, abs=1e-14
    )


# --- best wavelength ------------------------------------------------------------------------


def test_best_wavelength_delta0_is_the_quadrature_maximum():
    best = oned.best_wavelength(0.0)
    grid = np.linspace(4.0, 9.0, 201)
    gains = np.array([oracle_gain(lam, 0.0) for lam in grid])
    i = int(np.argmax(gains))
    assert abs(best - grid[i]) <= grid[1] - grid[0]
    assert oracle_gain(best, 0.0) >= gains.max() - 1e-12
    # Stationary point of the quadrature gain.
    h = 1e-3
    slope = (oracle_gain(best + h, 0.0) - oracle_gain(best - h, 0.0)) / (2 * h)
    assert abs(slope) < 1e-6
    # The paper reads "about six standard deviations" off its Fig. 9.
    assert 5.5 < best < 6.5


def test_best_wavelength_is_in_sigma_units():
    """Same geometry in other units (sigma = 2, support [-8, 8]) gives the same lambda/sigma."""
    assert oned.best_wavelength(0.0, sigma=2.0, half_width=8.0) == pytest.approx(
        oned.best_wavelength(0.0), rel=1e-6
    )


def test_best_wavelength_without_interior_optimum_raises():
    with pytest.raises(ValueError, match="bound"):
        oned.best_wavelength(np.pi)  # |gain| keeps growing with lambda
    with pytest.raises(ValueError, match="zero"):
        oned.best_wavelength(np.pi / 2)
    with pytest.raises(ValueError, match="bounds"):
        oned.best_wavelength(0.0, bounds=(5.0, 1.0))


@pytest.mark.parametrize("lam, delta, sigma", [(5.0, 0.0, 1.0), (2.0, 2.0, 0.7), (30.0, np.pi, 3.0)])
def test_periodic_relative_gain_is_the_wide_support_limit(lam, delta, sigma):
    half_width = 50 * lam  # whole periods, far beyond the report's tails
    ratio = oracle_gain(lam, delta, 0.0, sigma, half_width) / quad(
        lambda x: stats.norm.pdf(x, 0.0, sigma) / (2 * half_width), -half_width, half_width, 0.0
    )
    assert oned.periodic_relative_gain(lam, delta, sigma) == pytest.approx(ratio, rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("half_width", [2.0, 4.0, 11.0])
def test_normaliser_min_wavelength_minimises_the_quadrature_normaliser(half_width):
    grid = np.linspace(0.5 * half_width, 3 * half_width, 2001)
    norms = [quad(lambda x, lam=lam: raw_terrain(x, lam, 0.0), -half_width, half_width) for lam in grid]
    lam = oned.normaliser_min_wavelength(half_width)
    assert abs(lam - grid[int(np.argmin(norms))]) <= grid[1] - grid[0]


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: oned.previously_unseen(0.0), "wavelength"),
        (lambda: oned.previously_unseen(-1.0), "wavelength"),
        (lambda: oned.previously_unseen(1.0, sigma=0.0), "sigma"),
        (lambda: oned.terrain_density(0.0, 1.0, half_width=-1.0), "half_width"),
        (lambda: oned.report_density(0.0, sigma=np.nan), "sigma"),
    ],
)
def test_bad_arguments_name_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()
