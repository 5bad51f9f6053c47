"""The greedy association-estimation tracker of paper 1 (Fig. 3) with a terrain prior, in log space.

For each report (z, V, t), in arrival order, with N̂_D hypotheses p̂_q(y) = c_q⁻¹ G(a_q, A_q, y) r(y)
after k reports:

    bestPrevious     = S(N̂_D, k+1) · max_q G(z; a_q, A_q+V) · ∫G(b_q, B_q, y) r(y) dy / c_q
    previouslyUnseen = S(N̂_D+1, k+1) · ∫G(z, V, y) r(y) dy

(B_q = (A_q⁻¹+V⁻¹)⁻¹, b_q = B_q(A_q⁻¹a_q + V⁻¹z)); a new hypothesis when previouslyUnseen >
bestPrevious, else the report is fused into the best q (Gaussian product, c_q ← ∫G(b_q,B_q)r).
Ties fuse, and equal bestPrevious candidates go to the lowest hypothesis index.

Variants (paper 1, section 6): ``"TT"`` uses the terrain prior r in association and estimate;
``"UU"`` uses the uniform density u = 1 / (grid area) taken over all space, so every integral is
analytic (∫G u = u) and bestPrevious reduces to G(z; a_q, A_q+V); ``"UT"`` associates exactly as UU
and applies r to its reported estimate only (the saved estimate stays Gaussian).

Gate and its proof. Only hypotheses with Mahalanobis d² = (z-a_q)ᵀ(A_q+V)⁻¹(z-a_q) <= γ are scored.
A hypothesis outside the gate has

    G(z; a_q, A_q+V) < e^{-γ/2} / (2π √det(A_q+V)) <= e^{-γ/2} / (2π √det V)      (A_q+V ⪰ V)
    ∫G(b_q,B_q) r / c_q <= r_max / c_q                  (∫G r <= max r)

(UU/UT: the ratio is exactly 1). So whenever

    -γ/2 - ln(2π √det V) + ln(r_max / c_floor) <= max(best gated score, previouslyUnseen score)

with c_floor a lower bound on c_q over all but the LOW_C hypotheses of least c, and the same bound
with each of those LOW_C's own c_q and exact d² holds too, no hypothesis outside the gate can be
chosen nor beat previouslyUnseen: the gated decision equals the ungated one. (One bad normaliser
would otherwise loosen the bound for every report.) This is checked for every report; when it fails, that report is re-gated by brute
force with the γ that makes the inequality hold, so decisions never depend on γ (γ only trades
speed). r_max carries a factor 2 of slack for the terrace rule's error. TT with constant velocity is
the exception: the predicted normaliser c'_q has no lower bound, so there the gate is the plain χ²
gate at γ (the gate probability) and no widening is attempted. UU/UT with motion keep the proof.

Streaming with sequential semantics, fast (kernels in :mod:`tracker.association.walk`). Reports are taken in
blocks: a block is gated against the hypotheses at its start (one ``gate`` call) and every gated pair
is scored in one ``integrate`` call. A numba walk then takes the reports in order. A report none of
whose scored candidates changed, and whose gate received no hypothesis created or moved by an earlier
report of the block, sees exactly the block-start state, so its precomputed scores are the sequential
ones. Otherwise its stale candidates are rescored from the current state: inside numba for UU/UT and
for TT candidates that the bound ln G - ln c + ln r_max puts below previouslyUnseen (they need no
integral), else by a refresh that rescores the pairs of all remaining reports against the hypotheses
changed since the last refresh (one more ``integrate`` call). With S = e^{-nτ} the same bound skips
the integral of every pair that cannot reach previouslyUnseen.

Static hypotheses with the default gater live in a grid of cells kept across blocks
(:func:`walk.grid_gate`), so a block's gate costs one query per report rather than a gating
structure rebuilt over every hypothesis. UU and UT need no integrals, so their static blocks skip
the scoring ahead altogether: :func:`walk.walk_sequential` takes the reports one by one against the
current hypotheses, gating each with the grid (updated after every decision), which is the
sequential algorithm itself. A ``gater`` given by the caller, and constant velocity, keep the
per-block ``gate`` call.
"""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numba
import numpy as np

