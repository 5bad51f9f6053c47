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
    ∫G(b_q,B_q) r / c_q <= r_max / c_min                (∫G r <= max r; c_min the least c over q)

(UU/UT: the ratio is exactly 1). So whenever

    -γ/2 - ln(2π √det V) + ln(r_max / c_min) <= max(best gated score, previouslyUnseen score)

no hypothesis outside the gate can be chosen nor beat previouslyUnseen: the gated decision equals
the ungated one. This is checked for every report; when it fails, that report is re-gated by brute
force with the γ that makes the inequality hold, so decisions never depend on γ (γ only trades
speed). r_max carries a factor 2 of slack for the terrace rule's error. With constant velocity the
same bound is used with the normalisers at the hypotheses' last update (the predicted normaliser
c'_q is not bounded), so there it is a strong heuristic rather than a proof.

Streaming with sequential semantics, fast. Reports are processed in blocks: the block is gated
against the hypotheses at its start (one ``gate`` call) and every gated pair is scored in one
``integrate`` call. A numba walk then takes the reports in order; a report whose gated candidates
were all left untouched by earlier reports of the block, and whose gate holds no hypothesis they
created or moved, sees exactly the block-start state, so its precomputed scores are the sequential
ones. Other reports (conflicts) are rescored from the current state before they are decided.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np
from numba import njit

from pipeline.prior import TerrainPrior
from tracker.hypotheses import MOTION_CV, ConstantVelocity, Hypotheses, MotionModel, Static
from tracker.reports import Reports, check_gaussians, gaussian_product
from tracker.sfunc import ExpS, PoissonS, SModel, log_s_ratio_code

VARIANTS = ("UU", "UT", "TT")
GATE_PROB = 1.0 - 1e-9
"""Default gate probability; γ = χ²₂ quantile = -2 ln(1 - GATE_PROB) ≈ 41.4."""
DEFAULT_GAMMA = -2.0 * math.log(1.0 - GATE_PROB)
BLOCK = 2048
"""Reports per block: larger blocks amortise gating, smaller ones conflict less."""
_RMAX_SLACK = math.log(2.0)
_LOG_2PI = math.log(2.0 * math.pi)

_DONE, _CONFLICT, _WIDEN = 0, 1, 2

Integrator = Callable[..., np.ndarray]
Gater = Callable[..., tuple]


@dataclass(frozen=True)
class Estimate:
    """Reported position densities p̂_q(y) = exp(-log_c_q) G(y; means_q, covs_q) r(y) when ``terrain``,
    else the Gaussians G(y; means_q, covs_q) alone (UU). ``means`` (N, 2) m, ``covs`` (N, 2, 2) m²,
    ``log_c`` (N,) ln of per m², ``counts`` (N,) reports per hypothesis, ``labels`` (N,) the truth
    label of each density for perfect association (else -1)."""

    means: np.ndarray
    covs: np.ndarray
    log_c: np.ndarray
    counts: np.ndarray
    terrain: bool
    labels: np.ndarray


@dataclass
class AssociationResult:
    """``assignments`` (K,) hypothesis index per report (-1: skipped off the prior),
    ``hypotheses`` the saved estimate, ``n_detected`` N̂_D, ``estimate`` the reported one,
    ``stats`` counters (blocks, gated pairs, conflicts, widened gates)."""

    assignments: np.ndarray
    hypotheses: Hypotheses
    n_detected: int
    estimate: Estimate
    stats: dict = field(default_factory=dict)


def _default_integrator() -> Integrator:
    from tracker.terrace import integrate

    return integrate


def _default_gater() -> Gater:
    from tracker.gating import gate

    return gate


def _log(x: np.ndarray) -> np.ndarray:
    """ln of integrals; summed-area rounding can leave -1e-20 where the prior is zero: that is -inf."""
    with np.errstate(divide="ignore"):
        return np.log(np.maximum(x, 0.0))


# ----------------------------------------------------------------------------- numba kernels


