"""Paper 1, section 5: a Gaussian report against a cosine terrain prior in one dimension.

The report likelihood is G(x; z, sigma^2) (default z = 0, sigma = 1). The terrain prior is the
paper's eq. (17),

    p(x) = (1 + cos(2*pi*x/lambda + delta)) / N   on [-L, L], 0 outside,

with N its integral over [-L, L] (default L = 4, as in the paper and its Mathematica code).
The support is bounded because a cosine prior on the whole line is not normalisable; the
"uniform terrain" it is compared with is 1/(2L) on the same interval. Positions, wavelengths
and half-widths are in the same (arbitrary) length unit as the report's sigma.

Every integral of a Gaussian against a cosine over an interval has a closed form through the
Faddeeva function w(z) = exp(-z^2) erfc(-iz) (`scipy.special.wofz`), evaluated only where it is
bounded, so the forms stay accurate for wavelengths far below sigma (no exp(+k^2) overflow).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import optimize, special

HALF_WIDTH = 4.0
"""The paper's support [-4, 4] in units of the report's sigma."""

_SQRT2 = np.sqrt(2.0)


def _check_positive(name: str, value: ArrayLike) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return arr


def _phase_cdf_left(beta: np.ndarray, s: np.ndarray) -> np.ndarray:
    """int_{-inf}^{beta} phi(u) exp(i s u) du for beta <= 0 (phi: standard normal pdf).

    Equals exp(-s^2/2) Phi(beta - i s) = exp(-beta^2/2 + i beta s) w(-(s + i beta)/sqrt2) / 2,
    where the Faddeeva argument has Im >= 0, so |w| <= 1 and nothing overflows.
    """
    return 0.5 * np.exp(-0.5 * beta**2 + 1j * beta * s) * special.wofz(-(s + 1j * beta) / _SQRT2)


def _phase_cdf(beta: np.ndarray, s: np.ndarray) -> np.ndarray:
    """int_{-inf}^{beta} phi(u) exp(i s u) du for any real beta (reflection for beta > 0)."""
    beta, s = np.broadcast_arrays(np.asarray(beta, float), np.asarray(s, float))
    left = beta <= 0
    out = np.empty(beta.shape, dtype=complex)
    out[left] = _phase_cdf_left(beta[left], s[left])
    # The upper tail int_beta^inf phi(u) e^{isu} du is the lower tail at (-beta, -s).
    right = ~left
    out[right] = np.exp(-0.5 * s[right] ** 2) - _phase_cdf_left(-beta[right], -s[right])
    return out


def gauss_cos_integral(
    wavenumber: ArrayLike,
    phase: ArrayLike,
    lower: ArrayLike,
    upper: ArrayLike,
    z: ArrayLike = 0.0,
    sigma: ArrayLike = 1.0,
) -> np.ndarray:
    """int_lower^upper G(x; z, sigma^2) cos(wavenumber*x + phase) dx (closed form, broadcast).

    wavenumber in radians per length unit (k = 2*pi/lambda, k = 0 allowed); phase in radians.
    """
    sigma = _check_positive("sigma", sigma)
    k = np.asarray(wavenumber, dtype=float)
    z = np.asarray(z, dtype=float)
    s = k * sigma
    window = _phase_cdf((upper - z) / sigma, s) - _phase_cdf((lower - z) / sigma, s)
    return np.real(np.exp(1j * (k * z + phase)) * window)


def _mass(z: ArrayLike, sigma: ArrayLike, half_width: float) -> np.ndarray:
    """int_{-L}^{L} G(x; z, sigma^2) dx."""
    z = np.asarray(z, dtype=float)
    return special.ndtr((half_width - z) / sigma) - special.ndtr((-half_width - z) / sigma)


def terrain_norm(wavelength: ArrayLike, phase: ArrayLike, half_width: float = HALF_WIDTH) -> np.ndarray:
    """N = int_{-L}^{L} (1 + cos(2 pi x/lambda + delta)) dx = 2L + 2 cos(delta) sin(kL)/k."""
    lam = _check_positive("wavelength", wavelength)
    half_width = float(_check_positive("half_width", half_width))
    k = 2 * np.pi / lam
    # sin(kL)/k = L sinc(kL/pi), finite as lambda -> inf.
    return 2 * half_width * (1 + np.cos(phase) * np.sinc(k * half_width / np.pi))


def report_density(x: ArrayLike, z: float = 0.0, sigma: float = 1.0) -> np.ndarray:
    """Report likelihood G(x; z, sigma^2), per length unit."""
    sigma = _check_positive("sigma", sigma)
    return np.exp(-0.5 * ((np.asarray(x, float) - z) / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma)


def _inside(x: np.ndarray, half_width: float) -> np.ndarray:
    return (x >= -half_width) & (x <= half_width)


def uniform_density(x: ArrayLike, half_width: float = HALF_WIDTH) -> np.ndarray:
    """Uniform terrain 1/(2L) on [-L, L], 0 outside."""
    half_width = float(_check_positive("half_width", half_width))
    x = np.asarray(x, dtype=float)
    return np.where(_inside(x, half_width), 1 / (2 * half_width), 0.0)


def terrain_density(
    x: ArrayLike, wavelength: ArrayLike, phase: ArrayLike = 0.0, half_width: float = HALF_WIDTH
) -> np.ndarray:
    """Cosine terrain prior p(x) of eq. (17), per length unit (broadcast over all arguments)."""
    x = np.asarray(x, dtype=float)
    lam = _check_positive("wavelength", wavelength)
    raw = 1 + np.cos(2 * np.pi * x / lam + phase)
    return np.where(_inside(x, half_width), raw / terrain_norm(lam, phase, half_width), 0.0)


def previously_unseen(
    wavelength: ArrayLike,
    phase: ArrayLike = 0.0,
    z: ArrayLike = 0.0,
    sigma: ArrayLike = 1.0,
    half_width: float = HALF_WIDTH,
) -> np.ndarray:
    """previouslyUnseen with S = 1: int G(x; z, sigma^2) p(x) dx for the cosine terrain."""
    lam = _check_positive("wavelength", wavelength)
    sigma = _check_positive("sigma", sigma)
    k = 2 * np.pi / lam
    numer = _mass(z, sigma, half_width) + gauss_cos_integral(
        k, phase, -half_width, half_width, z, sigma
    )
    return numer / terrain_norm(lam, phase, half_width)


def previously_unseen_uniform(
    z: ArrayLike = 0.0, sigma: ArrayLike = 1.0, half_width: float = HALF_WIDTH
) -> np.ndarray:
    """previouslyUnseen with S = 1 for the uniform terrain: int_{-L}^{L} G dx / (2L)."""
    sigma = _check_positive("sigma", sigma)
    half_width = float(_check_positive("half_width", half_width))
    return _mass(z, sigma, half_width) / (2 * half_width)


def unseen_gain(
    wavelength: ArrayLike,
    phase: ArrayLike = 0.0,
    z: ArrayLike = 0.0,
    sigma: ArrayLike = 1.0,
    half_width: float = HALF_WIDTH,
) -> np.ndarray:
    """The paper's Figs. 8-9 quantity: previouslyUnseen(cosine) - previouslyUnseen(uniform).

    Zero means the cosine prior changes nothing in association; positive values favour
    declaring a new target, negative values favour associating with an existing one.
    """
    return previously_unseen(wavelength, phase, z, sigma, half_width) - previously_unseen_uniform(
        z, sigma, half_width
    )


def periodic_relative_gain(
    wavelength: ArrayLike, phase: ArrayLike = 0.0, sigma: ArrayLike = 1.0
) -> np.ndarray:
    """Whole-line limit of unseen_gain / previously_unseen_uniform: exp(-k^2 sigma^2 / 2) cos(delta).

    For a report at a terrain crest (z = 0) on an unbounded periodic terrain normalised per period
    (support [-L, L] with L a multiple of lambda, L >> sigma). Dimensionless.
    """
    k = 2 * np.pi / _check_positive("wavelength", wavelength)
    sigma = _check_positive("sigma", sigma)
    return np.exp(-0.5 * (k * sigma) ** 2) * np.cos(phase)


def posterior_density(
    x: ArrayLike,
    wavelength: ArrayLike,
    phase: ArrayLike = 0.0,
    z: float = 0.0,
    sigma: float = 1.0,
    half_width: float = HALF_WIDTH,
) -> np.ndarray:
    """Target-location posterior G(x; z, sigma^2) p(x) / int G p, per length unit."""
    prior = terrain_density(x, wavelength, phase, half_width)
    return report_density(x, z, sigma) * prior / previously_unseen(
        wavelength, phase, z, sigma, half_width
    )


def uniform_posterior_density(
    x: ArrayLike, z: float = 0.0, sigma: float = 1.0, half_width: float = HALF_WIDTH
) -> np.ndarray:
    """Posterior under the uniform terrain: the report Gaussian truncated to [-L, L]."""
    x = np.asarray(x, dtype=float)
    inside = _inside(x, float(_check_positive("half_width", half_width)))
    return np.where(inside, report_density(x, z, sigma) / _mass(z, sigma, half_width), 0.0)


def posterior_ise(
    wavelength: ArrayLike,
    phase: ArrayLike = 0.0,
    z: ArrayLike = 0.0,
    sigma: ArrayLike = 1.0,
    half_width: float = HALF_WIDTH,
) -> np.ndarray:
    """Integrated squared difference between the cosine- and uniform-terrain posteriors.

    The estimation-side measure the paper describes around Fig. 10, per length unit. Closed form:
    G^2 = G(x; z, sigma^2/2) / (2 sqrt(pi) sigma), and (a + b cos t)^2 = a^2 + b^2/2 + 2ab cos t
    + (b^2/2) cos 2t.
    """
    lam = _check_positive("wavelength", wavelength)
    sigma = _check_positive("sigma", sigma)
    k = 2 * np.pi / lam
    # Posterior difference = G(x) (a + b cos(kx + delta)) on [-L, L].
    c = previously_unseen(lam, phase, z, sigma, half_width) * terrain_norm(lam, phase, half_width)
    b = 1 / c
    a = b - 1 / _mass(z, sigma, half_width)
    narrow = sigma / _SQRT2
    scale = 1 / (2 * np.sqrt(np.pi) * sigma)
    lo, hi = -half_width, half_width
    return scale * (
        (a**2 + b**2 / 2) * _mass(z, narrow, half_width)
        + 2 * a * b * gauss_cos_integral(k, phase, lo, hi, z, narrow)
        + b**2 / 2 * gauss_cos_integral(2 * k, 2 * np.asarray(phase), lo, hi, z, narrow)
    )


def normaliser_min_wavelength(half_width: ArrayLike = HALF_WIDTH) -> np.ndarray:
    """Wavelength minimising the delta = 0 normaliser 2L + 2 sin(kL)/k (same units as L).

    d/dk [sin(kL)/k] = 0 at tan(kL) = kL; the first positive root lies in (pi, 3 pi/2). The lower
    normaliser raises the prior at the report, which is why best_wavelength tracks the support.
    """
    half_width = _check_positive("half_width", half_width)
    root = optimize.brentq(lambda t: np.sin(t) - t * np.cos(t), np.pi, 1.5 * np.pi, xtol=1e-14)
    return 2 * np.pi * half_width / root


def best_wavelength(
    delta: float = 0.0,
    *,
    z: float = 0.0,
    sigma: float = 1.0,
    half_width: float = HALF_WIDTH,
    bounds: tuple[float, float] = (0.05, 50.0),
    grid_size: int = 400,
) -> float:
    """Wavelength, in units of the report's sigma, at which |unseen_gain| is largest.

    A log-spaced grid over `bounds` (in sigma units) brackets the global maximum; Brent's bounded
    method (scipy.optimize.minimize_scalar) then refines it between the neighbouring grid points.
    Raises ValueError when the maximum is on a bound (no interior optimum: e.g. delta = pi, where
    the prior's effect grows with lambda) or when the gain is identically zero (delta = pi/2, z = 0).
    """
    sigma = float(_check_positive("sigma", sigma))
    lo, hi = (float(b) for b in _check_positive("bounds", bounds))
    if not lo < hi:
        raise ValueError(f"bounds must be increasing, got {bounds!r}")

    def objective(lam_sigma: float) -> float:
        return -abs(float(unseen_gain(lam_sigma * sigma, delta, z, sigma, half_width)))

    grid = np.geomspace(lo, hi, grid_size)
    values = -np.abs(unseen_gain(grid * sigma, delta, z, sigma, half_width))
    i = int(np.argmin(values))
    if -values[i] < 1e-12:
        raise ValueError(f"unseen_gain is zero over bounds {bounds!r} for delta={delta!r}")
    if i in (0, grid_size - 1):
        raise ValueError(
            f"|unseen_gain| is largest at the bound lambda={grid[i]:g} sigma for delta={delta!r}: "
            "no interior optimum within bounds"
        )
    res = optimize.minimize_scalar(
        objective, bounds=(grid[i - 1], grid[i + 1]), method="bounded", options={"xatol": 1e-10}
    )
    return float(res.x)