from pipeline.prior import TerrainPrior
from tracker.association.walk import (
    CONFLICT,
    DONE,
    WIDEN,
    build_report_grid,
    decide,
    fresh_pairs,
    grid_gate,
    grid_place,
    half_log_det,
    least_k,
    link_pairs,
    needed_pairs,
    no_grid,
    pair_geometry,
    pair_geometry_parallel,
    pair_scores,
    walk,
    walk_sequential,
    widened_gate,
)
from tracker.integrate import Integrator, integrate_checked
from tracker.models.motion import ConstantVelocity, MotionModel, Static
from tracker.models.sfunc import ExpS, PoissonS, SModel
from tracker.types.estimate import Estimate
from tracker.types.hypotheses import Hypotheses
from tracker.types.reports import Reports

if TYPE_CHECKING:  # gating loads on first use (_default_gater)
    from tracker.gating import Gater

VARIANTS = ("UU", "UT", "TT")
GATE_PROB = 1.0 - 1e-9
"""Default gate probability; γ = χ²₂ quantile = -2 ln(1 - GATE_PROB) ≈ 41.4."""
DEFAULT_GAMMA = -2.0 * math.log(1.0 - GATE_PROB)
BLOCK = 2048
"""Reports per block: larger blocks amortise gating, smaller ones conflict less."""
MASS_FLOOR = 1e-10
"""Prior mass near a report (∫G(z,V) r · 2π√det V) below which it is off the prior (rounding floor)."""
LOW_C = 256
"""Hypotheses of least normaliser that the gate bound checks one by one (the rest share a floor)."""
MAX_GRID_CELLS = 1 << 22
"""Cells of the static hypotheses' grid at most (its cell grows on larger priors)."""
TIMINGS = ("gate", "geometry", "integrals", "walk", "refresh", "growth", "setup", "total")
"""Keys of ``Tracker.timings_``: seconds in each step of the block loop (see :meth:`Tracker._block`)."""
_RMAX_SLACK = math.log(2.0)
_LOG_2PI = math.log(2.0 * math.pi)



@dataclass
class AssociationResult:
    """``assignments`` (K,) hypothesis index per report (-1: skipped off the prior),
    ``hypotheses`` the saved estimate, ``n_detected`` N̂_D, ``estimate`` the reported one,
    ``stats`` counters (blocks, scored pairs, refreshes, widened gates, skipped reports, integrals)."""

    assignments: np.ndarray
    hypotheses: Hypotheses
    n_detected: int
    estimate: Estimate
    stats: dict = field(default_factory=dict)


def _default_gater() -> Gater:
    from tracker.gating.gate import gate_unchecked

    return gate_unchecked


_RMAX_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _log_rmax(prior: TerrainPrior) -> float:
    """ln max r (per m²) plus the terrace slack, once per prior object (experiments build many trackers)."""
    if prior not in _RMAX_CACHE:
        _RMAX_CACHE[prior] = math.log(prior.max_density) + _RMAX_SLACK
    return _RMAX_CACHE[prior]


def _log(x: np.ndarray) -> np.ndarray:
    """ln of integrals; summed-area rounding can leave -1e-20 where the prior is zero: that is -inf."""
    with np.errstate(divide="ignore"):
        return np.log(np.maximum(x, 0.0))


# ----------------------------------------------------------------------------- the tracker


# Below this many rows a parallel kernel's launch costs more than it saves. Measured on the 1 M / 100 k
# bench stream on a quiet 2-core machine: TT 7.9 s at 1,024 and 256 against 9.5 s at 4,096 (identical
# decisions); on a loaded machine a launch waits for a core and 4,096 was faster.
SERIAL_BELOW = 1024


def one_thread_when_small(fn: Callable, size_arg: int) -> Callable:
    """Run ``fn`` on one numba thread when its argument ``size_arg`` has fewer than
    :data:`SERIAL_BELOW` rows."""

    def run(*args, **kwargs):
        if args[size_arg].shape[0] >= SERIAL_BELOW:
            return fn(*args, **kwargs)
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            return fn(*args, **kwargs)
        finally:
            numba.set_num_threads(threads)

    return run


