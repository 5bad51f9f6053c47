"""Basis forms of continuous features: log r(v) = B(g(v)) · θ, linear in θ.

``g`` is the feature's scale (``"linear"``: g = v; ``"log1p"``: g = log(1 + v), for distances and
counts, v >= 0). Every form is 0 at the feature's lowest grid value g_lo (the intercept is
profiled out of the Poisson-process likelihood, so only differences of log r are identified):

- ``linear``: log r = β·(g − g_lo), one free β.
- ``increasing`` / ``decreasing``: log r = ±Σ_k θ_k·h_k(g) with θ_k >= 0 and hinges
  h_k(g) = clip(g − κ_k, 0, κ_{k+1} − κ_k) between equally spaced knots κ_0 = g_lo .. κ_K = g_hi:
  a piecewise-linear monotone function of g (any monotone function is the limit as K grows).
- ``spline``: f(g) − f(g_lo), f = Σ_j c_j B_j cubic B-splines on K equally spaced knot intervals
  over [g_lo, g_hi], c_0 fixed at 0 (identifiability), and the P-spline difference penalty
  ½·λ·Σ (Δ² c)² (Eilers & Marx 1996); λ is chosen by AIC with effective degrees of freedom.

The fit never needs more than B at the fine bins' mean values (cells) and at the points' exact
values, so every form runs on the same sufficient statistics as the categorical and road forms.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline

BASIS_FORMS = ("linear", "increasing", "decreasing", "spline")
SCALES = ("linear", "log1p")
SPLINE_DEGREE = 3
PENALTY_ORDER = 2


def to_scale(scale: str, v: np.ndarray) -> np.ndarray:
    """g(v) (NaN stays NaN); ValueError for log1p of values <= -1."""
    v = np.asarray(v, dtype=np.float64)
    if scale == "linear":
        return v
    if scale == "log1p":
        if np.any(v[np.isfinite(v)] <= -1):
            raise ValueError("scale log1p needs values > -1 (distances, counts)")
        return np.log1p(v)
    raise ValueError(f"scale must be one of {SCALES}, got {scale!r}")


def from_scale(scale: str, g: np.ndarray) -> np.ndarray:
    """v(g), the inverse of :func:`to_scale`."""
    g = np.asarray(g, dtype=np.float64)
    return np.expm1(g) if scale == "log1p" else g


def knots(lo: float, hi: float, n_knots: int) -> np.ndarray:
    """Equally spaced knots κ_0 = lo .. κ_K = hi on the scale g (K = ``n_knots`` intervals)."""
    hi = hi if hi > lo else lo + 1.0
    return np.linspace(lo, hi, n_knots + 1)


def basis(form: str, g: np.ndarray, kappa: np.ndarray) -> np.ndarray:
    """B (n, K) at scale values ``g`` (n,), knots ``kappa``; rows of NaN values are 0."""
    g = np.asarray(g, dtype=np.float64)
    nan = ~np.isfinite(g)
    gg = np.clip(np.where(nan, kappa[0], g), kappa[0], kappa[-1])
    if form == "linear":
        out = (gg - kappa[0])[:, None]
    elif form in ("increasing", "decreasing"):
        out = np.clip(gg[:, None] - kappa[None, :-1], 0.0, np.diff(kappa)[None, :])
        if form == "decreasing":
            out = -out
    elif form == "spline":
        k = SPLINE_DEGREE
        step = kappa[1] - kappa[0]
        t = np.concatenate([kappa[0] - step * np.arange(k, 0, -1), kappa, kappa[-1] + step * np.arange(1, k + 1)])
        full = BSpline.design_matrix(gg, t, k, extrapolate=False).toarray()
        at_lo = BSpline.design_matrix(kappa[:1], t, k, extrapolate=False).toarray()
        # f(g) − f(g_lo) with f = Σ c_j B_j and c_0 = 0: zero at g_lo, and no constant (Σ_j B_j = 1)
        out = (full - at_lo)[:, 1:]
    else:
        raise ValueError(f"form must be one of {BASIS_FORMS}, got {form!r}")
    out = np.array(out, dtype=np.float64)
    out[nan] = 0.0
    return out


def n_coef(form: str, n_knots: int) -> int:
    """Free coefficients of a form with ``n_knots`` knot intervals."""
    return {"linear": 1, "increasing": n_knots, "decreasing": n_knots, "spline": n_knots + SPLINE_DEGREE - 1}[form]


def difference_penalty(form: str, n_knots: int) -> np.ndarray:
    """P (K, K) with ½·λ·θᵀPθ the spline's difference penalty on [0, θ]; zeros for other forms."""
    k = n_coef(form, n_knots)
    if form != "spline":
        return np.zeros((k, k))
    d = np.diff(np.eye(k + 1), PENALTY_ORDER, axis=0)[:, 1:]  # drop the fixed first coefficient
    return d.T @ d


__all__ = ["BASIS_FORMS", "SCALES", "basis", "difference_penalty", "from_scale", "knots", "n_coef", "to_scale"]
