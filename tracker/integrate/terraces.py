"""Gaussian-terrace integration of 2-D Gaussians against a terrain prior (paper 1, appendix A).

:func:`integrate_terraces` returns ∫ G(y; a_n, A_n) r(y) dy (per m²; ∫ G r² dy per m⁴ when
``squared``) for a batch of Gaussians in pixel units (:func:`pixel_gaussians`). It is the
integrator of :func:`tracker.integrate.integrate` with ``method="terraces"``, and takes the Gaussians
the default pyramid (:mod:`tracker.integrate.scalespace`) is not made for. A terrace integral costs
about ``n_terraces × n_strips`` summed-area-table rectangles whatever the Gaussian's spread.

The Gaussian is replaced by a stack of concentric elliptical terraces (its constant-density
contours at Mahalanobis radii ρ_1 < … < ρ_K): a step function, constant on each ring, whose
integral against r is Σ_k c_k R(ρ_k) with R(ρ) the prior's mass inside the ellipse of radius ρ
(each ellipse enters with its terrace height minus the next one's: "inner ellipse subtracted,
times the terrace height"). Each R(ρ) is the sum of vertical strips read from the summed-area
table with fractional edges; each strip is the rectangle with the strip's exact ellipse area
(the strip-vs-ellipse area correction) centred on the strip's area centroid, so a prior that is
linear across the ellipse is integrated exactly.

Heights and radii come from the layer-cake identity (s = ρ²/2, G = e^{-s}/(2π√det A))

    ∫ G r dy = ∫_0^∞ R(ρ) ρ e^{-ρ²/2} dρ / (2π √det A),

by the trapezoid rule on equally spaced radii, and only over the radii where the grid is:
R(ρ) = 0 below ρ_lo (the Mahalanobis distance from the mean to the grid) and R(ρ) = R_grid above
ρ_hi (the distance to its farthest corner), both known exactly. The terraces span [ρ_lo, ρ_end]
with ρ_end = min(ρ_hi, √(ρ_lo² + ρ_M²)), ρ_M the radius holding ``mass`` of the Gaussian: the
stop at the covered mass. The rest beyond ρ_end is e^{-ρ_end²/2}·(R(ρ_end)/(2π√det A) + δ), exact
when ρ_end = ρ_hi (δ = 0) and otherwise extrapolating with δ, the mean density of the outermost
ring. So Gaussians far larger than the grid, or centred off it, get their terraces where the
prior is and keep their relative accuracy.

Where this differs from the paper, and why (numbers in docs/terrace.md): the paper's terraces
hold equal mass shares up to 99 % of the mass, a fixed rule that is 1-20 % off next to a grid
edge or lake 1-2 σ from the mean, or for a Gaussian much larger than the grid. ``scheme="paper"``
keeps that rule for comparison. Thin tilted ellipses get more strips (:func:`n_strips_for`): the
cost grows with eccentricity, never with spread.
"""

from __future__ import annotations

from typing import Literal

import numba as nb
import numpy as np

from pipeline.prior import TerrainPrior, sat_rect

N_TERRACES = 24
"""Default number of terraces (ellipses), from the accuracy study in docs/terrace.md."""
N_STRIPS = 32
"""Default (minimum) number of vertical strips per ellipse."""
SHEAR = 16.0
"""Default strips per unit of shear κ (see :func:`n_strips_for`)."""
MASS = 0.9999
"""Default Gaussian mass covered by the terraces (beyond the grid's nearest point)."""
MAX_STRIPS = 4096
"""Most strips per ellipse: the cap on ⌈shear·κ⌉ that bounds the time and memory of a thin tilted
Gaussian (κ above 256, e.g. 512:1 at 45°); past it the accuracy is the one measured in docs/terrace.md."""

_FAR = 1400.0  # ρ_lo² beyond which e^{-ρ²/2} underflows: the integral is 0 in float64