class _HypothesisGrid:
    """The static hypotheses in a grid of square cells kept across blocks (:func:`walk.grid_place`,
    :func:`walk.grid_gate`): a block's gate is one query per report. The cell is set at the first block,
    √(2γ λ) with λ the median largest eigenvalue of its report covariances (m), over the prior's bounds
    (hypotheses outside go to border cells); hypotheses with an eigenvalue above WIDE · λ go to the
    wide list that every query scans."""

    WIDE = 4.0

    def __init__(self, bounds: tuple[float, float, float, float], gamma: float) -> None:
        self.bounds = bounds
        self.gamma = gamma
        self.arrays: tuple | None = None

    def _start(self, V: np.ndarray, capacity: int) -> None:
        xmin, ymin, xmax, ymax = self.bounds
        lam_v = float(np.median(np.linalg.eigvalsh(V)[:, -1]))
        cell = max(math.sqrt(2.0 * self.gamma * lam_v), math.sqrt((xmax - xmin) * (ymax - ymin) / MAX_GRID_CELLS), 1e-3)
        nx, ny = math.ceil((xmax - xmin) / cell) or 1, math.ceil((ymax - ymin) / cell) or 1
        geo = np.array([xmin, ymin, cell, float(nx), float(ny), 0.0, self.WIDE * cell * cell / (2.0 * self.gamma)])
        self.arrays = (geo, np.full(nx * ny + 1, -1, np.int64), *(np.full(capacity, -1, np.int64) for _ in range(3)),
                       np.zeros(nx * ny + 1))

    def reserve(self, V: np.ndarray, capacity: int) -> None:
        """Room for ``capacity`` hypotheses (the first call sizes the cells from the block's covariances)."""
        if self.arrays is None:
            self._start(V, capacity)
        old = self.arrays[2].shape[0]
        if capacity > old:
            grown = tuple(np.concatenate([a, np.full(capacity - old, -1, np.int64)]) for a in self.arrays[2:5])
            self.arrays = self.arrays[:2] + grown + self.arrays[5:]


class _PairPool:
    """Scored (hypothesis, report) pairs of a block as a growable pool of per-report linked lists."""

    def __init__(self, m: int, state_dim: int, capacity: int) -> None:
        self.arrays = (
            np.zeros(capacity, np.int64),
            np.zeros(capacity),
            np.zeros((capacity, state_dim)),
            np.zeros((capacity, state_dim, state_dim)),
            np.zeros(capacity),
            np.zeros(capacity, np.int64),
            np.full(m, -1, np.int64),
        )

    def add(self, rep, h, scored, hyp, istate, blk, j) -> None:
        """Link new pairs (growing the pool when needed) and start a new refresh period at report j."""
        need = int(istate[3]) + h.size
        cap = self.arrays[0].shape[0]
        if need > cap:
            new_cap = max(need, 2 * cap)
            self.arrays = tuple(
                np.concatenate([a, np.zeros((new_cap - cap,) + a.shape[1:], a.dtype)]) for a in self.arrays[:6]
            ) + (self.arrays[6],)
        link_pairs(j, self.arrays, istate, rep, h, *scored, hyp, blk[5])


def _s_model(tau: float | None, s_model: SModel | None) -> SModel:
    if (tau is None) == (s_model is None):
        raise ValueError("give exactly one of tau= (S = exp(-n tau)) or s_model= (ExpS or PoissonS)")
    if s_model is None:
        return ExpS(float(tau))
    if not isinstance(s_model, ExpS | PoissonS):
        raise ValueError(f"s_model must be ExpS or PoissonS, got {s_model!r}")
    return s_model


