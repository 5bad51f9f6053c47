"""Scale-space integration of 2-D Gaussians against a terrain prior: a Gaussian pyramid of the prior.

The identity behind it: a Gaussian G_A splits as G_{s²I} ⊛ G_C with C = A - s²I whenever s² is at
most A's smaller eigenvalue, so

    ∫ G(y; a, A) r(y) dy = E_{z ~ N(a, C)} [ f_s(z) ],    f_s = r ⊛ G_{s²I}.

The prior smoothed at scale s, f_s, is stored once per prior on lattices of spacing s/γ for scales
s_k = s_0 q^k (a Gaussian pyramid, as cubic B-spline coefficients). Each integral picks the largest
stored s_k under its smaller standard deviation and averages f_{s_k} over the leftover Gaussian
N(a, C) with a product rule in C's eigenframe: Gauss-Hermite where C is narrow against s_k, the
trapezoid rule (spacing ≤ α s_k) along an eccentric major axis. f_s is smooth on the scale s, so a
few lattice look-ups give an integral accurate to ~1e-4 whatever the spread: the cost depends on the
eccentricity and on where the smaller σ falls between two levels, never on the spread.

Levels k < CELL_LEVELS (s_k ≤ 16 cells) are exact: r is constant on cells, so f_{s_k} at a node
is Σ_cells r · ΔΦ_u · ΔΦ_v. Each higher level k+1 comes from level k by the trapezoid rule on the
lattice (f_{s_{k+1}} = f_{s_k} ⊛ G_d, d² = s_{k+1}² - s_k²), accurate to ~e^{-2π²γ² d²/(s_k²+d²)}
because f_{s_k} is band-limited on the scale s_k.
Lattices reach 7 s_k beyond the grid (the prior is zero off the grid; f_s there is below Φ(-7)).
Coefficients come from a finite prefilter (:data:`FIR` taps a side), so each is local.
Gaussians whose smaller σ is under s_0 are smoothed at that σ exactly, on the fly, from the cells
around each point of the rule.

Units: Gaussians in pixel units (u = column, v = row, cells; :func:`tracker.integrate.terraces.pixel_gaussians`);
values in the prior's units (per m² for r, per m⁴ for r²), since a Gaussian normalised in pixels
averages r. The method and its measurements: docs/terrace.md.
"""

from __future__ import annotations

import threading
import weakref
from typing import NamedTuple

import numba as nb
import numpy as np
from scipy.special import ndtr

from pipeline.prior import TerrainPrior
from tracker.integrate.terraces import grid_radii, root_det
from tracker.integrate.tiny import TINY

FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}
"""LLVM fast-math flags for the kernels: fused multiply-adds and reassociation (~30 % faster),
but not 'no NaNs/infinities' (the checks in :func:`_one` and :func:`_phi` must stay)."""
S0 = 2.0**0.75
"""Finest stored smoothing scale, cells (1.68). Gaussians with a smaller σ are smoothed at their own
smaller σ on the fly, exactly, from the cells near each point (:func:`_window`). Why not 1 cell, as
before session 22: levels at s = 1, 1.19 and 1.41 cells hold 8.8 of the 13.7 nodes per cell of all
levels (4, 2.8 and 2 nodes per cell), so they were 64 % of a pyramid's memory and of its build,
while a Gaussian that would read them costs 1.5-2x more from the cells when its eccentricity is
below ~1.5 and 4x more at 2:1. They paid for themselves only on priors that serve more than
~0.1-0.7 such integrals per cell (docs/terrace.md, "Session 22")."""
RATIO = 2.0**0.25
"""Ratio of consecutive scales."""
GAMMA = 2.0
"""Lattice nodes per smoothing σ (spacing s/γ)."""
PAD = 7.0
"""Lattice margin beyond the grid, in σ of the level."""
TILE = 32
"""Nodes per side of the blocks each level is stored in. A block keeps the 3-node apron its last
nodes' 4 x 4 B-spline footprints reach (35 x 35 float32, 4.9 KiB), so a look-up reads four rows
140 bytes apart in one block instead of four rows a lattice-width apart: 1.3x faster at σ = 3
cells on a 2,000² prior (lattices larger than the cache), 20 % more memory; a power of two keeps
the block arithmetic to shifts."""
BLOCK = (TILE + 3) ** 2
"""Floats per stored block (a TILE x TILE node block with its apron)."""
MAX_CELLS = 25_000_000
"""Largest grid (cells) :func:`tracker.integrate.integrate` builds a whole pyramid for (~1.3 GiB peak
at this size, see :func:`pyramid_bytes`); larger priors get a :class:`tracker.integrate.lazy.LazyPyramid`
(the same lattices, built per tile where Gaussians fall, in a bounded cache)."""


def lattice(k: int, shape: tuple[int, int]) -> tuple[float, float, float, int, int]:
    """Level ``k`` of a pyramid of a grid of ``shape`` (H, W) cells: its scale s_k and node spacing h
    (cells), the pixel coordinate of node 0 on both axes, and its node counts (nu, nv); node j on an
    axis is at ``origin + h * j``."""
    s = S0 * RATIO**k
    h = s / GAMMA
    height, width = shape
    pad = PAD * s + 2.0 * h
    return s, h, -pad, int(np.ceil((width + 2 * pad) / h)) + 1, int(np.ceil((height + 2 * pad) / h)) + 1


def pyramid_bytes(shape: tuple[int, int]) -> float:
    """Peak bytes to build and keep a pyramid of r (or r²) for a grid of ``shape`` cells: its float32
    levels (~3.4 x level 0) and, while level 0 is built, three float64 arrays of its size."""
    nodes0 = (GAMMA / S0) ** 2 * shape[0] * shape[1]
    return nodes0 * (4 * ((TILE + 3) / TILE) ** 2 / (1 - RATIO**-2) + 3 * 8)


