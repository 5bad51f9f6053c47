"""Batch association: the MAP partition of the reports, and samples of its posterior, under paper 1's
own model (static targets in 2-D; see docs/batch.md).

With n clusters among K reports, S of eq. 16 (``PoissonS``) or the paper's ``ExpS``,

    ln p(Λ | Z) = ln S(n, K) + Σ_C ln L_C + const,
    L_C = ∫ r(y) Π_{k∈C} G(z_k; y, V_k) dy = κ_C · ∫ G(y; b_C, B_C) r(y) dy,

B_C = (Σ V_k⁻¹)⁻¹, b_C = B_C Σ V_k⁻¹ z_k and
ln κ_C = −(m−1) ln 2π − ½ Σ ln det V_k + ½ ln det B_C − ½(Σ z_kᵀV_k⁻¹z_k − b_Cᵀ B_C⁻¹ b_C) (m = |C|).
UU takes r = u = 1 / (grid area) over all space (∫G u = u), TT the terrain prior. Every cluster is
kept as its sufficient statistics (count, Σ V⁻¹, Σ V⁻¹z, Σ zᵀV⁻¹z, Σ ln det V), with z measured from
an origin near the reports so that Σ zᵀV⁻¹z does not cancel catastrophically.

Moves (all on gated candidates only):

* collapsed Gibbs, one report at a time, to a gated cluster or a new one, as an exact sequential scan
  in a random order (the random stream is drawn per sweep, so it does not depend on ``chunk``). A
  round takes the next ``chunk`` reports of the scan, gates them against the current cluster
  posteriors (b_D, B_D + V_i), and selects those whose move cannot interact with an earlier report
  of the round (disjoint own and candidate clusters; no possible new cluster of one gates the other);
  their deltas come from one integrate call and a numba loop applies them in scan order with the
  current n in ln S(n₋, K) vs ln S(n₋+1, K). The rest go to the next round, in order.
* split–merge (Jain & Neal 2004) on gated report pairs, with a restricted-Gibbs launch state.

Gate bound. Let n₋ be the number of clusters without report i, c_i = ∫G(z_i; y, V_i) r(y) dy (ln L({i}))
and I_D = ∫G(y; b_D, B_D) r. Joining a cluster D with d² = (z_i−b_D)ᵀ(B_D+V_i)⁻¹(z_i−b_D) > γ has, relative
to the new-cluster option, the weight

    w_D / w_new = [S(n₋, K) / S(n₋+1, K)] · G(z_i; b_D, B_D+V_i) · I_{D∪i} / (I_D · c_i)
               ≤ [S(n₋, K) / S(n₋+1, K)] · e^{−γ/2} r_max / (2π √det V_i · I_D · c_i)

(B_D + V_i ⪰ V_i, I_{D∪i} ≤ r_max; UU: I = c = u). The probability a move neglects is at most the sum
of this bound over the clusters outside the gate (:func:`gate_bound`).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from tqdm.auto import tqdm

from pipeline.prior import TerrainPrior
from tracker.association.batch_kernels import (
    apply_moves,
    earlier_dependency,
    info_gaussians,
    own_without,
    round_options,
    select_round,
)
from tracker.association.cluster_index import ClusterIndex, lambda_max
from tracker.association.greedy import (
    DEFAULT_GAMMA,
    associate,
    one_thread_when_small,
    perfect_estimate,
)
from tracker.integrate import Integrator
from tracker.models.sfunc import ExpS, PoissonS, SModel, log_s
from tracker.types.estimate import Estimate
from tracker.types.reports import Reports

if TYPE_CHECKING:  # gating loads on first use (_default_gater)
    from tracker.gating import Gater

VARIANTS = ("UU", "TT")
MODES = ("map", "sample")
CHUNK = 65536
"""Reports per Gibbs round: larger rounds amortise gating and integrate calls, smaller ones conflict less."""
CACHE_MAX_K = 20000
"""Up to this many reports a chain memoises ln L per cluster (by member set): a chain on a few hundred
reports revisits the same clusters (~3 % of the candidates of a calibration run are distinct), while at
10⁶ reports a sweep rarely does and the table would only cost memory."""
_KEY_SEED = 0x5EED_C1A5
_LOG_2PI = math.log(2.0 * math.pi)

def _default_integrator() -> Integrator:
    from tracker.integrate import integrate_checked

    return integrate_checked


def _default_gater() -> Gater:
    from tracker.gating.gate import gate_unchecked

    return gate_unchecked


def _log(x: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(np.maximum(x, 0.0))


def _log_u(prior: TerrainPrior) -> float:
    xmin, ymin, xmax, ymax = prior.grid.bounds
    return -math.log((xmax - xmin) * (ymax - ymin))


@dataclass(frozen=True)
class ReportStats:
    """Per report: ``vinv`` V⁻¹ (K,2,2) per m², ``hv`` V⁻¹(z − origin) (K,2) per m, ``qv`` (z−o)ᵀV⁻¹(z−o)
    (K,), ``ldv`` ln det V (K,) ln m⁴; ``origin`` (2,) m, ``z`` (K,2) m and ``V`` (K,2,2) m² as given;
    ``key`` (K,) uint64 random keys (fixed seed): a cluster's key is the XOR of its members' (Zobrist
    hashing; two different member sets share a key with probability 2⁻⁶⁴)."""

    vinv: np.ndarray
    hv: np.ndarray
    qv: np.ndarray
    ldv: np.ndarray
    origin: np.ndarray
    z: np.ndarray
    V: np.ndarray
    key: np.ndarray

    @classmethod
    def of(cls, reports: Reports) -> ReportStats:
        z, V = reports.means, reports.covs  # a Reports batch is checked when built
        if z.shape[1] != 2:
            raise ValueError(f"reports: positions must be 2-D, got dimension {z.shape[1]}")
        origin = z.mean(axis=0) if z.shape[0] else np.zeros(2)
        _, vinv, det_v = info_gaussians(V, np.zeros_like(z))  # V⁻¹ and det V of the 2×2 closed form
        zo = z - origin
        hv = np.stack([vinv[:, 0, 0] * zo[:, 0] + vinv[:, 0, 1] * zo[:, 1],
                       vinv[:, 1, 0] * zo[:, 0] + vinv[:, 1, 1] * zo[:, 1]], axis=1)
        qv = zo[:, 0] * hv[:, 0] + zo[:, 1] * hv[:, 1]
        key = np.random.default_rng(_KEY_SEED).integers(0, np.iinfo(np.uint64).max, z.shape[0], dtype=np.uint64, endpoint=True)
        return cls(vinv, hv, qv, np.log(det_v), origin, z, V, key)


def cluster_log_lik(
    prior: TerrainPrior, variant: str, cnt: np.ndarray, P: np.ndarray, h: np.ndarray, q: np.ndarray,
    ld: np.ndarray, origin: np.ndarray, integrator: Integrator | None = None,
) -> np.ndarray:
    """ln L_C (ln of per m^{2m}) of clusters given by their sums (count, Σ V⁻¹, Σ V⁻¹z, Σ zᵀV⁻¹z,
    Σ ln det V; z from ``origin``), with ONE integrate call for all of them (TT)."""
    if cnt.size == 0:
        return np.zeros(0)
    b, B, det_p = info_gaussians(P, h)
    ln_kappa = _log_kappa(cnt, h, q, ld, b, det_p)
    if variant == "UU":
        return ln_kappa + _log_u(prior)
    return ln_kappa + _log((integrator or _default_integrator())(prior, b + origin, B))


def _log_kappa(cnt: np.ndarray, h: np.ndarray, q: np.ndarray, ld: np.ndarray, b: np.ndarray, det_p: np.ndarray) -> np.ndarray:
    """ln κ_C of the Gaussian product: −(m−1) ln 2π − ½ Σ ln det V + ½ ln det B − ½(Σ zᵀV⁻¹z − hᵀBh),
    with b = B h and det P = 1 / det B."""
    hb = h[:, 0] * b[:, 0] + h[:, 1] * b[:, 1]
    return -(cnt - 1) * _LOG_2PI - 0.5 * ld - 0.5 * np.log(det_p) - 0.5 * (q - hb)


def _sums(labels: np.ndarray, rs: ReportStats, n: int) -> tuple[np.ndarray, ...]:
    cnt = np.bincount(labels, minlength=n)
    P = np.stack([np.bincount(labels, rs.vinv[:, a, e], n) for a in range(2) for e in range(2)], axis=1).reshape(n, 2, 2)
    h = np.stack([np.bincount(labels, rs.hv[:, a], n) for a in range(2)], axis=1)
    return cnt, P, h, np.bincount(labels, rs.qv, n), np.bincount(labels, rs.ldv, n)


def log_posterior(
    prior: TerrainPrior, reports: Reports, labels: np.ndarray, s_model: SModel, variant: str = "TT",
    integrator: Integrator | None = None,
) -> float:
    """ln p(Λ | Z) up to a constant common to all partitions: ln S(n, K) + Σ_C ln L_C, for the partition
    given by ``labels`` (K,) (any integers; equal labels share a cluster). One integrate call (TT)."""
    _check_variant(variant)
    rs = ReportStats.of(reports)
    _, inv = np.unique(np.asarray(labels), return_inverse=True)
    n = int(inv.max()) + 1 if inv.size else 0
    ll = cluster_log_lik(prior, variant, *_sums(inv, rs, n), rs.origin, integrator)
    return float(log_s(s_model, n, len(reports))) + float(ll.sum())


def gate_bound(log_s_ratio: float, gamma: float, log_rmax: float, log_det_v: float, log_c: float, log_i_d: np.ndarray) -> float:
    """Upper bound on the probability a Gibbs move of report i gives to the clusters outside its gate:
    Σ_D e^{ln S(n₋,K) − ln S(n₋+1,K)} e^{−γ/2} r_max / (2π √det V_i · I_D · c_i) over the out-of-gate
    clusters' ln I_D (``log_i_d``); ``log_s_ratio`` = ln S(n₋,K) − ln S(n₋+1,K), ``log_c`` = ln c_i."""
    base = log_s_ratio - 0.5 * gamma + log_rmax - _LOG_2PI - 0.5 * log_det_v - log_c
    return float(np.exp(base - np.asarray(log_i_d)).sum())