def pixel_gaussians(prior: TerrainPrior, means: np.ndarray, covs: np.ndarray):
    """Means and covariances in fractional pixel coordinates (u = column, v = row, rows grow southward).

    Returns (uc, vc, cuu, cuv, cvv) as (N,) arrays; the y flip makes the u-v covariance the
    negative of the x-y covariance divided by the cell sizes.
    """
    g = prior.grid
    uc, vc = g.to_pixel(means[:, 0], means[:, 1])
    cuu = covs[:, 0, 0] / (g.dx * g.dx)
    cvv = covs[:, 1, 1] / (g.dy * g.dy)
    cuv = -0.5 * (covs[:, 0, 1] + covs[:, 1, 0]) / (g.dx * g.dy)
    return uc, vc, cuu, cuv, cvv


def paper_rule(n_terraces: int, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """The paper's terraces: radii ρ_k (K,) each adding ``mass / K``, coefficients c_k (K,).

    ∫ G r ≈ Σ_k c_k R(ρ_k) / √det A (pixel units), with the rest (1 - ``mass``) at the mean
    density of the outermost ring.
    """
    k = np.arange(1, n_terraces + 1)
    rho = np.sqrt(-2.0 * np.log1p(-mass * k / n_terraces))
    height = (mass / n_terraces) / np.diff(np.pi * rho * rho, prepend=0.0)
    coef = height - np.append(height[1:], 0.0)
    tail = (1.0 - mass) / (np.pi * (rho[-1] ** 2 - rho[-2] ** 2))
    coef[-1] += tail
    coef[-2] -= tail
    return rho, coef


def n_strips_for(cuu: np.ndarray, cuv: np.ndarray, cvv: np.ndarray, n_strips: int, shear: float) -> np.ndarray:
    """Strips per ellipse: ``n_strips``, raised for tilted thin ellipses so each strip's drift stays small.

    A vertical strip of a tilted ellipse is a parallelogram; the rectangle standing in for it is
    off by the parallelogram's vertical drift across the strip, which relative to the strip's
    height is about κ/S with κ = |c|/√(1-c²) (c the u-v correlation). S = ⌈shear·κ⌉ keeps that
    near 1/shear. κ depends on orientation and eccentricity only (at most (e - 1/e)/2 for an
    e:1 ellipse), never on the spread. Capped at :data:`MAX_STRIPS` (or ``n_strips`` if larger).
    """
    c = np.clip(cuv / np.sqrt(cuu) / np.sqrt(cvv), -1.0, 1.0)  # no product of variances: no under/overflow
    kappa = np.abs(c) / np.sqrt((1.0 - np.abs(c)) * (1.0 + np.abs(c)))
    return np.maximum(n_strips, np.minimum(np.ceil(shear * kappa), MAX_STRIPS)).astype(np.int64)


def strip_tables(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Strip geometry of the unit circle for each strip count in ``counts``.

    The circle is cut at u = sin θ_i with θ equally spaced over [-π/2, π/2], which puts the narrow
    strips where the boundary is steep. For count S stored at ``offset``: edges
    ``t[offset + i + 1]`` (i < S), area centroids ``tbar[offset + i]`` and half-heights
    ``eta[offset + i]`` of the rectangles with each strip's exact area. Returns (offsets, t, tbar, eta).
    """
    offsets = np.concatenate([[0], np.cumsum(counts + 1)])
    t, tbar, eta = (np.zeros(offsets[-1]) for _ in range(3))
    for count, off in zip(counts, offsets[:-1], strict=False):
        theta = np.linspace(-0.5 * np.pi, 0.5 * np.pi, count + 1)
        edge = np.sin(theta)
        edge[0], edge[-1] = -1.0, 1.0
        area = np.diff(theta + edge * np.cos(theta))  # ∫ 2cos²θ dθ: twice the unit circle's strip area
        moment = np.diff(-2.0 / 3.0 * np.cos(theta) ** 3)  # ∫ 2u cos θ du: its first moment in u
        t[off : off + count + 1] = edge
        tbar[off : off + count] = moment / area
        eta[off : off + count] = area / (2.0 * np.diff(edge))
    return offsets[:-1], t, tbar, eta


def locality_order(
    shape: tuple[int, int], uc: np.ndarray, vc: np.ndarray, cuu: np.ndarray, cvv: np.ndarray, tile: int = 32
) -> np.ndarray:
    """An order of the Gaussians in which neighbours read nearby parts of the summed-area table.

    The kernel is bound by memory latency on tables larger than the cache; sorting by the
    ``tile``-cell block of the (clipped) centre, then by spread, makes consecutive Gaussians share
    cache lines (3-10x faster on a 2000 x 2000 grid with random centres).
    """
    h, w = shape
    tu = (np.clip(uc, 0, w - 1) // tile).astype(np.int64)
    tv = (np.clip(vc, 0, h - 1) // tile).astype(np.int64)
    spread = np.clip(np.log2(np.sqrt(np.maximum(cuu, cvv))) + 8, 0, 63).astype(np.int64)
    return np.argsort((tv * (w // tile + 1) + tu) * 64 + spread, kind="stable")


@nb.njit(cache=True, inline="always")
def _disc_column(x):
    """∫_0^x √(1-s²) ds: area under the upper half of the unit circle."""
    return 0.5 * (x * np.sqrt(max(1.0 - x * x, 0.0)) + np.arcsin(x))


@nb.njit(cache=True, inline="always")
def _line_roots(a, b, ta, tb):
    """Where the line y = a + b x meets the unit circle, clamped to [ta, tb] (both ta if it misses)."""
    qa = 1.0 + b * b
    qb = 2.0 * a * b
    disc = qb * qb - 4.0 * qa * (a * a - 1.0)
    if not disc > 0.0:
        return ta, ta
    r = np.sqrt(disc)
    return min(max((-qb - r) / (2.0 * qa), ta), tb), min(max((-qb + r) / (2.0 * qa), ta), tb)


@nb.njit(cache=True, inline="always")
def _band_piece(p, q, a_lo, a_hi, b):
    """Area between the disc's and the lines' binding bounds over [p, q], where neither changes."""
    if q <= p:
        return 0.0
    m = 0.5 * (p + q)
    top = np.sqrt(max(1.0 - m * m, 0.0))
    if a_hi + b * m < top:
        upper = a_hi * (q - p) + 0.5 * b * (q * q - p * p)
        up_m = a_hi + b * m
    else:
        upper = _disc_column(q) - _disc_column(p)
        up_m = top
    if a_lo + b * m > -top:
        lower = a_lo * (q - p) + 0.5 * b * (q * q - p * p)
        lo_m = a_lo + b * m
    else:
        lower = -(_disc_column(q) - _disc_column(p))
        lo_m = -top
    return upper - lower if up_m > lo_m else 0.0


@nb.njit(cache=True)
def disc_band_area(ta, tb, a_lo, a_hi, b):
    """Area of {ta <= x <= tb, x² + y² <= 1, a_lo + b x <= y <= a_hi + b x}: a strip of the unit
    disc between two parallel lines (a grid's two edges across the strips, mapped to the disc)."""
    r1, r2 = _line_roots(a_lo, b, ta, tb)
    r3, r4 = _line_roots(a_hi, b, ta, tb)
    # Merge the two sorted pairs: on each of the five pieces the binding bounds are fixed.
    m1 = min(r1, r3)
    m4 = max(r2, r4)
    m2 = min(max(r1, r3), min(r2, r4))
    m3 = max(max(r1, r3), min(r2, r4))
    return (
        _band_piece(ta, m1, a_lo, a_hi, b)
        + _band_piece(m1, m2, a_lo, a_hi, b)
        + _band_piece(m2, m3, a_lo, a_hi, b)
        + _band_piece(m3, m4, a_lo, a_hi, b)
        + _band_piece(m4, tb, a_lo, a_hi, b)
    )


@nb.njit(cache=True, inline="always")
def _band_span(a_lo, a_hi, b):
    """x-range of {x² + y² <= 1, a_lo + b x <= y <= a_hi + b x}: the part of the unit disc between
    two parallel lines, as (lo, hi) with hi <= lo when it is empty.

    The set is convex, so its extreme x are at the lines' crossings with the circle or at (±1, 0).
    """
    lo = np.inf
    hi = -np.inf
    for x in (-1.0, 1.0):
        if a_lo + b * x <= 0.0 <= a_hi + b * x:
            lo = min(lo, x)
            hi = max(hi, x)
    for a in (a_lo, a_hi):
        r1, r2 = _line_roots(a, b, -1.0, 1.0)
        if r2 > r1:
            lo = min(lo, r1)
            hi = max(hi, r2)
    return lo, hi


@nb.njit(cache=True, inline="always")
def _ellipse_sum(sat, uc, vc, su, slope, half, extent, other, transposed, rho, ns, off, t, tbar, eta):
    """R(ρ): the table's sum over the ellipse of Mahalanobis radius ρ, as ``ns`` strip rectangles.

    Strips run across u (columns, or rows when ``transposed``); the grid spans [0, ``extent``]
    along u and [0, ``other``] along v. When the ellipse reaches beyond the grid its strips are
    spread over the u-range of its part on the grid (between the u edges, and within the u-range of
    its piece between the v edges), so none is wasted off the grid and the u edges are cut
    exactly, areas and centroids in closed form. A strip crossing
    a v edge gets the exact area of its piece inside the grid (:func:`disc_band_area`), as a
    rectangle against that edge.
    """
    width = rho * su
    shift = slope * width
    height = rho * half
    # Only the part of the ellipse over the grid gets strips: between the grid's u edges and
    # within the u-range of its piece between the v edges (a thin cap of a large tilted ellipse
    # across a v edge would otherwise fall into a few of the strips).
    b_lo, b_hi = _band_span(-vc / height, (other - vc) / height, -shift / height)
    t_lo = max(-uc / width, b_lo)
    t_hi = min((extent - uc) / width, b_hi)
    if t_hi <= t_lo:
        return 0.0
    clipped = t_lo > -1.0 or t_hi < 1.0
    th_b = np.arcsin(t_lo)
    th_step = (np.arcsin(t_hi) - th_b) / ns
    sin_step = np.sin(th_step)  # edges by rotation: no trigonometry per strip
    cos_step = np.cos(th_step)
    tb = t_lo
    cb = np.sqrt(1.0 - t_lo * t_lo)
    total = 0.0
    for i in range(ns):
        if clipped:
            # Spread the strips over the part of the ellipse between the grid's u edges.
            th_a, ta, ca = th_b, tb, cb
            th_b = th_a + th_step
            tb = min(ta * cos_step + ca * sin_step, 1.0)
            cb = max(ca * cos_step - ta * sin_step, 0.0)
            area = th_b + tb * cb - th_a - ta * ca  # twice the piece's area in the unit disc
            if not (area > 0.0 and tb > ta):
                continue
            tm = -2.0 / 3.0 * (cb * cb * cb - ca * ca * ca) / area
            e = area / (2.0 * (tb - ta))
        else:
            ta = t[off + i]
            tb = t[off + i + 1]
            tm = tbar[off + i]
            e = eta[off + i]
        hh = height * e
        vm = vc + shift * tm
        v0 = vm - hh
        v1 = vm + hh
        # The strip lies within the centre line at its edges ± its widest half-chord.
        chord = height if ta < 0.0 < tb else height * np.sqrt(max(1.0 - min(ta * ta, tb * tb), 0.0))
        reach_lo = vc + min(shift * ta, shift * tb) - chord
        reach_hi = vc + max(shift * ta, shift * tb) + chord
        if reach_hi <= 0.0 or reach_lo >= other:
            continue
        if reach_lo < 0.0 or reach_hi > other:
            # The grid's v edges are lines in the unit disc's coordinates (v = vc + shift x + height y).
            inside = disc_band_area(ta, tb, -vc / height, (other - vc) / height, -shift / height)
            inside *= height / (tb - ta)  # mean v-length of the piece inside the grid, in cells
            if inside < 2.0 * hh * (1.0 - 1e-12):
                if reach_lo < 0.0 and reach_hi > other:
                    v0 = max(vm - 0.5 * inside, 0.0)
                    v0 = min(v0, other - inside)
                elif reach_lo < 0.0:
                    v0 = 0.0
                else:
                    v0 = other - inside
                v1 = v0 + inside
            else:  # all of the piece is inside: keep its rectangle inside too
                v0 = min(max(v0, 0.0), other - 2.0 * hh)
                v1 = v0 + 2.0 * hh
        if transposed:
            total += sat_rect(sat, v0, v1, uc + width * ta, uc + width * tb)
        else:
            total += sat_rect(sat, uc + width * ta, uc + width * tb, v0, v1)
    return total


@nb.njit(cache=True, inline="always")
def _maha2(du, dv, su, sv, c):
    """Squared Mahalanobis length of (du, dv) for σ_u = ``su``, σ_v = ``sv``, correlation ``c``:
    standardised first, so neither 1e-300 nor 1e300 cells² under- or overflows."""
    x = du / su
    y = dv / sv
    return (x * x - 2.0 * c * x * y + y * y) / ((1.0 - c) * (1.0 + c))


@nb.njit(cache=True, inline="always")
def root_det(cuu, cuv, cvv):
    """√det of [[cuu, cuv], [cuv, cvv]] (cells²) as σ_u σ_v √(1 - c²), and (σ_u, σ_v, c): no variance is squared."""
    su = np.sqrt(cuu)
    sv = np.sqrt(cvv)
    c = min(max(cuv / su / sv, -1.0), 1.0)
    return su * sv * np.sqrt((1.0 - c) * (1.0 + c)), su, sv, c


@nb.njit(cache=True)
def grid_radii(uc, vc, cuu, cuv, cvv, w, h):
    """Squared Mahalanobis distances from the mean to the grid [0,w]x[0,h] and which edges are nearer.

    Returns (lo2, hi2, rows): lo2 to the grid's nearest point (0 inside), hi2 to its farthest
    corner, and ``rows`` True when the nearer of the edges v = 0, v = h (as segments) is nearer
    than the nearer of u = 0, u = w: strips then run across rows so those edges are cut exactly.
    """
    su, sv, c = root_det(cuu, cuv, cvv)[1:]
    hi = 0.0
    for cu in (0.0, w):
        for cv in (0.0, h):
            hi = max(hi, _maha2(cu - uc, cv - vc, su, sv, c))
    # On an edge u = U the quadratic is least at dv = (cuv / cuu) du, clamped to the edge.
    d_cols = np.inf
    for cu in (0.0, w):
        du = cu - uc
        dv = min(max(vc + cuv / cuu * du, 0.0), h) - vc
        d_cols = min(d_cols, _maha2(du, dv, su, sv, c))
    d_rows = np.inf
    for cv in (0.0, h):
        dv = cv - vc
        du = min(max(uc + cuv / cvv * dv, 0.0), w) - uc
        d_rows = min(d_rows, _maha2(du, dv, su, sv, c))
    inside = 0.0 <= uc <= w and 0.0 <= vc <= h
    return (0.0 if inside else min(d_cols, d_rows)), hi, d_rows < d_cols


@nb.njit(cache=True, parallel=True)
def near_grid(uc, vc, cuu, cuv, cvv, w, h, max_rho, max_spread):
    """True for Gaussians within Mahalanobis distance ``max_rho`` of the grid [0,w]x[0,h] whose
    2π√det (pixel²) is at most ``max_spread`` times the grid's area: most of their mass is on it."""
    out = np.empty(uc.shape[0], dtype=np.bool_)
    for n in nb.prange(uc.shape[0]):
        lo2 = grid_radii(uc[n], vc[n], cuu[n], cuv[n], cvv[n], w, h)[0]
        spread = 2.0 * np.pi * root_det(cuu[n], cuv[n], cvv[n])[0]
        out[n] = lo2 <= max_rho * max_rho and spread <= max_spread * w * h
    return out


@nb.njit(cache=True, inline="always")
def _orient(rows, uc, vc, cuu, cvv, w, h):
    """(strip-axis centre, other-axis centre, strip-axis σ, grid size along it, along the other)."""
    if rows:
        return vc, uc, np.sqrt(cvv), h, w
    return uc, vc, np.sqrt(cuu), w, h


@nb.njit(cache=True, parallel=True)
def _terrace_kernel(sat, uc, vc, cuu, cuv, cvv, strips, offset, n_terraces, rho_mass, t, tbar, eta, out):
    h = float(sat.shape[0] - 1)
    w = float(sat.shape[1] - 1)
    r_grid = sat[sat.shape[0] - 1, sat.shape[1] - 1]
    for n in nb.prange(uc.shape[0]):
        lo2, hi2, transposed = grid_radii(uc[n], vc[n], cuu[n], cuv[n], cvv[n], w, h)
        if lo2 > _FAR:
            out[n] = 0.0
            continue
        lo = np.sqrt(lo2)
        whole = hi2 <= lo2 + rho_mass * rho_mass  # the terraces reach the far corner
        end = np.sqrt(hi2) if whole else np.sqrt(lo2 + rho_mass * rho_mass)
        sd = root_det(cuu[n], cuv[n], cvv[n])[0]
        a, b, saa, extent, other = _orient(transposed, uc[n], vc[n], cuu[n], cvv[n], w, h)
        slope = cuv[n] / saa / saa  # not / saa²: that overflows at 1e300 cells²
        half = sd / saa  # half-height of the unit ellipse at its centre column
        step = (end - lo) / n_terraces
        acc = 0.0
        r_k = 0.0
        r_prev = 0.0
        rho = lo
        for k in range(1, n_terraces + 1):
            rho = lo + k * step
            r_prev = r_k
            if k == n_terraces and whole:
                r_k = r_grid
            else:
                r_k = _ellipse_sum(
                    sat, a, b, saa, slope, half, extent, other, transposed, rho, strips[n], offset[n], t, tbar, eta
                )
            weight = step * rho * np.exp(-0.5 * rho * rho)
            acc += (0.5 * weight if k == n_terraces else weight) * r_k
        # Beyond ρ_end: R(ρ) ≈ R(ρ_end) + δ·(area beyond), δ from the outermost ring; δ = 0 if whole.
        delta = 0.0
        if not whole:
            rho_prev = rho - step
            delta = (r_k - r_prev) / (np.pi * sd * (rho * rho - rho_prev * rho_prev))
        out[n] = (acc + np.exp(-0.5 * end * end) * r_k) / (2.0 * np.pi * sd) + np.exp(-0.5 * end * end) * delta


@nb.njit(cache=True, parallel=True)
def _paper_kernel(sat, uc, vc, cuu, cuv, cvv, strips, offset, rho, coef, t, tbar, eta, out):
    h = float(sat.shape[0] - 1)
    w = float(sat.shape[1] - 1)
    for n in nb.prange(uc.shape[0]):
        sd = root_det(cuu[n], cuv[n], cvv[n])[0]
        transposed = grid_radii(uc[n], vc[n], cuu[n], cuv[n], cvv[n], w, h)[2]
        a, b, saa, extent, other = _orient(transposed, uc[n], vc[n], cuu[n], cvv[n], w, h)
        acc = 0.0
        for k in range(rho.shape[0]):
            acc += coef[k] * _ellipse_sum(
                sat, a, b, saa, cuv[n] / saa / saa, sd / saa, extent, other, transposed, rho[k], strips[n], offset[n], t, tbar, eta
            )
        out[n] = acc / sd


def integrate_terraces(
    prior: TerrainPrior,
    uc: np.ndarray,
    vc: np.ndarray,
    cuu: np.ndarray,
    cuv: np.ndarray,
    cvv: np.ndarray,
    squared: bool,
    n_terraces: int,
    n_strips: int,
    mass: float,
    shear: float,
    scheme: Literal["adaptive", "paper"],
) -> np.ndarray:
    """The terrace integrals (per m², or per m⁴ when ``squared``) of Gaussians in pixel units
    (:func:`pixel_gaussians`), with settings already checked by :func:`tracker.integrate.integrate_checked`."""
    strips = n_strips_for(cuu, cuv, cvv, n_strips, shear)
    counts, which = np.unique(strips, return_inverse=True)
    offsets, t, tbar, eta = strip_tables(counts)
    order = locality_order(prior.grid.shape, uc, vc, cuu, cvv)
    args = [a[order] for a in (uc, vc, cuu, cuv, cvv, strips, offsets[which])]
    sat = np.asarray(prior.sat2 if squared else prior.sat).view()
    sat.flags.writeable = False  # the kernels' one signature, whether or not the prior's table is read-only
    out = np.empty(uc.shape[0])
    if scheme == "adaptive":
        _terrace_kernel(sat, *args, int(n_terraces), np.sqrt(-2.0 * np.log1p(-mass)), t, tbar, eta, out)
    else:
        _paper_kernel(sat, *args, *paper_rule(int(n_terraces), mass), t, tbar, eta, out)
    result = np.empty_like(out)
    # The kernels work in pixels: mass / √det(pixel²) is per pixel area; divide by its m².
    result[order] = out / prior.grid.cell_area
    return result