@njit(cache=True, inline="always")
def _pos_at(Hm, Hc, Ht, h, t, motion, q):
    """Position mean and covariance (x, y, c00, c01, c11) of hypothesis h predicted to time t."""
    if motion != MOTION_CV:
        return Hm[h, 0], Hm[h, 1], Hc[h, 0, 0], Hc[h, 0, 1], Hc[h, 1, 1]
    dt = t - Ht[h]
    noise = q * abs(dt) ** 3 / 3.0
    x = Hm[h, 0] + dt * Hm[h, 2]
    y = Hm[h, 1] + dt * Hm[h, 3]
    c00 = Hc[h, 0, 0] + 2.0 * dt * Hc[h, 0, 2] + dt * dt * Hc[h, 2, 2] + noise
    c01 = Hc[h, 0, 1] + dt * (Hc[h, 0, 3] + Hc[h, 1, 2]) + dt * dt * Hc[h, 2, 3]
    c11 = Hc[h, 1, 1] + 2.0 * dt * Hc[h, 1, 3] + dt * dt * Hc[h, 3, 3] + noise
    return x, y, c00, c01, c11


@njit(cache=True, inline="always")
def _in_gate(Hm, Hc, Ht, h, z, V, t, motion, q, gamma):
    x, y, c00, c01, c11 = _pos_at(Hm, Hc, Ht, h, t, motion, q)
    s00 = c00 + V[0, 0]
    s01 = c01 + V[0, 1]
    s11 = c11 + V[1, 1]
    det = s00 * s11 - s01 * s01
    dx = z[0] - x
    dy = z[1] - y
    return (s11 * dx * dx - 2.0 * s01 * dx * dy + s00 * dy * dy) <= gamma * det


@njit(cache=True)
def _decide(j, c_h, c_score, c_mean, c_cov, c_logc, lo, hi, z, V, t, log_unseen, half_logdet_v,
            Hm, Hc, Hlogc, Hcount, Ht, dirty, dirty_list, istate, fstate, gamma, check_gate,
            terrain_ratio, log_rmax, s_kind, s_param, motion, vel_std, assign):
    """Decide report j among candidates [lo, hi) and apply the estimation step.

    istate = [N̂_D, n_dirty, k reports done]; fstate = [ln c_min, γ needed on _WIDEN].
    """
    n = istate[0]
    best = -np.inf
    arg = -1
    for p in range(lo, hi):
        if c_score[p] > best:
            best = c_score[p]
            arg = p
    unseen = log_unseen[j] + log_s_ratio_code(s_kind, s_param, n, istate[2] + 1)
    if check_gate and n > 0:
        extra = log_rmax - fstate[0] if terrain_ratio else 0.0
        const = -_LOG_2PI - half_logdet_v[j] + extra
        top = max(best, unseen)
        if const - 0.5 * gamma > top:
            fstate[1] = 2.0 * (const - top) * (1.0 + 1e-12) + 1e-9
            return _WIDEN
    D = Hm.shape[1]
    if arg < 0 or unseen > best:
        h = n
        Hm[h, :] = 0.0
        Hc[h, :, :] = 0.0
        Hm[h, 0] = z[j, 0]
        Hm[h, 1] = z[j, 1]
        for a in range(2):
            for b in range(2):
                Hc[h, a, b] = V[j, a, b]
        if motion == MOTION_CV:
            for a in range(2, D):
                Hc[h, a, a] = vel_std * vel_std
        Hlogc[h] = log_unseen[j]
        Hcount[h] = 1
        istate[0] = n + 1
    else:
        h = c_h[arg]
        Hm[h, :] = c_mean[arg]
        Hc[h, :, :] = c_cov[arg]
        Hlogc[h] = c_logc[arg]
        Hcount[h] += 1
    Ht[h] = t[j]
    if Hlogc[h] < fstate[0]:
        fstate[0] = Hlogc[h]
    if not dirty[h]:
        dirty[h] = True
        dirty_list[istate[1]] = h
        istate[1] += 1
    istate[2] += 1
    assign[j] = h
    return _DONE