def _gain(with_k: float, without_k: float) -> float:
    """ln L(G ∪ k) − ln L(G) for a restricted-Gibbs step: NaN (a group of zero prior mass on both sides)
    is no weight, and ±inf is clipped to ±float max."""
    d = with_k - without_k
    if d != d:
        return -math.inf
    return max(min(d, sys.float_info.max), -sys.float_info.max)


def _check_variant(variant: str) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS} (UT associates as UU), got {variant!r}")


@dataclass
class BatchResult:
    """``labels`` (K,) cluster per report (0..n−1), ``log_posterior`` its ln p(Λ|Z) (+const), and the
    greedy start's ``greedy_labels`` / ``greedy_log_posterior``. ``membership`` (K,): each report's
    posterior probability of belonging to its cluster (see :meth:`BatchAssociator.fit`; 1 in map
    mode). Sampling mode: ``pairs`` (P,2) gated report pairs i < j with ``pair_prob`` (P,) the
    posterior P(i and j from one target), and ``nd_values`` / ``nd_prob`` the posterior of N_D.
    ``samples`` (S, K) int32: the sampled partitions' labels, when the associator keeps them.
    ``trace`` ln p per sweep; ``stats`` counters."""

    labels: np.ndarray
    log_posterior: float
    greedy_labels: np.ndarray
    greedy_log_posterior: float
    membership: np.ndarray
    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    pair_prob: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nd_values: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    nd_prob: np.ndarray = field(default_factory=lambda: np.zeros(0))
    samples: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int32))
    trace: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    @property
    def n_detected(self) -> int:
        return int(self.labels.max()) + 1 if self.labels.size else 0