class Tracker:
    """Streaming association-estimation (paper 1, Fig. 3) against a :class:`TerrainPrior`.

    ``variant`` "TT", "UT" or "UU"; the S factor as ``tau`` (S = e^{-nτ}) or ``s_model``
    (:class:`~tracker.models.sfunc.ExpS`, :class:`~tracker.models.sfunc.PoissonS`); ``motion``
    :class:`~tracker.models.motion.Static` or :class:`~tracker.models.motion.ConstantVelocity`; ``gamma``
    the gate on d² (decisions do not depend on it, see the module doc); ``off_prior`` what to do
    with a report whose ∫G(z,V) r is 0 (off the grid or on structural zeros) in TT/UT: "raise"
    (default; nothing is changed) or "skip" (assignment -1, not counted in k). ``gater`` (a :class:`~tracker.gating.Gater`) defaults to
    :func:`tracker.gating.gate.gate_unchecked` (the reports and hypotheses are checked already); ``integrator`` (an :class:`~tracker.integrate.Integrator`, given
    only Gaussians built from checked reports) to :func:`tracker.integrate.integrate_checked`.

    Fitted state: ``hypotheses_``, ``n_detected_``, ``n_reports_`` (k), ``stats_``, ``timings_`` (seconds
    per step of the block loop, keys :data:`TIMINGS`; "total" minus the others is Python overhead).
    """

    def __init__(
        self,
        prior: TerrainPrior,
        variant: str = "TT",
        tau: float | None = None,
        s_model: SModel | None = None,
        motion: MotionModel | None = None,
        gamma: float = DEFAULT_GAMMA,
        block: int = BLOCK,
        off_prior: str = "raise",
        gater: Gater | None = None,
        integrator: Integrator | None = None,
    ) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        if not (math.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma must be positive and finite, got {gamma}")
        if off_prior not in ("raise", "skip"):
            raise ValueError(f"off_prior must be 'raise' or 'skip', got {off_prior!r}")
        if int(block) < 1:
            raise ValueError(f"block must be >= 1, got {block}")
        self.prior = prior
        self.variant = variant
        self.s_model = _s_model(tau, s_model)
        self.motion = motion or Static()
        if self.motion.pos_dim != 2:
            raise ValueError("the tracker works on 2-D positions (pos_dim = 2)")
        self.gamma = float(gamma)
        self.block = int(block)
        self.off_prior = off_prior
        self.gater = one_thread_when_small(gater or _default_gater(), 2)  # sized by the reports
        # Static hypotheses with the default gater: a grid kept across blocks (walk.grid_gate) gates them.
        static = not isinstance(self.motion, ConstantVelocity)
        self._grid = _HypothesisGrid(prior.grid.bounds, self.gamma) if gater is None and static else None
        self._grid_gate = one_thread_when_small(grid_gate, 0)
        # UU/UT need no integrals, so their static blocks run as the plain sequential loop in numba.
        self._sequential = self._grid is not None and not self.terrain_association
        self.integrator = one_thread_when_small(integrator or integrate_checked, 1)
        xmin, ymin, xmax, ymax = prior.grid.bounds
        self.log_u = -math.log((xmax - xmin) * (ymax - ymin))
        self.log_rmax = _log_rmax(prior)
        self.hypotheses_ = Hypotheses(self.motion.state_dim)
        self.n_reports_ = 0
        self._last_time = -np.inf
        self.stats_ = {"blocks": 0, "pairs": 0, "conflicts": 0, "widened": 0, "skipped": 0, "integrals": 0}
        self.timings_ = dict.fromkeys(TIMINGS, 0.0)

    @property
    def terrain_association(self) -> bool:
        return self.variant == "TT"

    @property
    def n_detected_(self) -> int:
        return self.hypotheses_.n

    # -- input checks: everything is validated before any state changes. The Gaussians and times
    # were checked once, when the Reports batch was built; here only what the tracker adds.

    def _check(self, reports: Reports) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z, V, t = reports.means, reports.covs, reports.times
        if z.shape[1] != 2:
            raise ValueError(f"reports: positions must be 2-D (x, y) metres, got dimension {z.shape[1]}")
        if isinstance(self.motion, ConstantVelocity) and t.size:
            back = np.flatnonzero(np.diff(np.concatenate([[self._last_time], t])) < 0)
            if back.size:
                raise ValueError(
                    f"reports: times go backwards at indices {back[:10].tolist()} (the motion model "
                    f"only predicts forwards; last time seen {self._last_time} s)"
                )
        return z, V, t

    def _log_unseen(self, z: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ln ∫G(z,V) r for association (ln u for UU/UT) and a mask of reports on the prior."""
        if self.variant == "UU":
            return np.full(z.shape[0], self.log_u), np.ones(z.shape[0], bool)
        log_iz = _log(self.integrator(self.prior, z, V))
        self.stats_["integrals"] += z.shape[0]
        # ∫G r · 2π√det V is the prior mass near the report, G-weighted; the summed-area tables leave
        # ~1e-13 of rounding where the true value is 0, so below MASS_FLOOR it counts as no mass. The area
        # is at least one cell's: a Gaussian under a cell is integrated exactly (its value is the cell's r).
        log_area = np.maximum(2.0 * half_log_det(V), 2.0 * math.log(self.prior.grid.cell_area))
        on = log_iz + _LOG_2PI + 0.5 * log_area > math.log(MASS_FLOOR)
        return (log_iz if self.terrain_association else np.full(z.shape[0], self.log_u)), on

    def update(self, reports: Reports) -> np.ndarray:
        """Process reports in order (one or many); returns the hypothesis index of each (-1 skipped).

        Raises ``ValueError`` naming the offending indices for NaN, non-PD covariances, backwards
        times (constant velocity) or reports off the prior (``off_prior="raise"``); the tracker is
        unchanged when it raises.
        """
        t_start = time.perf_counter()
        z, V, t = self._check(reports)
        if not z.shape[0]:
            return np.zeros(0, dtype=np.int64)
        t0 = time.perf_counter()
        log_unseen, on = self._log_unseen(z, V)
        self.timings_["integrals"] += time.perf_counter() - t0
        if not on.all():
            off = np.flatnonzero(~on)
            if self.off_prior == "raise":
                raise ValueError(
                    f"reports at indices {off[:10].tolist()} have zero prior mass under their Gaussian "
                    "(off the prior's grid or on structural zeros); use off_prior='skip' to drop them"
                )
            self.stats_["skipped"] += off.size
        assign = np.full(z.shape[0], -1, dtype=np.int64)
        keep = np.flatnonzero(on)
        step = max(keep.size, 1) if self._sequential else self.block  # the sequential loop needs no blocks
        for s in range(0, keep.size, step):
            idx = keep[s : s + step]
            assign[idx] = self._block(z[idx], V[idx], t[idx], log_unseen[idx])
        if t.size:
            self._last_time = max(self._last_time, float(t[keep].max()) if keep.size else self._last_time)
        self.timings_["total"] += time.perf_counter() - t_start
        return assign

    # -- one block

    def _score(self, rep: np.ndarray, h: np.ndarray, blk, hyp, cfg):
        """Scores ln[G(z; a, A+V) ∫G(b,B)r / c] (ln G for UU/UT) of pairs (block report rep, hypothesis h)
        from the current hypotheses, with the posterior state, covariance and ln c of each pair."""
        t0 = time.perf_counter()
        geometry = pair_geometry_parallel if h.size >= SERIAL_BELOW else pair_geometry
        log_g, post_m, post_c, pred_m, pred_c = geometry(rep, h, blk, hyp, cfg)
        self.timings_["geometry"] += time.perf_counter() - t0
        if not self.terrain_association:
            return log_g, post_m, post_c, np.full(h.size, self.log_u)
        if not h.size:
            return log_g, post_m, post_c, np.zeros(0)
        t0 = time.perf_counter()
        if isinstance(self.s_model, ExpS) and not isinstance(self.motion, ConstantVelocity):
            # static, S = e^{-nτ}: the bound, the gathers and the scores in two compiled passes
            log_c, need, k, means, covs = needed_pairs(
                log_g, self.hypotheses_._log_c, h, rep, blk[3], self.log_rmax, self.s_model.tau, post_m, post_c
            )
            self.stats_["integrals"] += k
            log_needed = _log(self.integrator(self.prior, means, covs)) if k else np.zeros(0)
            score, log_i = pair_scores(log_g, log_c, need, log_needed)
            self.timings_["integrals"] += time.perf_counter() - t0
            return score, post_m, post_c, log_i
        if isinstance(self.motion, ConstantVelocity):
            log_c = _log(self.integrator(self.prior, pred_m, pred_c))
            need = np.ones(h.size, bool)
        else:
            log_c = self.hypotheses_.log_c[h]
            need = self._needs_integral(log_g - log_c, blk[3][rep])
        self.stats_["integrals"] += int(need.sum()) + (h.size if isinstance(self.motion, ConstantVelocity) else 0)
        log_i = np.zeros(h.size)
        if need.any():  # a refresh often needs none: skip the integrator's per-call cost
            log_i[need] = _log(self.integrator(self.prior, post_m[need, :2], np.ascontiguousarray(post_c[need, :2, :2])))
        score = np.full(h.size, -np.inf)
        ok = need & np.isfinite(log_i)
        score[ok] = log_g[ok] + log_i[ok] - log_c[ok]
        self.timings_["integrals"] += time.perf_counter() - t0
        return score, post_m, post_c, log_i

    def _needs_integral(self, log_g_over_c: np.ndarray, log_unseen: np.ndarray) -> np.ndarray:
        """Pairs whose bound ln G - ln c + ln r_max reaches previouslyUnseen. With S = e^{-nτ} the
        unseen score ln ∫G(z,V)r - τ does not depend on the state, so a pair below it can neither be
        chosen nor beat previouslyUnseen and its score is left at -inf (no integral)."""
        if not isinstance(self.s_model, ExpS):
            return np.ones(log_g_over_c.size, bool)
        return log_g_over_c + self.log_rmax >= log_unseen - self.s_model.tau

    def _gate(self, z: np.ndarray, V: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gated (hypothesis, report) pairs of the block against the current hypotheses, CSR by report."""
        H = self.hypotheses_
        if H.n == 0:
            return np.zeros(z.shape[0] + 1, np.int64), np.zeros(0, np.int64)
        if self._grid is not None:
            return self._grid_gate(z, V, self.gamma, H._means, H._covs, self._grid.arrays)
        if isinstance(self.motion, ConstantVelocity):
            h, r = self.gater(H.means, H.covs, z, V, threshold=self.gamma, report_times=t,
                              track_times=H.times, process_noise=self.motion.q)
        else:
            h, r = self.gater(H.means, H.covs, z, V, threshold=self.gamma)
        order = np.lexsort((h, r))
        ptr = np.zeros(z.shape[0] + 1, np.int64)
        np.cumsum(np.bincount(r, minlength=z.shape[0]), out=ptr[1:])
        return ptr, np.asarray(h, np.int64)[order]

    def _brute(self, h_all: np.ndarray, z: np.ndarray, V: np.ndarray, t: float, gamma: float) -> np.ndarray:
        """Hypotheses among ``h_all`` whose current Gaussian gates report (z, V) at d² <= gamma."""
        H = self.hypotheses_
        a, A = H.means[h_all], H.covs[h_all]
        if isinstance(self.motion, ConstantVelocity):
            a, A = self.motion.predict(a, A, t - H.times[h_all])
        r = z[None, :] - a[:, :2]
        S = A[:, :2, :2] + V[None]
        d2 = np.einsum("ni,nij,nj->n", r, np.linalg.inv(S), r)
        return h_all[d2 <= gamma]

    def _block(self, z, V, t, log_unseen) -> np.ndarray:
        """Reports of one block in order (see :mod:`tracker.association.walk`): gate and score against the
        block-start state, walk, and on a conflict refresh the pairs of the remaining reports with the
        hypotheses changed since the last refresh (one scoring call per refresh). Each step's seconds
        go to ``timings_``."""
        clock = time.perf_counter
        tm = self.timings_
        t_start = clock()
        H = self.hypotheses_
        m = z.shape[0]
        H.reserve(m)
        if self._grid is not None:
            self._grid.reserve(V, H.capacity)
        t0 = clock()
        tm["growth"] += t0 - t_start
        if self._sequential:
            return self._block_sequential(z, V, t, log_unseen)
        ptr, p_h = self._gate(z, V, t)
        t1 = clock()
        tm["gate"] += t1 - t0
        p_rep = np.repeat(np.arange(m), np.diff(ptr))
        pool = _PairPool(m, H.state_dim, max(2 * p_h.size, 64))
        dirty = np.zeros(H.capacity, dtype=np.bool_)
        low, is_low, floor = self._low_c(m)
        hyp = (H._means, H._covs, H._log_c, H._counts, H._times, dirty, np.zeros(m, dtype=np.int64), low, is_low)
        assign = np.full(m, -1, dtype=np.int64)
        blk = (z, V, t, log_unseen, half_log_det(V), np.zeros(m, dtype=np.bool_), assign,
               *build_report_grid(z, V, self.gamma), np.zeros(m, dtype=np.int64))
        istate = np.array([H.n, 0, self.n_reports_, 0, min(H.n, LOW_C)], dtype=np.int64)
        fstate = np.array([floor, 0.0, self._low_min(low, istate[4])])
        cfg = self._cfg()
        hgrid = no_grid() if self._grid is None else self._grid.arrays
        widened = np.zeros(1, np.int64)  # the gates walk() widens itself
        tm["setup"] += clock() - t1
        pool.add(p_rep, p_h, self._score(p_rep, p_h, blk, hyp, cfg), hyp, istate, blk, 0)
        self.stats_["blocks"] += 1
        j = 0
        while j < m:
            t0 = clock()
            j, status = walk(j, blk, pool.arrays, hyp, istate, fstate, cfg, hgrid, widened)
            t1 = clock()
            tm["walk"] += t1 - t0
            scoring = tm["geometry"] + tm["integrals"]  # counted there, not as refresh
            H.n = int(istate[0])
            if status == CONFLICT:
                self.stats_["conflicts"] += 1
                f_rep, f_h = fresh_pairs(j, blk, hyp, istate, cfg)
                pool.add(f_rep, f_h, self._score(f_rep, f_h, blk, hyp, cfg), hyp, istate, blk, j)
            elif status == WIDEN:
                self.stats_["widened"] += 1
                if self._grid is not None:
                    cand = widened_gate(j, float(fstate[1]), z, V, t, H._means, H._covs, H._times, H.n, assign, hgrid)
                else:
                    cand = self._brute(np.arange(H.n), z[j], V[j], t[j], float(fstate[1]))
                c = self._score(np.full(cand.size, j), cand, blk, hyp, cfg)
                status = decide(j, np.arange(cand.size), cand.size, cand, *c, False, blk, hyp, istate, fstate, cfg)
                if status != DONE:
                    raise RuntimeError(f"report {j}: decision failed after widening the gate")
                H.n = int(istate[0])
                j += 1
            tm["refresh"] += clock() - t1 - (tm["geometry"] + tm["integrals"] - scoring)
        t0 = clock()
        if self._grid is not None:
            grid_place(assign, H._means, H._covs, self._grid.arrays)
        tm["walk"] += clock() - t0
        self.stats_["widened"] += int(widened[0])
        self.stats_["pairs"] += int(istate[3])
        self.n_reports_ = int(istate[2])
        return assign

    def _block_sequential(self, z, V, t, log_unseen) -> np.ndarray:
        """UU/UT with static hypotheses: the whole block in :func:`walk.walk_sequential` (no scoring ahead)."""
        t0 = time.perf_counter()
        H = self.hypotheses_
        m = z.shape[0]
        low, is_low, floor = self._low_c(m)
        hyp = (H._means, H._covs, H._log_c, H._counts, H._times, np.zeros(H.capacity, dtype=np.bool_),
               np.zeros(m, dtype=np.int64), low, is_low)
        assign = np.full(m, -1, dtype=np.int64)
        none = np.zeros(0, np.int64)  # the block's report grid: not used here
        blk = (z, V, t, log_unseen, half_log_det(V), np.zeros(m, dtype=np.bool_), assign,
               none, none, np.zeros(6), none)
        istate = np.array([H.n, 0, self.n_reports_, 0, min(H.n, LOW_C)], dtype=np.int64)
        fstate = np.array([floor, 0.0, self._low_min(low, istate[4])])
        t1 = time.perf_counter()
        self.timings_["setup"] += t1 - t0
        self.stats_["widened"] += walk_sequential(blk, hyp, istate, fstate, self._cfg(), self._grid.arrays)
        self.timings_["walk"] += time.perf_counter() - t1
        H.n = int(istate[0])
        self.stats_["blocks"] += 1
        self.n_reports_ = int(istate[2])
        return assign

    def _low_min(self, low: np.ndarray, n_low: int) -> float:
        """Least ln c over the low list (inf when empty)."""
        return float(self.hypotheses_._log_c[low[:n_low]].min()) if n_low else math.inf

    def _low_c(self, m: int) -> tuple[np.ndarray, np.ndarray, float]:
        """The LOW_C hypotheses of least ln c (checked one by one by the gate bound), a flag per
        hypothesis, and the floor of ln c over the others."""
        H = self.hypotheses_
        low = np.zeros(LOW_C + m, dtype=np.int64)
        is_low = np.zeros(H.capacity, dtype=np.bool_)
        if H.n <= LOW_C:
            low[: H.n] = np.arange(H.n)
            is_low[: H.n] = True
            return low, is_low, np.inf
        least, floor = least_k(H.log_c, LOW_C)
        low[: least.size] = least
        is_low[least] = True
        return low, is_low, floor

    def _cfg(self) -> tuple:
        s_kind, s_param = self.s_model.code
        m_kind, q, vel_std = self.motion.code
        return (self.gamma, self.terrain_association, self.log_rmax, s_kind, s_param, m_kind, q, vel_std)

    # -- outputs

    def estimate(self) -> Estimate:
        """The reported estimate: TT its saved densities; UT the saved Gaussians times r, renormalised;
        UU the Gaussians alone."""
        H = self.hypotheses_
        pos_m, pos_c = H.position()
        labels = np.full(H.n, -1, dtype=np.int64)
        if self.variant == "UU":
            return Estimate(pos_m.copy(), pos_c.copy(), np.full(H.n, self.log_u), H.counts.copy(), False, labels)
        if self.variant == "UT":
            log_c = _log(self.integrator(self.prior, pos_m, pos_c)) if H.n else np.zeros(0)
        else:
            log_c = H.log_c.copy()
        return Estimate(pos_m.copy(), pos_c.copy(), log_c, H.counts.copy(), True, labels)

    def result(self, assignments: np.ndarray) -> AssociationResult:
        return AssociationResult(assignments, self.hypotheses_.copy(), self.n_detected_, self.estimate(), dict(self.stats_))


def associate(
    prior: TerrainPrior,
    reports: Reports,
    variant: str = "TT",
    tau: float | None = None,
    s_model: SModel | None = None,
    motion: MotionModel | None = None,
    **kwargs,
) -> AssociationResult:
    """Run the tracker over all reports in order (batch form of :class:`Tracker`)."""
    tracker = Tracker(prior, variant, tau=tau, s_model=s_model, motion=motion, **kwargs)
    return tracker.result(tracker.update(reports))


def perfect_estimate(
    prior: TerrainPrior, reports: Reports, terrain: bool = True, integrator: Integrator | None = None
) -> Estimate:
    """The "perfect association" estimate of paper 1, eq. 18: static reports grouped by ``reports.truth``,
    each group fused (information form, so order does not matter), then r applied (``terrain``) or not.
    Densities are ordered by ascending truth label (``labels``)."""
    truth = np.asarray(reports.truth)
    if truth.size and truth.min() < 0:
        raise ValueError(f"perfect_estimate: reports {np.flatnonzero(truth < 0)[:10].tolist()} have no truth label")
    z, V = reports.means, reports.covs
    labels, group = np.unique(truth, return_inverse=True)
    V_inv = np.linalg.inv(V)
    info = np.zeros((labels.size, z.shape[1], z.shape[1]))
    vec = np.zeros((labels.size, z.shape[1]))
    np.add.at(info, group, V_inv)
    np.add.at(vec, group, np.einsum("nij,nj->ni", V_inv, z))
    B = np.linalg.inv(info)
    B = 0.5 * (B + B.transpose(0, 2, 1))
    b = np.einsum("nij,nj->ni", B, vec)
    counts = np.bincount(group, minlength=labels.size)
    if terrain:
        log_c = _log((integrator or integrate_checked)(prior, b, B))
    else:
        xmin, ymin, xmax, ymax = prior.grid.bounds
        log_c = np.full(labels.size, -math.log((xmax - xmin) * (ymax - ymin)))
    return Estimate(b, B, log_c, counts, terrain, labels.astype(np.int64))
