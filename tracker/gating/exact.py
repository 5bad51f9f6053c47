"""Exact per-pair gate arithmetic: closed-form 2x2/3x3 Mahalanobis distances, log-determinants
and safe upper bounds on the largest eigenvalue (the coarse gate's radius).

All functions are numba kernels on symmetric positive-definite covariances (metres^2).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# Relative slack on every coarse radius: the radius is a mathematical bound, the slack absorbs the
# rounding in lambda_max, in the squared distance and in the cell arithmetic (all ~1e-15 relative),
# so the coarse gate cannot drop a pair the exact test keeps unless cond(P + R) > ~1e9.
RADIUS_SLACK = 1e-6


@njit(cache=True, inline="always")
def sym_d2_logdet(v00, v01, v02, v11, v12, v22, dx, dy, dz, dim, with_logdet=True):
    """Mahalanobis d^2 = dx^T V^-1 dx and ln det V for symmetric V (2-D uses v00, v01, v11);
    ln det is 0.0 unless ``with_logdet`` (the logarithm costs as much as the rest of the test).

    Returns (inf, -inf) when V is not numerically positive definite.
    """
    if dim == 2:
        det = v00 * v11 - v01 * v01
        if not (v00 > 0.0 and det > 0.0):
            return np.inf, -np.inf
        d2 = (v11 * dx * dx - 2.0 * v01 * dx * dy + v00 * dy * dy) / det
        return d2, math.log(det) if with_logdet else 0.0
    c00 = v11 * v22 - v12 * v12
    c01 = v02 * v12 - v01 * v22
    c02 = v01 * v12 - v02 * v11
    c11 = v00 * v22 - v02 * v02
    c12 = v01 * v02 - v00 * v12
    c22 = v00 * v11 - v01 * v01
    det = v00 * c00 + v01 * c01 + v02 * c02
    if not (v00 > 0.0 and c22 > 0.0 and det > 0.0):
        return np.inf, -np.inf
    num = (c00 * dx * dx + c11 * dy * dy + c22 * dz * dz
           + 2.0 * (c01 * dx * dy + c02 * dx * dz + c12 * dy * dz))
    return num / det, math.log(det) if with_logdet else 0.0


@njit(cache=True)
def lambda_max_bound(c):
    """Upper bound (slightly above) on the largest eigenvalue of each symmetric (N, d, d) matrix.

    2-D: closed form. 3-D: trigonometric closed form capped by the Gershgorin bound. Both get an
    absolute slack of 1e-12 * trace so rounding can only make the bound larger.
    """
    n, dim = c.shape[0], c.shape[1]
    out = np.empty(n)
    for i in prange(n):
        if dim == 2:
            a, b, d = c[i, 0, 0], c[i, 0, 1], c[i, 1, 1]
            m = 0.5 * (a + d)
            lam = m + math.sqrt(0.25 * (a - d) ** 2 + b * b)
            tr = a + d
        else:
            a, b, e = c[i, 0, 0], c[i, 0, 1], c[i, 0, 2]
            d, f, g = c[i, 1, 1], c[i, 1, 2], c[i, 2, 2]
            tr = a + d + g
            q = tr / 3.0
            p1 = b * b + e * e + f * f
            p2 = (a - q) ** 2 + (d - q) ** 2 + (g - q) ** 2 + 2.0 * p1
            p = math.sqrt(p2 / 6.0)
            if p == 0.0:
                lam = q
            else:
                b00, b11, b22 = (a - q) / p, (d - q) / p, (g - q) / p
                b01, b02, b12 = b / p, e / p, f / p
                detb = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                        + b02 * (b01 * b12 - b11 * b02))
                r = min(1.0, max(-1.0, 0.5 * detb))
                lam = q + 2.0 * p * math.cos(math.acos(r) / 3.0)
            gersh = max(a + abs(b) + abs(e), max(d + abs(b) + abs(f), g + abs(e) + abs(f)))
            lam = min(lam, gersh)
        out[i] = lam + 1e-12 * abs(tr)
    return out


@njit(cache=True)
def log_det(c):
    """ln det of each symmetric positive-definite (N, d, d) matrix (closed form)."""
    n, dim = c.shape[0], c.shape[1]
    out = np.empty(n)
    for i in prange(n):
        if dim == 2:
            _, out[i] = sym_d2_logdet(c[i, 0, 0], c[i, 0, 1], 0.0, c[i, 1, 1], 0.0, 0.0,
                                      0.0, 0.0, 0.0, 2)
        else:
            _, out[i] = sym_d2_logdet(c[i, 0, 0], c[i, 0, 1], c[i, 0, 2], c[i, 1, 1],
                                      c[i, 1, 2], c[i, 2, 2], 0.0, 0.0, 0.0, 3)
    return out