class _Chain:
    """One partition state with its cluster sums and keys, ln L per cluster, and ln p(Λ|Z) kept up to
    date. ``cache`` (None: off) maps a cluster's key to its ln L, shared by the chains of one fit."""

    def __init__(self, owner: BatchAssociator, rs: ReportStats, single_ll: np.ndarray, labels: np.ndarray,
                 table: np.ndarray | None, cache: dict[int, float] | None = None) -> None:
        self.o, self.rs, self.single_ll, self.table, self.cache = owner, rs, single_ll, table, cache
        K = rs.z.shape[0]
        self.K = K
        _, inv = np.unique(labels, return_inverse=True)
        n = int(inv.max()) + 1 if K else 0
        self.labels = inv.astype(np.int64)
        self.cnt, self.P, self.h, self.q, self.ld = (np.zeros((K,) + s, d) for s, d in
                                                     (((), np.int64), ((2, 2), float), ((2,), float), ((), float), ((), float)))
        for dst, src in zip((self.cnt, self.P, self.h, self.q, self.ld), _sums(self.labels, rs, n), strict=True):
            dst[:n] = src
        self.zh = np.zeros(K, np.uint64)
        np.bitwise_xor.at(self.zh, self.labels, rs.key)
        self.logL = np.zeros(K)
        # a singleton's ln L is its report's (the same sums, so the same integral): integrate the rest
        member = np.zeros(n, np.int64)
        member[self.labels] = np.arange(K)
        self.logL[:n] = single_ll[member]
        mc = np.flatnonzero(self.cnt[:n] > 1)
        self.logL[mc] = self._ll(self.cnt[mc], self.P[mc], self.h[mc], self.q[mc], self.ld[mc], self._masks(mc), self.zh[mc])
        self.cb, self.cB = np.zeros((K, 2)), np.tile(np.eye(2), (K, 1, 1))
        self.cb[:n], self.cB[:n] = self._gaussians(self.P[:n], self.h[:n])
        self.lam_v = lambda_max(rs.V)
        self.index = ClusterIndex.for_reports(rs.z - rs.origin, self.lam_v, K, owner.gamma)
        self.index.update(np.arange(n), self.cb[:n], self.cB[:n])
        self.free = np.zeros(K, np.int64)
        self.free[: K - n] = np.arange(K - 1, n - 1, -1)  # LOW ids popped first: deterministic ids
        self.istate = np.array([n, K - n, K], np.int64)
        self.s_cache = np.full(K + 2, np.nan)
        self.lp = float(log_s(owner.s_model, n, K)) + float(self.logL[:n].sum())

    # -- ln L of candidate clusters: the table (tests, K <= 20), the cache, or the integrator

    def _masks(self, clusters: np.ndarray) -> np.ndarray | None:
        if self.table is None:
            return None
        masks = np.zeros(self.K, np.int64)
        np.bitwise_or.at(masks, self.labels, np.left_shift(np.int64(1), np.arange(self.K, dtype=np.int64)))
        return masks[clusters]

    def _ll(self, cnt, P, h, q, ld, masks, keys) -> np.ndarray:
        if self.table is not None:
            return self.table[masks]
        if self.cache is None:
            return self._integrate(cnt, P, h, q, ld)
        got = self._cached(keys)
        miss = np.flatnonzero(np.isnan(got))
        if miss.size:
            got[miss] = self._integrate(cnt[miss], P[miss], h[miss], q[miss], ld[miss])
            self.cache.update(zip(keys[miss].tolist(), got[miss].tolist(), strict=True))
        return got

    def _cached(self, keys: np.ndarray) -> np.ndarray:
        """ln L of the clusters with ``keys`` from the cache, NaN where absent (ln L is never NaN)."""
        get = self.cache.get
        return np.array([get(k, math.nan) for k in keys.tolist()], float)

    def _integrate(self, cnt, P, h, q, ld) -> np.ndarray:
        self.o.stats_["integrals"] += int(cnt.size) if self.o.variant == "TT" else 0
        return cluster_log_lik(self.o.prior, self.o.variant, cnt, P, h, q, ld, self.rs.origin, self.o.integrator)

    def _gaussians(self, P: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b, B, _ = info_gaussians(P, h)
        return b, B

    # -- one Gibbs sweep

    def sweep(self, beta: float, rng: np.random.Generator) -> int:
        """One exact sequential scan (gated) in a random order at inverse temperature ``beta``; returns
        the number of reports that changed cluster."""
        order = rng.permutation(self.K)
        u = rng.random(self.K)
        moved = 0
        deferred = order[:0]  # the scan still to do is deferred, then order[at:]
        at = 0
        size = min(self.o.chunk, 2048)
        while deferred.size or at < self.K:
            fresh = order[at: at + max(size - deferred.size, 0)]
            at += fresh.size
            U = np.concatenate([deferred[:size], fresh])
            sel, m = self._round(U, beta, u)
            moved += m
            deferred = np.concatenate([U[~sel], deferred[size:]])
            # about half of a round is selectable when its reports meet ~1 gated neighbour each:
            # round sizes follow that point (the chain does not depend on them)
            size = int(np.clip(2 * sel.sum(), 64, self.o.chunk))
            self.o.stats_["rounds"] += 1
        return moved

    def _gated(self, zc: np.ndarray, V: np.ndarray, U: np.ndarray, own: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gated clusters of the round's reports other than their own: CSR (ptr (m+1,), ids ascending
        per report). From the cluster index, or (a gater given) by gating all live clusters with it."""
        if self.o.given_gater is None:
            return self.index.gated(zc, V, self.lam_v[U], own)
        live = np.flatnonzero(self.cnt > 0)
        c_idx, r_idx = self.o.gater(self.cb[live], self.cB[live], zc, V, threshold=self.o.gamma)
        cl, pos = live[np.asarray(c_idx, np.int64)], np.asarray(r_idx, np.int64)
        keep = cl != own[pos]
        cl, pos = cl[keep], pos[keep]
        order = np.lexsort((cl, pos))
        return np.concatenate([[0], np.cumsum(np.bincount(pos, minlength=U.size))]), cl[order]

    def _round(self, U: np.ndarray, beta: float, u: np.ndarray) -> tuple[np.ndarray, int]:
        rs, gam = self.rs, self.o.gamma
        m = U.size
        zc = rs.z[U] - rs.origin
        V = rs.V[U]
        own = self.labels[U]
        ptr, cl = self._gated(zc, V, U, own)
        pos = np.repeat(np.arange(m), np.diff(ptr))
        # own cluster without the report: its Gaussian decides whether staying is a gated option
        multi, mi, bm, Bm, own_gated = own_without(U, own, self.cnt, self.P, self.h, rs.vinv, rs.hv, zc, V, gam)
        # possible new clusters of each report ({i}, own \ i, C ∪ i) and who they gate
        earlier = earlier_dependency(zc, V, self.lam_v[U], gam, mi, bm, Bm, pos, cl, self.P, self.h, U, rs.vinv, rs.hv)
        self.o.stamp += 1
        sel = select_round(own, ptr, cl, earlier, self.o.blocked(self.K), self.o.stamp)
        # options of the selected reports: own (if gated and not alone) and gated clusters, by cluster id
        s_pos = np.flatnonzero(sel)
        o_ptr, o_cl, is_own, o_pos = round_options(sel, own, ptr, cl, own_gated)
        jo = U[o_pos]
        ext = ~is_own
        sm = s_pos[multi[s_pos]]  # selected reports that leave a non-empty cluster behind
        jm = U[sm]
        e_cl, e_j, m_cl = o_cl[ext], jo[ext], own[sm]
        cnt_all = np.concatenate([self.cnt[e_cl] + 1, self.cnt[m_cl] - 1])
        P_all = np.concatenate([self.P[e_cl] + rs.vinv[e_j], self.P[m_cl] - rs.vinv[jm]])
        h_all = np.concatenate([self.h[e_cl] + rs.hv[e_j], self.h[m_cl] - rs.hv[jm]])
        q_all = np.concatenate([self.q[e_cl] + rs.qv[e_j], self.q[m_cl] - rs.qv[jm]])
        ld_all = np.concatenate([self.ld[e_cl] + rs.ldv[e_j], self.ld[m_cl] - rs.ldv[jm]])
        masks = None
        if self.table is not None:
            cm = self._masks(np.arange(self.K))
            bit = np.left_shift(np.int64(1), np.arange(self.K, dtype=np.int64))
            masks = np.concatenate([cm[e_cl] | bit[e_j], cm[m_cl] & ~bit[jm]])
        keys = np.concatenate([self.zh[e_cl] ^ rs.key[e_j], self.zh[m_cl] ^ rs.key[jm]])
        ll = self._ll(cnt_all, P_all, h_all, q_all, ld_all, masks, keys)
        n_ext = e_cl.size
        own_minus = np.zeros(m)
        own_minus[sm] = ll[n_ext:]
        opt_ll = np.empty(o_cl.size)
        opt_ll[ext] = ll[:n_ext]
        opt_ll[is_own] = self.logL[o_cl[is_own]]
        opt_delta = np.where(is_own, opt_ll - own_minus[o_pos], opt_ll - self.logL[o_cl])
        kind, param = self.o.s_model.code
        j_sel = U[s_pos]
        before = own[s_pos]
        d_lp, moved = apply_moves(
            j_sel, o_ptr, o_cl, opt_delta, opt_ll, own_minus[s_pos], self.single_ll, u, float(beta),
            self.labels, self.cnt, self.P, self.h, self.q, self.ld, self.logL, self.free, self.istate,
            self.s_cache, kind, param, rs.vinv, rs.hv, rs.qv, rs.ldv)
        self.lp += d_lp
        after = self.labels[j_sel]
        went = after != before  # only the reports that moved changed clusters
        np.bitwise_xor.at(self.zh, before[went], rs.key[j_sel[went]])
        np.bitwise_xor.at(self.zh, after[went], rs.key[j_sel[went]])
        changed = np.unique(np.concatenate([before[went], after[went]]))
        self.index.remove(changed[self.cnt[changed] == 0])
        changed = changed[self.cnt[changed] > 0]
        self.cb[changed], self.cB[changed] = self._gaussians(self.P[changed], self.h[changed])
        self.index.update(changed, self.cb[changed], self.cB[changed])
        return sel, moved

    # -- split-merge (Jain & Neal 2004), restricted Gibbs launch

    def _set_ll(self, members: list[np.ndarray]) -> np.ndarray:
        rs = self.rs
        keys = np.array([np.bitwise_xor.reduce(rs.key[x]) for x in members], np.uint64)
        if self.table is None and self.cache is not None:
            got = self._cached(keys)
            if not np.isnan(got).any():
                return got  # no sums needed
        cnt = np.array([x.size for x in members], np.int64)
        P = np.array([rs.vinv[x].sum(0) for x in members]).reshape(-1, 2, 2)
        h = np.array([rs.hv[x].sum(0) for x in members]).reshape(-1, 2)
        q = np.array([rs.qv[x].sum() for x in members])
        ld = np.array([rs.ldv[x].sum() for x in members])
        masks = None
        if self.table is not None:
            masks = np.array([np.bitwise_or.reduce(np.left_shift(np.int64(1), x.astype(np.int64))) for x in members], np.int64)
        return self._ll(cnt, P, h, q, ld, masks, keys)

    def _restricted(self, i: int, j: int, rest: np.ndarray, side: np.ndarray, rng, target: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """One restricted Gibbs scan of ``rest`` between the groups of i and j from state ``side`` (True =
        with j). With ``target`` the scan is forced to it and only its log probability is accumulated
        (the merge move's reverse proposal). Returns (side, ln q)."""
        log_q = 0.0
        side = side.copy()
        key = self.rs.key
        # the groups' keys without report k, kept by XOR: the member arrays are built on a cache miss only
        ki = int(np.bitwise_xor.reduce(key[rest[~side]], initial=key[i]))
        kj = int(np.bitwise_xor.reduce(key[rest[side]], initial=key[j]))
        get = self.cache.get if self.cache is not None and self.table is None else None
        for t in range(rest.size):
            k = rest[t]
            kk = int(key[k])
            if side[t]:
                kj ^= kk
            else:
                ki ^= kk
            ll = [get(x) for x in (ki, ki ^ kk, kj, kj ^ kk)] if get else [None]
            if None in ll:
                others = np.delete(np.arange(rest.size), t)
                gi = np.concatenate([[i], rest[others][~side[others]]]).astype(np.int64)
                gj = np.concatenate([[j], rest[others][side[others]]]).astype(np.int64)
                ll = self._set_ll([gi, np.append(gi, k), gj, np.append(gj, k)]).tolist()
            wi, wj = _gain(ll[1], ll[0]), _gain(ll[3], ll[2])
            top = max(wi, wj)
            if top == -math.inf:
                return side, -math.inf  # k fits neither group (prior zero): the proposal is void
            norm = top + math.log(math.exp(wi - top) + math.exp(wj - top))
            side[t] = rng.random() < math.exp(wj - norm) if target is None else target[t]
            log_q += (wj if side[t] else wi) - norm
            if side[t]:
                kj ^= kk
            else:
                ki ^= kk
        return side, log_q

    def split_merge(self, beta: float, rng: np.random.Generator, pairs: np.ndarray, n_moves: int, launch: int) -> int:
        """``n_moves`` split–merge proposals on random gated report pairs; beta = inf accepts improvements
        only. Returns the number accepted."""
        accepted = 0
        K, s = self.K, self.o.s_model
        for _ in range(n_moves if pairs.shape[0] else 0):
            i, j = pairs[rng.integers(pairs.shape[0])]
            ci, cj = self.labels[i], self.labels[j]
            members = np.flatnonzero((self.labels == ci) | (self.labels == cj))
            rest = members[(members != i) & (members != j)]
            side = rng.random(rest.size) < 0.5
            for _ in range(launch):
                side, _ = self._restricted(i, j, rest, side, rng)
            n = int(self.istate[0])
            if ci == cj:
                side, log_q = self._restricted(i, j, rest, side, rng)
                if log_q == -math.inf:
                    continue
                gi, gj = np.append(rest[~side], i), np.append(rest[side], j)
                ll = self._set_ll([gi, gj])
                d = float(log_s(s, n + 1, K) - log_s(s, n, K)) + ll.sum() - self.logL[ci]
                log_acc = -math.inf if not np.isfinite(d) else (beta * d - log_q if np.isfinite(beta) else (0.0 if d > 0 else -math.inf))
            else:
                _, log_q = self._restricted(i, j, rest, side, rng, self.labels[rest] == cj)
                ll = self._set_ll([members])
                d = float(log_s(s, n - 1, K) - log_s(s, n, K)) + ll[0] - self.logL[ci] - self.logL[cj]
                log_acc = -math.inf if not np.isfinite(d) else (beta * d + log_q if np.isfinite(beta) else (0.0 if d > 0 else -math.inf))
            if math.log(rng.random()) < log_acc:
                new = self.labels.copy()
                if ci == cj:
                    new[rest[side]] = -1
                    new[j] = -1
                else:
                    new[members] = ci
                self._reset(new)
                accepted += 1
        return accepted

    def _reset(self, labels: np.ndarray) -> None:
        """Rebuild the state from labels (-1: a new cluster); after an accepted split–merge."""
        labels = labels.copy()
        labels[labels < 0] = labels.max() + 1
        self.__init__(self.o, self.rs, self.single_ll, labels, self.table, self.cache)


class BatchAssociator:
    """MAP search (``mode="map"``) or posterior sampling (``mode="sample"``) over partitions of static
    2-D reports under paper 1's model, started from the greedy tracker's result.

    ``variant`` "UU" or "TT"; S as ``tau`` (ExpS) or ``s_model``; ``gamma`` the gate on d²; ``chunk``
    reports per Gibbs round. Map mode: per restart (the first from greedy, the others from all
    singletons) ``anneal`` Gibbs sweeps with inverse temperature rising geometrically from 1 to
    ``beta_max``, then zero-temperature sweeps (ICM) to convergence (at most ``icm_max``); the best
    state visited wins. Sample mode: ``burn_in`` sweeps then ``samples`` sweeps, one sample each.
    ``split_merge`` proposals per sweep with ``launch`` restricted-Gibbs launch scans; ``keep_samples``
    keeps every sampled partition (``BatchResult.samples``). ``seed`` for a ``numpy.random.Generator``; ``progress`` shows tqdm over sweeps. ``table=True`` (K <= 20, tests)
    precomputes ln L for all 2^K subsets in one integrate call; otherwise ``cache`` (None: when K <=
    :data:`CACHE_MAX_K`) memoises each cluster's ln L by its member set for the fit. Rounds gate through the chain's cluster
    index (:class:`~tracker.association.cluster_index.ClusterIndex`, the gater's exact test); a ``gater``
    given instead gates each round against all live clusters (the same chain, slower; tests and
    benchmarks); the gated report pairs of split–merge use ``gater`` (default
    :func:`~tracker.gating.gate.gate_unchecked`).
    """

    def __init__(
        self, prior: TerrainPrior, variant: str = "TT", tau: float | None = None, s_model: SModel | None = None,
        mode: str = "map", gamma: float = DEFAULT_GAMMA, chunk: int = CHUNK, anneal: int = 20, beta_max: float = 50.0,
        icm_max: int = 50, restarts: int = 2, burn_in: int = 20, samples: int = 200, split_merge: int = 0,
        launch: int = 3, seed: int = 0, keep_samples: bool = False, progress: bool = False, table: bool = False,
        cache: bool | None = None,
        integrator: Integrator | None = None, gater: Gater | None = None,
    ) -> None:
        _check_variant(variant)
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if (tau is None) == (s_model is None):
            raise ValueError("give exactly one of tau= (S = exp(-n tau)) or s_model= (ExpS or PoissonS)")
        self.s_model = ExpS(float(tau)) if s_model is None else s_model
        if not isinstance(self.s_model, ExpS | PoissonS):
            raise ValueError(f"s_model must be ExpS or PoissonS, got {self.s_model!r}")
        if not (math.isfinite(gamma) and gamma > 0) or chunk < 1:
            raise ValueError(f"gamma must be positive and finite and chunk >= 1, got {gamma}, {chunk}")
        self.prior, self.variant, self.mode, self.gamma, self.chunk = prior, variant, mode, float(gamma), int(chunk)
        self.anneal, self.beta_max, self.icm_max, self.restarts = int(anneal), float(beta_max), int(icm_max), int(restarts)
        self.burn_in, self.samples, self.n_split_merge, self.launch = int(burn_in), int(samples), int(split_merge), int(launch)
        self.seed, self.progress, self.use_table, self.cache = seed, progress, table, cache
        self.keep_samples = bool(keep_samples)
        # rounds are small: one numba thread below 4096 rows, as in greedy
        self.integrator = one_thread_when_small(integrator or _default_integrator(), 1)
        self.gater = one_thread_when_small(gater or _default_gater(), 2)
        self.given_gater = gater  # None: rounds gate through the chain's cluster index
        self.stamp = 0
        self._blocked = np.zeros(0, np.int64)
        self.stats_ = {"rounds": 0, "integrals": 0, "sweeps": 0, "split_merge_accepted": 0}

    def blocked(self, K: int) -> np.ndarray:
        """Per cluster id, the last round stamp that touched it (reused across rounds)."""
        if self._blocked.size < K:
            self._blocked = np.zeros(K, np.int64)
            self.stamp = 1
        return self._blocked

    def _table(self, rs: ReportStats) -> np.ndarray:
        K = rs.z.shape[0]
        if K > 20:
            raise ValueError(f"table=True enumerates 2^K subsets; K = {K} > 20")
        masks = np.arange(1, 2**K, dtype=np.int64)
        bits = ((masks[:, None] >> np.arange(K)) & 1).astype(float)
        ll = cluster_log_lik(self.prior, self.variant, bits.sum(1).astype(np.int64), np.einsum("mk,kij->mij", bits, rs.vinv),
                             bits @ rs.hv, bits @ rs.qv, bits @ rs.ldv, rs.origin, self.integrator)
        return np.concatenate([[0.0], ll])

    def chain(self, reports: Reports, labels: np.ndarray) -> _Chain:
        """A chain at partition ``labels`` (used by :meth:`fit`; exposed for tests and benchmarks)."""
        rs = ReportStats.of(reports)
        table = self._table(rs) if self.use_table else None
        if table is not None:
            single_ll = table[np.left_shift(np.int64(1), np.arange(rs.z.shape[0], dtype=np.int64))]
        else:
            one = np.ones(rs.z.shape[0], np.int64)
            single_ll = cluster_log_lik(self.prior, self.variant, one, rs.vinv, rs.hv, rs.qv, rs.ldv, rs.origin, self.integrator)
        if not np.isfinite(single_ll).all():
            bad = np.flatnonzero(~np.isfinite(single_ll))
            raise ValueError(f"reports at indices {bad[:10].tolist()} have zero prior mass under their Gaussian")
        K = rs.z.shape[0]
        cache = {} if table is None and (self.cache if self.cache is not None else K <= CACHE_MAX_K) else None
        return _Chain(self, rs, single_ll, np.asarray(labels), table, cache)

    def greedy(self, reports: Reports) -> np.ndarray:
        """The greedy tracker's assignments (paper 1, Fig. 3) under the same variant and S."""
        return associate(self.prior, reports, self.variant, s_model=self.s_model).assignments

    def fit(self, reports: Reports, init: np.ndarray | None = None) -> BatchResult:
        """Search (map) or sample (sample) from ``init`` labels (default: greedy).

        Membership (sample mode): for report i with best-state cluster M(i) of size > 1, the mean over
        samples of the fraction of M(i)'s other members that share i's sampled cluster; for a singleton,
        the fraction of samples in which i is alone."""
        rng = np.random.default_rng(self.seed)
        init = self.greedy(reports) if init is None else np.asarray(init)
        ch = self.chain(reports, init)
        g_labels, g_lp = ch.labels.copy(), ch.lp
        pairs = self._pairs(ch.rs)
        best_lp, best = ch.lp, ch.labels.copy()
        trace: list[float] = []
        if self.mode == "map":
            for restart in range(self.restarts + 1):
                if restart:
                    ch = _Chain(self, ch.rs, ch.single_ll, np.arange(len(reports)), ch.table, ch.cache)
                betas = self.beta_max ** (np.arange(self.anneal) / max(self.anneal - 1, 1))
                for beta in tqdm(np.concatenate([betas, np.full(self.icm_max, np.inf)]), desc=f"batch map {restart}", unit="sweep", disable=not self.progress):
                    moved = ch.sweep(beta, rng)
                    moved += ch.split_merge(beta, rng, pairs, self.n_split_merge, self.launch)
                    self.stats_["sweeps"] += 1
                    trace.append(ch.lp)
                    if ch.lp > best_lp:
                        best_lp, best = ch.lp, ch.labels.copy()
                    if not np.isfinite(beta) and moved == 0:
                        break
            membership = np.ones(len(reports))
            return self._result(best, best_lp, g_labels, g_lp, membership, trace)
        kept = []
        nd = []
        co = np.zeros(pairs.shape[0])
        for s in tqdm(range(self.burn_in + self.samples), desc="batch sample", unit="sweep", disable=not self.progress):
            ch.sweep(1.0, rng)
            self.stats_["split_merge_accepted"] += ch.split_merge(1.0, rng, pairs, self.n_split_merge, self.launch)
            self.stats_["sweeps"] += 1
            trace.append(ch.lp)
            if ch.lp > best_lp:
                best_lp, best = ch.lp, ch.labels.copy()
            if s >= self.burn_in:
                kept.append(ch.labels.astype(np.int32))
                nd.append(int(ch.istate[0]))
                co += ch.labels[pairs[:, 0]] == ch.labels[pairs[:, 1]]
        res = self._result(best, best_lp, g_labels, g_lp, self._membership(best, kept), trace)
        res.pairs, res.pair_prob = pairs, co / max(len(kept), 1)
        res.nd_values, counts = np.unique(np.array(nd, np.int64), return_counts=True)
        res.nd_prob = counts / max(len(kept), 1)
        if self.keep_samples:
            res.samples = np.array(kept, np.int32).reshape(len(kept), len(reports))
        return res

    def _pairs(self, rs: ReportStats) -> np.ndarray:
        """Gated report pairs (i < j) with d² = (z_i−z_j)ᵀ(V_i+V_j)⁻¹(z_i−z_j) <= γ."""
        a, b = self.gater(rs.z - rs.origin, rs.V, rs.z - rs.origin, rs.V, threshold=self.gamma)
        a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
        keep = a < b
        return np.stack([a[keep], b[keep]], 1)

    @staticmethod
    def _membership(ref: np.ndarray, kept: list[np.ndarray]) -> np.ndarray:
        size = np.bincount(ref)[ref]
        acc = np.zeros(ref.size)
        for lab in kept:
            _, key = np.unique(lab.astype(np.int64) * (ref.max() + 1) + ref, return_inverse=True)
            shared = np.bincount(key)[key]  # reports with the same sampled and best cluster, incl. i
            alone = np.bincount(lab)[lab] == 1
            acc += np.where(size > 1, (shared - 1) / np.maximum(size - 1, 1), alone)
        return acc / max(len(kept), 1)

    def _result(self, labels, lp, g_labels, g_lp, membership, trace) -> BatchResult:
        _, inv = np.unique(labels, return_inverse=True)
        return BatchResult(inv.astype(np.int64), float(lp), g_labels, float(g_lp), membership, trace=trace, stats=dict(self.stats_))


def associate_batch(prior: TerrainPrior, reports: Reports, variant: str = "TT", tau: float | None = None,
                    s_model: SModel | None = None, **kwargs) -> BatchResult:
    """Batch form of :class:`BatchAssociator` (greedy start, then search or sampling)."""
    return BatchAssociator(prior, variant, tau=tau, s_model=s_model, **kwargs).fit(reports)


def batch_estimate(prior: TerrainPrior, reports: Reports, labels: np.ndarray, variant: str = "TT",
                   integrator: Integrator | None = None) -> Estimate:
    """Fused position densities of the clusters of ``labels`` (TT: times r, renormalised; UU: Gaussians)."""
    grouped = Reports(reports.means, reports.covs, reports.times, np.asarray(labels, np.int64))
    est = perfect_estimate(prior, grouped, terrain=variant == "TT", integrator=integrator)
    return Estimate(est.means, est.covs, est.log_c, est.counts, est.terrain, np.full(est.counts.size, -1, np.int64))