@njit(cache=True)
def _walk(start, z, V, t, log_unseen, half_logdet_v, ptr, p_h, p_score, p_mean, p_cov, p_logc,
          Hm, Hc, Hlogc, Hcount, Ht, dirty, dirty_list, istate, fstate, gamma, terrain_ratio,
          log_rmax, s_kind, s_param, motion, q, vel_std, assign):
    """Decide reports start.. of the block with the precomputed pair scores until one conflicts
    with an earlier decision of the block (returns (j, _CONFLICT)) or needs a wider gate."""
    for j in range(start, z.shape[0]):
        for p in range(ptr[j], ptr[j + 1]):
            if dirty[p_h[p]]:
                return j, _CONFLICT
        for i in range(istate[1]):
            if _in_gate(Hm, Hc, Ht, dirty_list[i], z[j], V[j], t[j], motion, q, gamma):
                return j, _CONFLICT
        status = _decide(j, p_h, p_score, p_mean, p_cov, p_logc, ptr[j], ptr[j + 1], z, V, t,
                         log_unseen, half_logdet_v, Hm, Hc, Hlogc, Hcount, Ht, dirty, dirty_list,
                         istate, fstate, gamma, True, terrain_ratio, log_rmax, s_kind, s_param,
                         motion, vel_std, assign)
        if status != _DONE:
            return j, status
    return z.shape[0], _DONE


@njit(cache=True)
def _fresh_pairs(j, z, V, t, Hm, Hc, Ht, dirty_list, n_dirty, motion, q, gamma):
    """(report, hypothesis) pairs in the gate between reports j.. and the dirty hypotheses."""
    count = 0
    for k in range(j, z.shape[0]):
        for i in range(n_dirty):
            if _in_gate(Hm, Hc, Ht, dirty_list[i], z[k], V[k], t[k], motion, q, gamma):
                count += 1
    rep = np.empty(count, np.int64)
    hyp = np.empty(count, np.int64)
    c = 0
    for k in range(j, z.shape[0]):
        for i in range(n_dirty):
            if _in_gate(Hm, Hc, Ht, dirty_list[i], z[k], V[k], t[k], motion, q, gamma):
                rep[c] = k
                hyp[c] = dirty_list[i]
                c += 1
    return rep, hyp


# ----------------------------------------------------------------------------- the tracker


def _one_thread_when_small(fn: Callable, size_arg: int) -> Callable:
    """Run ``fn`` on one numba thread when its argument ``size_arg`` has fewer than 4096 rows: on a
    loaded machine the launch of a parallel kernel for a few Gaussians costs ~100x the work."""

    def run(*args, **kwargs):
        if args[size_arg].shape[0] >= 4096:
            return fn(*args, **kwargs)
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            return fn(*args, **kwargs)
        finally:
            numba.set_num_threads(threads)

    return run