class Packed(NamedTuple):
    """A pyramid's levels as the kernel reads them: per level ``scale`` s_k and lattice ``step``
    (cells), ``u0``/``v0`` the pixel coordinates of node (0, 0), node counts ``nu``/``nv``, and
    ``offset`` into ``coef``, the cubic B-spline coefficients of all levels (float32, in blocks of
    :data:`TILE` nodes with their aprons, see :func:`_tile`)."""

    scale: np.ndarray
    step: np.ndarray
    u0: np.ndarray
    v0: np.ndarray
    nu: np.ndarray
    nv: np.ndarray
    offset: np.ndarray
    coef: np.ndarray


class Pyramid:
    """f_{s_k} = r ⊛ G_{s_k} for s_k = S0·RATIO^k, k = 0..L-1, L growing on demand (thread-safe).

    ``field`` is the (H, W) array of the prior's values per cell (density or density²).
    """

    def __init__(self, field: np.ndarray) -> None:
        self.field = np.ascontiguousarray(field, dtype=np.float64)
        self.packed = Packed(*(np.zeros(0) for _ in range(4)), *(np.zeros(k, np.int64) for k in (0, 0, 1)), np.zeros(0, np.float32))
        self._lock = threading.Lock()
        self._table = np.zeros(0, np.uint32)

    def slots(self, p: Packed) -> tuple[np.ndarray, np.ndarray]:
        """The block table and per-level offsets into it of the levels ``p``: block b of level k is block
        ``offset[k] // BLOCK + b`` of ``coef`` (the kernel reads a whole pyramid through the same kind of
        table as a lazy one, so both give the same numbers; see :func:`_spline_at`)."""
        return self._table, p.offset // BLOCK

    def levels(self, top_scale: float) -> Packed:
        """The levels up to the first with s_k >= ``top_scale`` cells (at least level 0), built if missing.

        Returns a consistent snapshot: later growth replaces, never changes, the arrays it holds."""
        with self._lock:
            p = self.packed
            if p.scale.size and p.scale[-1] >= top_scale:
                return p
            new = []
            k = p.scale.size
            while True:
                s, h, origin, n_u, n_v = lattice(k, self.field.shape)
                u = origin + h * np.arange(n_u)
                v = origin + h * np.arange(n_v)
                if k < FUSED_LEVELS:
                    coef = fused_coefficients(lambda r0, r1, c0, c1: self.field[r0:r1, c0:c1], k, self.field.shape,
                                              (0, n_v), (0, n_u))
                elif k < CELL_LEVELS:
                    coef = _prefilter(_exact_level(self.field, u, v, s))
                else:
                    # The level below, sampled at its nodes, from its float32 coefficients: the same
                    # numbers whether it was built in this call or an earlier one.
                    if new:
                        ps, ph, po, _, coef = new[-1]
                    else:
                        ps, ph, po = p.scale[-1], p.step[-1], p.u0[-1]
                        coef = _untile(p.coef[p.offset[-2] :], (int(p.nv[-1]), int(p.nu[-1])))
                    coef = _prefilter(_smooth(_node_values(np.ascontiguousarray(coef)), po, ph, u, v, np.sqrt(s * s - ps * ps)))
                new.append((s, h, origin, coef.shape, coef))
                k += 1
                if s >= top_scale:
                    break
            tiled = [_tile(n[4]) for n in new]
            sizes = np.cumsum([t.size for t in tiled])
            self.packed = Packed(
                np.append(p.scale, [n[0] for n in new]),
                np.append(p.step, [n[1] for n in new]),
                np.append(p.u0, [n[2] for n in new]),
                np.append(p.v0, [n[2] for n in new]),
                np.append(p.nu, [n[3][1] for n in new]).astype(np.int64),
                np.append(p.nv, [n[3][0] for n in new]).astype(np.int64),
                np.append(p.offset, p.offset[-1] + sizes).astype(np.int64),
                np.concatenate([p.coef, *tiled]),
            )
            self._table = np.arange(self.packed.coef.size // BLOCK, dtype=np.int32)  # grows with the levels
            return self.packed


def _tile(coef: np.ndarray) -> np.ndarray:
    """A level's (nv, nu) coefficients as blocks of TILE x TILE nodes, each with the nodes one before
    and two after it on both axes (zeros beyond the lattice), block rows first; flattened."""
    nv, nu = coef.shape
    ntv, ntu = -(-nv // TILE), -(-nu // TILE)
    padded = np.zeros((ntv * TILE + 3, ntu * TILE + 3), np.float32)
    padded[1 : nv + 1, 1 : nu + 1] = coef
    blocks = np.lib.stride_tricks.sliding_window_view(padded, (TILE + 3, TILE + 3))[::TILE, ::TILE]
    return np.ascontiguousarray(blocks).ravel()


def _untile(flat: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The (nv, nu) coefficients back from :func:`_tile`'s blocks."""
    nv, nu = shape
    ntv, ntu = -(-nv // TILE), -(-nu // TILE)
    blocks = flat.reshape(ntv, ntu, TILE + 3, TILE + 3)[:, :, 1 : TILE + 1, 1 : TILE + 1]
    return blocks.transpose(0, 2, 1, 3).reshape(ntv * TILE, ntu * TILE)[:nv, :nu]


def _band(first: np.ndarray, n_src: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Start indices (clipped so a band of ``width`` fits in ``n_src``) and the (nodes, width) source indices."""
    width = min(width, n_src)
    start = np.clip(first, 0, n_src - width).astype(np.int64)
    return start, start[:, None] + np.arange(width)


def _box_weights(nodes: np.ndarray, n_cells: int, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Banded weights ΔΦ, the mass of cell [i, i+1] under N(node, s²), over ±8 s: (start, (nodes, band))."""
    reach = int(np.ceil(8.0 * s)) + 1
    start, idx = _band(np.floor(nodes).astype(np.int64) - reach, n_cells, 2 * reach + 1)
    # Φ at each cell edge once: the band's edges are idx and idx[:, -1] + 1
    edges = ndtr((np.concatenate([idx, idx[:, -1:] + 1], axis=1) - nodes[:, None]) / s)
    return start, edges[:, 1:] - edges[:, :-1]


def _gauss_weights(nodes: np.ndarray, origin: float, n_src: int, d: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Banded trapezoid weights h·φ_d(node - src) for a source lattice origin + h·j, over ±10 d."""
    reach = int(np.ceil(10.0 * d / h)) + 1
    start, idx = _band(np.floor((nodes - origin) / h).astype(np.int64) - reach, n_src, 2 * reach + 1)
    x = (nodes[:, None] - origin - h * idx) / d
    return start, h * np.exp(-0.5 * x * x) / (np.sqrt(2 * np.pi) * d)


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _transpose(a):
    """``a.T`` as a new C-ordered array, copied in 32 x 32 blocks (each block's reads and writes stay in
    cache) on numba's threads: a whole level's 5,000² on two takes 0.20 s, numba's serial
    ``np.ascontiguousarray(a.T)`` 0.27 s."""
    h, w = a.shape
    out = np.empty((w, h), a.dtype)
    for ib in nb.prange((h + 31) // 32):
        i0 = ib * 32
        for j0 in range(0, w, 32):
            for i in range(i0, min(i0 + 32, h)):
                for j in range(j0, min(j0 + 32, w)):
                    out[j, i] = a[i, j]
    return out


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy", fastmath=FAST)
def _band_rows(src, start, weights):
    """out[m] = Σ_b weights[m, b] · src[start[m] + b]: whole rows added (contiguous, so they vectorise)."""
    n, band = weights.shape
    out = np.zeros((n, src.shape[1]))
    for m in nb.prange(n):
        for b in range(band):
            w = weights[m, b]
            row = src[start[m] + b]
            for j in range(src.shape[1]):
                out[m, j] += w * row[j]
    return out


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _separable(values, su, wu, sv, wv):
    """out[m, n] = Σ_b wv[m, b] Σ_c wu[n, c] values[sv[m] + b, su[n] + c]: rows first, then columns.
    Both passes add whole rows (:func:`_band_rows`) rather than gather along a row: the first runs on
    the transposed values and its result is transposed back (1.6x faster at level 0)."""
    return _band_rows(_transpose(_band_rows(_transpose(values), su, wu)), sv, wv)


def _exact_level(values: np.ndarray, u: np.ndarray, v: np.ndarray, s: float) -> np.ndarray:
    """f_s at the nodes u × v exactly: Σ_cells value · ΔΦ_u · ΔΦ_v (the field is constant on cells)."""
    return _separable(values, *_box_weights(u, values.shape[1], s), *_box_weights(v, values.shape[0], s))


def _smooth(values: np.ndarray, origin: float, h: float, u: np.ndarray, v: np.ndarray, d: float) -> np.ndarray:
    """f ⊛ G_d at the nodes u × v from samples of f on the lattice origin + h·(j, i)."""
    nv, nu = values.shape
    return _separable(values, *_gauss_weights(u, origin, nu, d, h), *_gauss_weights(v, origin, nv, d, h))


@nb.njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _node_values(coef):
    """A 2-D cubic B-spline's values at its nodes, (c₋ + 4c + c₊)/6 each way (mirror ends), float64."""
    h, w = coef.shape
    rows = np.empty((h, w))
    for j in nb.prange(h):
        for i in range(w):
            left = coef[j, i - 1] if i > 0 else coef[j, min(1, w - 1)]
            right = coef[j, i + 1] if i < w - 1 else coef[j, max(w - 2, 0)]
            rows[j, i] = (left + 4.0 * coef[j, i] + right) / 6.0
    out = np.empty((h, w))
    for j in nb.prange(h):
        up = j - 1 if j > 0 else min(1, h - 1)
        down = j + 1 if j < h - 1 else max(h - 2, 0)
        for i in range(w):
            out[j, i] = (rows[up, i] + 4.0 * rows[j, i] + rows[down, i]) / 6.0
    return out


_POLE = np.sqrt(3.0) - 2.0  # of the cubic B-spline's interpolation filter
FIR = 14
"""Taps each side of the B-spline prefilter (the inverse of the (1, 4, 1)/6 filter, √3·z^|m| with
z = √3 - 2, truncated at |m| = FIR; the lattice is zero beyond its ends). The truncation changes a
coefficient by at most ~4.7·|z|^15 = 1e-8 of the values around it, below float32 rounding. A
finite filter makes a coefficient depend on its 2·FIR + 1 neighbours only: a lazy tile computes the
same numbers as the whole lattice, and needs FIR nodes of values beyond it, not whole rows."""
CELL_LEVELS = int(round(4 * np.log2(16.0 / S0))) + 1
"""Levels k < CELL_LEVELS (s_k up to 16 cells: 14 levels) are exact cell sums Σ r·ΔΦ_u·ΔΦ_v at their nodes; higher
levels come from the level below by the trapezoid rule. Cell sums make a level independent of the
levels below (a lazy tile of it reads cells only, within 8 s_k + 1 of its nodes)."""


_TAPS = np.append(np.sqrt(3.0) * _POLE ** np.abs(np.arange(-FIR, FIR + 1)), 0.0)  # the last: off the band


def _fir_weights(first: int, last: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Banded prefilter weights for the nodes [first, last) of a lattice axis of ``n`` nodes:
    (start, (nodes, band)) with weight √3·z^|i - node| on |i - node| <= FIR (0 off the band)."""
    nodes = np.arange(first, last)
    start, idx = _band(nodes - FIR, n, 2 * FIR + 1)
    gap = idx - nodes[:, None] + FIR
    return start, _TAPS[np.where((gap >= 0) & (gap <= 2 * FIR), gap, 2 * FIR + 1)]


FUSED_LEVELS = int(np.ceil(4 * np.log2(2.0 / S0) - 1e-9))
"""Levels k < FUSED_LEVELS (s_k < 2 cells, more than one node per cell: the finest level alone) get their coefficients from the
cells in one banded pass with the prefilter folded into the cell weights (:func:`_fused_weights`): per
output node ~(8 s + 14 h) cells a side instead of 8 s cells and then 2·FIR + 1 nodes, 1.3-1.7x fewer
multiply-adds there; from s = 2 cells up (a node per cell or fewer) the two passes cost less."""


def _fused_weights(first: int, last: int, n_nodes: int, origin: float, h: float, s: float, n_cells: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Banded weights from cells straight to the B-spline coefficients of the nodes [first, last) of a
    cell level's axis (``n_nodes`` nodes at ``origin + h j``, ``n_cells`` cells): the prefilter's taps
    (:func:`_fir_weights`) applied to the cell masses of their nodes (:func:`_box_weights`),
    w[j, c] = Σ_t fir[j, t] ΔΦ(c; node fs_j + t), summed over t in order. (start, (nodes, band)): the
    band is the same for every node of the level, so a tile's weights are the whole axis's."""
    fs, fw = _fir_weights(first, last, n_nodes)
    taps = fw.shape[1]
    src0 = int(fs[0])
    bs, bw = _box_weights(origin + h * np.arange(src0, int(fs[-1]) + taps), n_cells, s)
    # box starts are floor(node) - reach clipped into the axis: 1-Lipschitz, so taps nodes apart they
    # differ by at most ceil((taps - 1) h) + 1 cells
    width = min(int(np.ceil((taps - 1) * h)) + 1 + bw.shape[1], n_cells)
    start = np.minimum(bs[fs - src0], n_cells - width)
    return start, _fold_taps(fs - src0, fw, bs, bw, start, width)


@nb.njit(cache=True, nogil=True)
def _fold_taps(first, fw, bs, bw, start, width: int):
    """w[j, bs[m] - start[j] + c] += fw[j, t] · bw[m, c] for m = first[j] + t, t in order (the loop of
    :func:`_fused_weights`; no fast-math, so any caller gets the same numbers)."""
    weights = np.zeros((first.size, width))
    for j in range(first.size):
        for t in range(fw.shape[1]):
            m = first[j] + t
            off = bs[m] - start[j]
            for c in range(bw.shape[1]):
                weights[j, off + c] += fw[j, t] * bw[m, c]
    return weights


def fused_coefficients(cells, k: int, shape: tuple[int, int], rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """Level k's (< FUSED_LEVELS) coefficients (float32) at nodes ``rows`` x ``cols`` ([lo, hi) each) of
    the lattice of a grid of ``shape`` cells, from ``cells(r0, r1, c0, c1)``, the grid's values on a window."""
    s, h, origin, nu, nv = lattice(k, shape)
    su, wu = _fused_weights(*cols, nu, origin, h, s, shape[1])
    sv, wv = _fused_weights(*rows, nv, origin, h, s, shape[0])
    c_lo, r_lo = int(su.min()), int(sv.min())
    window = np.ascontiguousarray(cells(r_lo, int(sv.max()) + wv.shape[1], c_lo, int(su.max()) + wu.shape[1]))
    return _separable(window, su - c_lo, wu, sv - r_lo, wv).astype(np.float32)


def _prefilter(values: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients (float32) interpolating the 2-D ``values`` of a whole lattice
    (to 1e-8, see :data:`FIR`), the lattice zero beyond its ends."""
    nv, nu = values.shape
    return _separable(values, *_fir_weights(0, nu, nu), *_fir_weights(0, nv, nv)).astype(np.float32)


# --- quadrature rules -------------------------------------------------------------------------

TOL = 3e-4
"""Worst error of a rule on a unit step smoothed at the level's σ (sets the number of points)."""
TRAP_STEP = 1.6
"""Trapezoid spacing along a wide leftover axis, in σ of the level."""
TRAP_SPAN = 5.0
"""Trapezoid nodes cover ± this many leftover σ."""
GH_SPAN = 5.6
"""Largest |node| of the rules (Gauss-Hermite up to 12 points: 5.50; trapezoid: TRAP_SPAN = 5), in
leftover σ: bounds how far from its centre a Gaussian's look-ups fall."""
MAX_POINTS = 4097
"""Most points along one axis; Gaussians needing more (eccentricity beyond ~500:1) go to the terraces."""


def _step_error(rho: float, x: np.ndarray, w: np.ndarray) -> float:
    """Worst error of the rule (x, w) for E[Φ(ρξ - c)] over offsets c (exact: Φ(-c/√(1+ρ²)))."""
    c = np.linspace(-10.0, 10.0, 401)  # the error is smooth in c: 0.05 apart finds its maximum
    est = ndtr(rho * x[None, :] - c[:, None]) @ w
    return float(np.abs(est - ndtr(-c / np.sqrt(1.0 + rho * rho))).max())


def _gh_tables(tol: float, max_n: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Hermite nodes, normalised weights ((max_n+1, max_n), row n = the n-point rule) and
    ``reach[n]``: the largest leftover ρ (in level σ) that n points integrate to ``tol``."""
    x = np.zeros((max_n + 1, max_n))
    w = np.zeros((max_n + 1, max_n))
    reach = np.zeros(max_n + 1)
    rhos = np.linspace(0.0, 2.0, 201)
    for n in range(1, max_n + 1):
        xn, wn = np.polynomial.hermite_e.hermegauss(n)
        x[n, :n], w[n, :n] = xn, wn / wn.sum()
        for rho in rhos[1:]:
            if _step_error(rho, x[n, :n], w[n, :n]) > tol:
                break
            reach[n] = rho
    return x, w, reach


GH_X, GH_W, GH_REACH = _gh_tables(TOL)


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _rule(rho, xs, ws):
    """Nodes (in units of the leftover σ times ρ, i.e. of the level σ) and weights of a rule for
    E[f(ρ ξ)], ξ ~ N(0, 1): Gauss-Hermite while ρ is small, else the trapezoid rule. Returns the
    count, or 0 when more than ``xs.size`` points would be needed."""
    n_max = GH_REACH.shape[0] - 1
    if rho <= GH_REACH[n_max]:
        n = 1
        while GH_REACH[n] < rho:
            n += 1
        for i in range(n):
            xs[i] = rho * GH_X[n, i]
            ws[i] = GH_W[n, i]
        return n
    m = int(np.ceil(2.0 * TRAP_SPAN * rho / TRAP_STEP)) | 1  # odd: a node at the centre
    if m > xs.shape[0]:
        return 0
    dx = 2.0 * TRAP_SPAN * rho / (m - 1)
    # e^{-x²/2ρ²} at equally spaced x by its ratio recurrence: two exponentials, not m.
    step = dx / rho
    w = np.exp(-0.5 * TRAP_SPAN * TRAP_SPAN)
    ratio = np.exp(TRAP_SPAN * step - 0.5 * step * step)
    shrink = np.exp(-step * step)
    tot = 0.0
    for i in range(m):
        xs[i] = -TRAP_SPAN * rho + i * dx
        ws[i] = w
        tot += w
        w *= ratio
        ratio *= shrink
    for i in range(m):
        ws[i] /= tot
    return m


# --- kernels ----------------------------------------------------------------------------------




@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _spline_at(coef, slots, off, nu, nv, u0, v0, h, u, v):
    """The cubic B-spline of one level at pixel point (u, v), 0 off its (nv, nu) lattice. Block b of the
    level (see :func:`_tile`) is block ``slots[off + b]`` of ``coef`` (BLOCK floats each): a whole
    pyramid's identity table (:meth:`Pyramid.slots`) or a lazy pyramid's, whose blocks not built point
    at an all-NaN block (:data:`tracker.integrate.lazy.MISSING`), so the result is NaN there and the
    lazy pyramid builds them and asks again.

    One access path for both, without a test: a run-time test for which kind of pyramid it reads
    cost the whole pyramid's kernel 12 % of its CPU time, and the test for a missing block ~6 %. A
    separately compiled specialisation for each kind (numba types) would round differently from the
    other in the last bit, depending on whether numba compiled it in the process or loaded it from
    its cache, so the lazy pyramid's integrals would no longer equal the whole one's bit for bit."""
    x = (u - u0) / h
    y = (v - v0) / h
    i = int(np.floor(x))
    j = int(np.floor(y))
    if i < 1 or j < 1 or i + 2 >= nu or j + 2 >= nv:
        return 0.0
    fx = x - i
    fy = y - j
    gx = 1.0 - fx
    gy = 1.0 - fy
    wx0 = gx * gx * gx / 6.0
    wx1 = (3.0 * fx * fx * fx - 6.0 * fx * fx + 4.0) / 6.0
    wx3 = fx * fx * fx / 6.0
    wx2 = 1.0 - wx0 - wx1 - wx3
    wy0 = gy * gy * gy / 6.0
    wy1 = (3.0 * fy * fy * fy - 6.0 * fy * fy + 4.0) / 6.0
    wy3 = fy * fy * fy / 6.0
    wy2 = 1.0 - wy0 - wy1 - wy3
    # The footprint's rows j-1..j+2 and columns i-1..i+2 all lie in the block of (j, i) (see _tile).
    width = TILE + 3
    block = (j // TILE) * ((nu + TILE - 1) // TILE) + i // TILE
    p = slots[off + block] * (width * width) + (j % TILE) * width + i % TILE
    r0 = wx0 * coef[p] + wx1 * coef[p + 1] + wx2 * coef[p + 2] + wx3 * coef[p + 3]
    p += width
    r1 = wx0 * coef[p] + wx1 * coef[p + 1] + wx2 * coef[p + 2] + wx3 * coef[p + 3]
    p += width
    r2 = wx0 * coef[p] + wx1 * coef[p + 1] + wx2 * coef[p + 2] + wx3 * coef[p + 3]
    p += width
    r3 = wx0 * coef[p] + wx1 * coef[p + 1] + wx2 * coef[p + 2] + wx3 * coef[p + 3]
    return wy0 * r0 + wy1 * r1 + wy2 * r2 + wy3 * r3


@nb.njit(cache=True, error_model="numpy", fastmath=FAST)
def _bspline(coef, off, nu, nv, u0, v0, h, u, v):
    """:func:`_spline_at` of a whole pyramid's level stored in blocks at ``coef[off:]``."""
    return _spline_at(coef, np.arange(coef.size // BLOCK, dtype=np.int32), off // BLOCK, nu, nv, u0, v0, h, u, v)


PHI_STEP = 1.0 / 256.0
PHI_EDGE = 8.5
"""Φ is tabulated on [-PHI_EDGE, PHI_EDGE] every PHI_STEP and taken as 0 or 1 beyond (Φ(-8.5) = 1e-17)."""


def _phi_table() -> np.ndarray:
    """(2, M): Φ and φ at the table's nodes, for cubic Hermite interpolation (error < 3e-13)."""
    x = np.arange(-PHI_EDGE, PHI_EDGE + PHI_STEP / 2, PHI_STEP)
    return np.vstack([ndtr(x), np.exp(-0.5 * x * x) / np.sqrt(2.0 * np.pi)])


PHI_TABLE = _phi_table()


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _phi(tab, x):
    """Φ(x) from the table: cubic Hermite on values and slopes, 3-4x faster than libm's erfc."""
    if x <= -PHI_EDGE:
        return 0.0
    if x >= PHI_EDGE:
        return 1.0
    y = (x + PHI_EDGE) / PHI_STEP
    i = min(int(y), tab.shape[1] - 2)
    t = y - i
    t2 = t * t
    t3 = t2 * t
    return (
        (2.0 * t3 - 3.0 * t2 + 1.0) * tab[0, i]
        + (t3 - 2.0 * t2 + t) * PHI_STEP * tab[1, i]
        + (-2.0 * t3 + 3.0 * t2) * tab[0, i + 1]
        + (t3 - t2) * PHI_STEP * tab[1, i + 1]
    )


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _window(values, frames, f, tab, u, v, s, wu):
    """f_s(u, v) exactly: Σ_cells value · ΔΦ_u · ΔΦ_v over the cells within 5 s of the point. Frame
    ``frames[f]`` = (r0, c0, H, W): ``values`` holds the (H, W) grid's cells from row r0, column c0 on, at
    least those read (the whole grid: (0, 0, H, W)). Inlined into :func:`_one` (one call per rule point otherwise:
    4-7 % of the sub-cell Gaussians' time; the same numbers bit for bit)."""
    r0, c0, h, w = frames[f, 0], frames[f, 1], frames[f, 2], frames[f, 3]
    reach = 5.0 * s
    # ceil - 1: a point on a cell edge also weighs the cell that ends there (reach may round to 0).
    i0 = max(int(np.ceil(u - reach)) - 1, 0)
    i1 = min(int(np.floor(u + reach)), w - 1)
    j0 = max(int(np.ceil(v - reach)) - 1, 0)
    j1 = min(int(np.floor(v + reach)), h - 1)
    if i1 < i0 or j1 < j0:
        return 0.0
    inv = 1.0 / s
    prev = _phi(tab, (i0 - u) * inv)
    for i in range(i0, i1 + 1):
        nxt = _phi(tab, (i + 1 - u) * inv)
        wu[i - i0] = nxt - prev
        prev = nxt
    acc = 0.0
    prev = _phi(tab, (j0 - v) * inv)
    for j in range(j0, j1 + 1):
        nxt = _phi(tab, (j + 1 - v) * inv)
        wv = nxt - prev
        prev = nxt
        if wv == 0.0:
            continue
        row = 0.0
        jj = j - r0
        for i in range(i0, i1 + 1):
            row += values[jj, i - c0] * wu[i - i0]
        acc += wv * row
    return acc


@nb.njit(cache=True, error_model="numpy", fastmath=FAST)
def _one(values, frames, f, tab, coef, slots, scale, step, u0, v0, nu, nv, offset, uc, vc, cuu, cuv, cvv, xs1, ws1, xs2, ws2, wu):
    """∫ G r for one Gaussian in pixel units (mean (uc, vc), covariance [[cuu, cuv], [cuv, cvv]] cells²);
    ``slots`` and ``offset``: where each level's blocks are (see :func:`_spline_at`).

    Returns (value, look-ups), look-ups 0 when the Gaussian is too eccentric for the rules."""
    m = 0.5 * (cuu + cvv)
    dd = 0.5 * (cuu - cvv)
    rad = np.sqrt(dd * dd + cuv * cuv)
    lam1 = m + rad
    lam2 = max(m - rad, 0.0)
    th = 0.5 * np.arctan2(2.0 * cuv, cuu - cvv)
    e1u = np.cos(th)
    e1v = np.sin(th)
    if lam2 < scale[0] * scale[0]:
        if frames[f, 2] == 0:  # NO_CELLS: the caller smooths it from the cells (lazy.LazyPyramid._fine)
            return np.nan, -1
        # Finer than the pyramid: smooth at s = the smaller σ exactly, average along the major axis.
        s = np.sqrt(lam2)
        n1 = _rule(np.sqrt(lam1 - lam2) / s, xs1, ws1)
        acc = 0.0
        for i in range(n1):
            a = xs1[i] * s
            acc += ws1[i] * _window(values, frames, f, tab, uc + a * e1u, vc + a * e1v, s, wu)
        return acc, n1
    k = int(np.floor(np.log(np.sqrt(lam2) / scale[0]) / np.log(RATIO) + 1e-9))
    k = min(max(k, 0), scale.shape[0] - 1)
    s = scale[k]
    n1 = _rule(np.sqrt(max(lam1 - s * s, 0.0)) / s, xs1, ws1)
    n2 = _rule(np.sqrt(max(lam2 - s * s, 0.0)) / s, xs2, ws2)
    acc = 0.0
    off = offset[k]
    for i in range(n1):
        a = xs1[i] * s
        pu = uc + a * e1u
        pv = vc + a * e1v
        row = 0.0
        for j in range(n2):
            b = xs2[j] * s
            row += ws2[j] * _spline_at(coef, slots, off, nu[k], nv[k], u0[k], v0[k], step[k], pu - b * e1v, pv + b * e1u)
        acc += ws1[i] * row
    return acc, n1 * n2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def fine_reach(cuu, cuv, cvv):
    """Cells from its mean within which :func:`_one` reads the cells of a Gaussian finer than the
    pyramid (pixel covariances): its rule's farthest point along the major axis (:func:`_rule`, as
    :func:`_one` builds it) plus :func:`_window`'s 5 σ_minor, and 2 cells for the window's rounding.
    Gaussians without a rule (σ_minor 0, or too eccentric) get GH_SPAN σ_major + 3."""
    xs = np.empty(MAX_POINTS)
    ws = np.empty(MAX_POINTS)
    out = np.empty(cuu.shape[0])
    for n in range(cuu.shape[0]):
        m = 0.5 * (cuu[n] + cvv[n])
        dd = 0.5 * (cuu[n] - cvv[n])
        rad = np.sqrt(dd * dd + cuv[n] * cuv[n])
        lam1 = m + rad
        lam2 = max(m - rad, 0.0)
        s = np.sqrt(lam2)
        n1 = _rule(np.sqrt(lam1 - lam2) / s, xs, ws) if s > 0.0 else 0
        if n1 <= 0:
            out[n] = GH_SPAN * np.sqrt(lam1) + 5.0 * s + 3.0
            continue
        far = 0.0
        for i in range(n1):
            far = max(far, abs(xs[i]))
        out[n] = far * s + 5.0 * s + 2.0
    return out


@nb.njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _kernel(values, frames, which, tab, coef, slots, scale, step, u0, v0, nu, nv, offset, uc, vc, cuu, cuv, cvv, order, out, counts,
            n_threads):
    """Gaussian ``order[i]`` for i = 0..N-1, in 256-Gaussian chunks; results go to its own index.
    ``values`` and ``frames``: the cells that Gaussians finer than the pyramid read (see :func:`_window`),
    Gaussian ``order[i]`` through ``frames[which[i]]`` (``which`` empty: every one through ``frames[0]``).
    Several windows of cells can so share one call, stacked in the rows of ``values`` (:func:`stacked_frames`).

    Each chunk first copies its Gaussians out of the inputs (reading them through ``order`` inside
    the loop costs 20 % more: five scattered reads per Gaussian)."""
    chunk = 256
    n_chunks = (order.shape[0] + chunk - 1) // chunk
    # Costs vary along the (level-sorted) order; deal chunks round-robin so the threads' static
    # shares of the range each hold every part of it.
    per = (n_chunks + n_threads - 1) // n_threads
    for q in nb.prange(per * n_threads):
        c = (q % per) * n_threads + q // per
        if c >= n_chunks:
            continue
        xs1 = np.empty(MAX_POINTS)
        ws1 = np.empty(MAX_POINTS)
        xs2 = np.empty(MAX_POINTS)
        ws2 = np.empty(MAX_POINTS)
        wu = np.empty(int(5.0 * 2 * scale[0]) + 9)
        lo = c * chunk
        hi = min(lo + chunk, order.shape[0])
        g = np.empty((hi - lo, 5))
        for i in range(lo, hi):
            n = order[i]
            g[i - lo, 0] = uc[n]
            g[i - lo, 1] = vc[n]
            g[i - lo, 2] = cuu[n]
            g[i - lo, 3] = cuv[n]
            g[i - lo, 4] = cvv[n]
        for i in range(lo, hi):
            r = g[i - lo]
            out[order[i]], counts[order[i]] = _one(
                values, frames, which[i] if which.shape[0] else 0, tab, coef, slots, scale, step, u0, v0, nu, nv, offset, r[0], r[1], r[2], r[3], r[4], xs1, ws1, xs2, ws2, wu
            )


@nb.njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _spread_bits(x):
    """The low 16 bits of x spread to the even bits of a 32-bit word (for a Morton code)."""
    x &= 0xFFFF
    x = (x | (x << 8)) & 0x00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F
    x = (x | (x << 2)) & 0x33333333
    return (x | (x << 1)) & 0x55555555


@nb.njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _order_keys(uc, vc, cuu, cuv, cvv, h, w, tile, smin_out, keys):
    """Smaller σ of each Gaussian (cells) and its sort key: pyramid level, then the Morton code of
    its centre's block of ``tile`` lattice nodes of that level."""
    inv_log = 1.0 / np.log(RATIO)
    for n in nb.prange(uc.shape[0]):
        m = 0.5 * (cuu[n] + cvv[n])
        dd = 0.5 * (cuu[n] - cvv[n])
        smin = np.sqrt(max(m - np.sqrt(dd * dd + cuv[n] * cuv[n]), 0.0))
        smin_out[n] = smin
        level = 0
        size = tile * S0 / GAMMA
        if smin >= S0:
            level = min(int(np.log(smin / S0) * inv_log) + 1, 1023)
            size = tile * S0 * RATIO ** (level - 1) / GAMMA
        tu = int(min(max(uc[n], 0.0), w - 1.0) / size)
        tv = int(min(max(vc[n], 0.0), h - 1.0) / size)
        keys[n] = (level << 32) | (_spread_bits(tv) << 1) | _spread_bits(tu)


_PYRAMIDS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_PYRAMIDS_LOCK = threading.Lock()


def pyramid(prior: TerrainPrior, squared: bool) -> Pyramid:
    """The prior's pyramid of r (or r²), made once per prior object and kept while it lives."""
    with _PYRAMIDS_LOCK:
        per_prior = _PYRAMIDS.setdefault(prior, {})
        if squared not in per_prior:
            values = np.asarray(prior.density, dtype=np.float64)
            per_prior[squared] = Pyramid(values * values if squared else values)
        return per_prior[squared]


def integrate_pixels(
    prior: TerrainPrior, uc: np.ndarray, vc: np.ndarray, cuu: np.ndarray, cuv: np.ndarray, cvv: np.ndarray, squared: bool
) -> tuple[np.ndarray, np.ndarray]:
    """∫ G r dy (per m², or ∫ G r² per m⁴) for Gaussians in pixel units (see :func:`tracker.integrate.terraces.pixel_gaussians`).

    Returns (values, look-ups per integral); look-ups 0 marks Gaussians left to the caller
    (eccentricity beyond ~500:1), whose values are undefined.
    """
    pyr = pyramid(prior, squared)
    n = uc.shape[0]
    smin = np.empty(n)
    keys = np.empty(n, dtype=np.int64)
    h, w = prior.grid.shape
    _order_keys(uc, vc, cuu, cuv, cvv, h, w, ORDER_TILE, smin, keys)
    p = pyr.levels(float(smin.max(initial=0.0)))
    out = np.empty(n)
    counts = np.empty(n, dtype=np.int64)
    slots, offset = pyr.slots(p)
    args = (pyr.field, whole_frame(pyr.field), ALL_FRAME_0, PHI_TABLE, p.coef, slots, p.scale, p.step, p.u0, p.v0, p.nu, p.nv, offset)
    _kernel(*args, uc, vc, cuu, cuv, cvv, np.argsort(keys), out, counts, nb.get_num_threads())
    return out, counts


SMALL_BATCH = 256
"""Batches of fewer Gaussians than this go to :func:`integrate_small` first: one serial compiled call
from metres to integrals, without the pyramid's sort or a parallel launch (the tracker's refreshes: ~4,000
calls of ~7 Gaussians on the 1 M-report stream, ~70 µs each through the general path)."""


def integrate_small(
    prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, squared: bool, max_rho: float, max_spread: float
) -> np.ndarray | None:
    """:func:`tracker.integrate.integrate_checked`'s values for a small batch of checked Gaussians (metres)
    whose every member takes the pyramid (not tiny, within ``max_rho`` σ of the grid and at most
    ``max_spread`` times its area, :data:`~tracker.integrate.NEAR_RHO`, :data:`~tracker.integrate.NEAR_SPREAD`,
    a finite value with look-ups) with the levels already built; ``None`` otherwise, and the caller takes
    the general path. One compiled pass (:func:`_prepare`) does the pixel arithmetic of
    :func:`~tracker.integrate.terraces.pixel_gaussians` and the tests of
    :func:`~tracker.integrate.tiny.is_tiny` and :func:`~tracker.integrate.terraces.near_grid` (without
    fast-math, as they are compiled), then the general path's own :func:`_kernel` integrates the batch in
    its given order (no sort keys, no argsort, none of the numpy steps around them). The same compiled
    kernel on the same inputs, so the same numbers bit for bit: a second compiled copy of :func:`_one`
    (a serial loop calling it) can round differently in the last bit, since LLVM optimises the inlined
    fast-math code per caller (seen: 1 ulp on one Gaussian of the test, in one compilation of two)."""
    n = means.shape[0]
    top, px = small_batch_pixels(prior, means, covs, max_rho, max_spread)
    pyr = pyramid(prior, squared)
    p = pyr.packed
    # the level of each Gaussian in the snapshot: its smaller σ below the top level's scale, with a margin
    # for this σ's rounding against _order_keys's (the general path builds up to the first level >= it)
    if not (top >= 0.0 and p.scale.size and top * (1.0 + 1e-6) < p.scale[-1]):
        return None
    out = np.empty(n)
    counts = np.empty(n, dtype=np.int64)
    slots, offset = pyr.slots(p)
    args = (pyr.field, whole_frame(pyr.field), ALL_FRAME_0, PHI_TABLE, p.coef, slots, p.scale, p.step, p.u0, p.v0, p.nu, p.nv, offset)
    _kernel(*args, px[0], px[1], px[2], px[3], px[4], np.arange(n), out, counts, nb.get_num_threads())
    if counts.min() <= 0 or not np.isfinite(out).all():
        return None
    return out


def small_batch_pixels(prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, max_rho: float, max_spread: float
                       ) -> tuple[float, np.ndarray]:
    """(largest smaller σ in cells, or -1 when a Gaussian is tiny or not near the grid; (5, N) pixel
    Gaussians uc, vc, cuu, cuv, cvv) of a small batch in metres on ``prior``'s grid (:func:`_prepare`),
    for :func:`integrate_small` and the lazy pyramid's own."""
    g = prior.grid
    px = np.empty((5, means.shape[0]))
    top = _prepare(means, covs, g.transform.c, g.transform.f, g.dx, g.dy, float(g.width), float(g.height), max_rho, max_spread, px)
    return top, px


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _prepare(means, covs, c, f, dx, dy, w, h, max_rho, max_spread, px):
    """Pixel Gaussians (rows uc, vc, cuu, cuv, cvv of ``px``) as :func:`~tracker.integrate.terraces.pixel_gaussians`
    computes them, and the largest smaller σ (cells); -1 as soon as one is tiny or not near the grid
    (:func:`~tracker.integrate.tiny.is_tiny`, :func:`~tracker.integrate.terraces.near_grid`: the same tests)."""
    top = 0.0
    for n in range(means.shape[0]):
        uc = (means[n, 0] - c) / dx
        vc = (f - means[n, 1]) / dy
        cuu = covs[n, 0, 0] / (dx * dx)
        cvv = covs[n, 1, 1] / (dy * dy)
        cuv = -0.5 * (covs[n, 0, 1] + covs[n, 1, 0]) / (dx * dy)
        if cuu + cvv <= TINY * TINY:
            return -1.0
        lo2 = grid_radii(uc, vc, cuu, cuv, cvv, w, h)[0]
        spread = 2.0 * np.pi * root_det(cuu, cuv, cvv)[0]
        if not (lo2 <= max_rho * max_rho and spread <= max_spread * w * h):
            return -1.0
        m = 0.5 * (cuu + cvv)
        dd = 0.5 * (cuu - cvv)
        top = max(top, np.sqrt(max(m - np.sqrt(dd * dd + cuv * cuv), 0.0)))
        px[0, n] = uc
        px[1, n] = vc
        px[2, n] = cuu
        px[3, n] = cuv
        px[4, n] = cvv
    return top


NO_CELLS = np.zeros((1, 4), np.int64)
"""The frames of a kernel call given no cells: Gaussians finer than the pyramid return (NaN, -1)."""
ALL_FRAME_0 = np.zeros(0, np.int64)
"""The kernel's ``which`` when every Gaussian reads its cells through the first frame."""


def whole_frame(values: np.ndarray) -> np.ndarray:
    """The kernel's frames (one :func:`_window` frame) of a field that holds the whole grid."""
    return np.array([[0, 0, values.shape[0], values.shape[1]]], np.int64)


def stacked_frames(bounds: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Room for windows of cells of an (H, W) grid, window i the cells [r0, r1) x [c0, c1) of
    ``bounds[i]``, stacked in the rows of one float64 array as wide as the widest (left unset beside
    the narrower ones: a frame's Gaussians read only its window), with a :func:`_window` frame each: (values, frames, views), ``views[i]`` the part
    of ``values`` that window i's cells go to. Frame i's first row is r0 less the row where window i
    starts in the stack, so ``values[j - r0, i - c0]`` is window i's cell (j, i): one :func:`_kernel`
    call serves them all."""
    heights = bounds[:, 1] - bounds[:, 0]
    widths = bounds[:, 3] - bounds[:, 2]
    starts = np.cumsum(heights) - heights
    # np.empty: zeroing would touch every page of the stack once more (~2 s/GB of fresh memory on a VM)
    values = np.empty((max(int(heights.sum()), 1), max(int(widths.max(initial=0)), 1)))
    frames = np.empty((bounds.shape[0], 4), np.int64)
    frames[:, 0] = bounds[:, 0] - starts
    frames[:, 1] = bounds[:, 2]
    frames[:, 2:] = shape
    views = [values[a : a + hh, :ww] for a, hh, ww in zip(starts.tolist(), heights.tolist(), widths.tolist(), strict=True)]
    return values, frames, views


ORDER_TILE = 32
"""Lattice nodes per block side in the kernel's order. The kernel waits on memory when a level is larger
than the cache; taking the batch by pyramid level, then by block of its centre, makes consecutive
look-ups fall on nearby lattice nodes (2.3x fewer CPU-seconds than a random order on a 2,000 x
2,000 grid; 15 % fewer than block first, then spread)."""