def _kalman_position_update(m: np.ndarray, P: np.ndarray, z: np.ndarray, V: np.ndarray):
    """Kalman measurement update of (N, D) states by position reports (N, d): H = [I 0].

    Returns (posterior means, posterior covariances, ln G(z; H m, H P Hᵀ + V)). With D = d this is
    :func:`tracker.reports.gaussian_product`, which the static model uses.
    """
    d = z.shape[1]
    S = P[:, :d, :d] + V
    S_inv = np.linalg.inv(S)
    K = P[:, :, :d] @ S_inv
    r = z - m[:, :d]
    post_m = m + np.einsum("nij,nj->ni", K, r)
    post_P = P - K @ P[:, :d, :]
    post_P = 0.5 * (post_P + post_P.transpose(0, 2, 1))
    maha = np.einsum("ni,nij,nj->n", r, S_inv, r)
    log_g = -0.5 * (maha + np.linalg.slogdet(S)[1] + d * _LOG_2PI)
    return post_m, post_P, log_g


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
    (:class:`~tracker.sfunc.ExpS`, :class:`~tracker.sfunc.PoissonS`); ``motion``
    :class:`~tracker.hypotheses.Static` or :class:`~tracker.hypotheses.ConstantVelocity`; ``gamma``
    the gate on d² (decisions do not depend on it, see the module doc); ``off_prior`` what to do
    with a report whose ∫G(z,V) r is 0 (off the grid or on structural zeros) in TT/UT: "raise"
    (default; nothing is changed) or "skip" (assignment -1, not counted in k). ``gater`` and
    ``integrator`` default to :func:`tracker.gating.gate` and :func:`tracker.terrace.integrate`.

    Fitted state: ``hypotheses_``, ``n_detected_``, ``n_reports_`` (k), ``stats_``.
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
        self.gater = _one_thread_when_small(gater or _default_gater(), 2)  # sized by the reports
        self.integrator = _one_thread_when_small(integrator or _default_integrator(), 1)
        xmin, ymin, xmax, ymax = prior.grid.bounds
        self.log_u = -math.log((xmax - xmin) * (ymax - ymin))
        self.log_rmax = math.log(float(np.max(prior.density))) + _RMAX_SLACK
        self.hypotheses_ = Hypotheses(self.motion.state_dim)
        self.n_reports_ = 0
        self._last_time = -np.inf
        self._min_log_c = np.inf
        self.stats_ = {"blocks": 0, "pairs": 0, "conflicts": 0, "widened": 0, "skipped": 0}

    @property
    def terrain_association(self) -> bool:
        return self.variant == "TT"

    @property
    def n_detected_(self) -> int:
        return self.hypotheses_.n

    # -- input checks: everything is validated before any state changes

    def _check(self, reports: Reports) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        z, V = check_gaussians(reports.means, reports.covs, "reports")
        if z.shape[1] != 2:
            raise ValueError(f"reports: positions must be 2-D (x, y) metres, got dimension {z.shape[1]}")
        t = np.asarray(reports.times, dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise ValueError(f"reports: non-finite times at indices {bad[:10].tolist()}")
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
        on = np.isfinite(log_iz)
        return (log_iz if self.terrain_association else np.full(z.shape[0], self.log_u)), on

    def update(self, reports: Reports) -> np.ndarray:
        """Process reports in order (one or many); returns the hypothesis index of each (-1 skipped).

        Raises ``ValueError`` naming the offending indices for NaN, non-PD covariances, backwards
        times (constant velocity) or reports off the prior (``off_prior="raise"``); the tracker is
        unchanged when it raises.
        """
        z, V, t = self._check(reports)
        log_unseen, on = self._log_unseen(z, V)
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
        for s in range(0, keep.size, self.block):
            idx = keep[s : s + self.block]
            assign[idx] = self._block(z[idx], V[idx], t[idx], log_unseen[idx])
        if t.size:
            self._last_time = max(self._last_time, float(t[keep].max()) if keep.size else self._last_time)
        return assign

    # -- one block

    def _score(self, h: np.ndarray, z: np.ndarray, V: np.ndarray, t: np.ndarray):
        """Scores ln[G(z; a, A+V) ∫G(b,B)r / c] (ln G for UU/UT) of pairs (hypothesis h, report) from
        the current hypotheses, with the posterior state, covariance and ln c of each pair."""
        H = self.hypotheses_
        a, A, log_c = H.means[h], H.covs[h], H.log_c[h]
        if isinstance(self.motion, ConstantVelocity):
            a, A = self.motion.predict(a, A, t - H.times[h])
            post_m, post_c, log_g = _kalman_position_update(a, A, z, V)
            if self.terrain_association and h.size:
                log_c = _log(self.integrator(self.prior, a[:, :2], A[:, :2, :2]))
        else:
            post_m, post_c, log_g = gaussian_product(a, A, z, V)
        if not self.terrain_association:
            return log_g, post_m, post_c, np.full(h.size, self.log_u)
        if not h.size:
            return log_g, post_m, post_c, np.zeros(0)
        log_i = _log(self.integrator(self.prior, post_m[:, :2], post_c[:, :2, :2]))
        with np.errstate(invalid="ignore"):
            score = np.where(np.isfinite(log_i), log_g + log_i - log_c, -np.inf)
        return score, post_m, post_c, log_i

    def _gate(self, z: np.ndarray, V: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gated (hypothesis, report) pairs of the block against the current hypotheses, CSR by report."""
        H = self.hypotheses_
        if H.n == 0:
            return np.zeros(z.shape[0] + 1, np.int64), np.zeros(0, np.int64)
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
        """Reports of one block in order: gate and score against the block-start state, walk, and on a
        conflict refresh the pairs of the remaining reports with the hypotheses changed since the
        last refresh (one scoring call per refresh, however many reports it serves)."""
        H = self.hypotheses_
        m = z.shape[0]
        ptr, p_h = self._gate(z, V, t)
        p_rep = np.repeat(np.arange(m), np.diff(ptr))
        pairs = self._score(p_h, z[p_rep], V[p_rep], t[p_rep])
        H.reserve(m)
        half_logdet_v = 0.5 * np.linalg.slogdet(V)[1]
        dirty = np.zeros(H.capacity, dtype=np.bool_)
        dirty_list = np.zeros(m, dtype=np.int64)
        if H.n:
            self._min_log_c = float(H.log_c.min())
        istate = np.array([H.n, 0, self.n_reports_], dtype=np.int64)
        fstate = np.array([self._min_log_c, 0.0])
        assign = np.full(m, -1, dtype=np.int64)
        s_kind, s_param = self.s_model.code
        m_kind, q, vel_std = self.motion.code
        store = (H._means, H._covs, H._log_c, H._counts, H._times)
        self.stats_["blocks"] += 1
        self.stats_["pairs"] += int(p_h.size)
        j = 0
        while j < m:
            j, status = _walk(j, z, V, t, log_unseen, half_logdet_v, ptr, p_h, *pairs, *store, dirty,
                              dirty_list, istate, fstate, self.gamma, self.terrain_association,
                              self.log_rmax, s_kind, s_param, m_kind, q, vel_std, assign)
            H.n = int(istate[0])
            if status == _CONFLICT:
                self.stats_["conflicts"] += 1
                n_dirty = int(istate[1])
                f_rep, f_h = _fresh_pairs(j, z, V, t, store[0], store[1], store[4], dirty_list, n_dirty,
                                          m_kind, q, self.gamma)
                fresh = self._score(f_h, z[f_rep], V[f_rep], t[f_rep])
                keep = (p_rep >= j) & ~dirty[p_h]
                p_rep = np.concatenate([p_rep[keep], f_rep])
                p_h = np.concatenate([p_h[keep], f_h])
                order = np.lexsort((p_h, p_rep))
                p_rep, p_h = p_rep[order], p_h[order]
                pairs = tuple(np.concatenate([x[keep], f])[order] for x, f in zip(pairs, fresh, strict=True))
                ptr = np.zeros(m + 1, np.int64)
                np.cumsum(np.bincount(p_rep, minlength=m), out=ptr[1:])
                self.stats_["pairs"] += int(f_h.size)
                dirty[dirty_list[:n_dirty]] = False
                istate[1] = 0
            elif status == _WIDEN:
                self.stats_["widened"] += 1
                fresh_h = self._brute(np.arange(H.n), z[j], V[j], t[j], float(fstate[1]))
                status = self._decide_fresh(j, fresh_h, z, V, t, log_unseen, half_logdet_v, dirty,
                                            dirty_list, istate, fstate, assign)
                if status != _DONE:
                    raise RuntimeError(f"report {j}: decision failed after widening the gate")
                H.n = int(istate[0])
                j += 1
        self.n_reports_ = int(istate[2])
        self._min_log_c = float(fstate[0])
        return assign

    def _decide_fresh(self, j, cand_h, z, V, t, log_unseen, half_logdet_v, dirty, dirty_list, istate,
                      fstate, assign) -> int:
        """Decide report j among hypotheses ``cand_h`` (ascending), all scored from the current state,
        without the gate check (the caller gated wide enough)."""
        H = self.hypotheses_
        rep = np.full(cand_h.size, j)
        c = self._score(cand_h, z[rep], V[rep], t[rep])
        s_kind, s_param = self.s_model.code
        m_kind, _, vel_std = self.motion.code
        return _decide(j, cand_h, *c, 0, cand_h.size, z, V, t, log_unseen, half_logdet_v,
                       H._means, H._covs, H._log_c, H._counts, H._times, dirty, dirty_list, istate, fstate,
                       self.gamma, False, self.terrain_association, self.log_rmax, s_kind, s_param,
                       m_kind, vel_std, assign)

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
    z, V = check_gaussians(reports.means, reports.covs, "reports")
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
        log_c = _log((integrator or _default_integrator())(prior, b, B))
    else:
        xmin, ymin, xmax, ymax = prior.grid.bounds
        log_c = np.full(labels.size, -math.log((xmax - xmin) * (ymax - ymin)))
    return Estimate(b, B, log_c, counts, terrain, labels.astype(np.int64))
