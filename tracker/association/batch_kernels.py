"""Numba kernels of the batch associator (:mod:`tracker.association.batch`): 2×2 information-form
Gaussians, a round's own-cluster options, dependencies and selection, and the sequential application
of precomputed collapsed-Gibbs moves.

The cluster state lives in flat arrays indexed by cluster id (capacity K): ``cnt`` reports per cluster,
the information sums ``P`` = Σ V⁻¹ (per m², stored as P00, P01, P11), ``h`` = Σ V⁻¹z (per m),
``q`` = Σ zᵀV⁻¹z, ``ld`` = Σ ln det V (ln m⁴), and ``logL`` the cluster's ln L_C. Free ids are a stack.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tracker.gating.grid import counting_order
from tracker.models.sfunc import log_s_code


@njit(cache=True)
def log_s_cached(cache: np.ndarray, kind: int, param: float, n: int, k: int) -> float:
    """ln S(n, k) with ``cache[n]`` memoised (NaN: not computed yet); n moves by ±1 per move."""
    v = cache[n]
    if np.isnan(v):
        v = log_s_code(kind, param, n, k)
        cache[n] = v
    return v


@njit(cache=True)
def move_log_weights(opt_delta: np.ndarray, new_ll: float, log_s_stay: float, log_s_new: float) -> np.ndarray:
    """Unnormalised ln weights of one report's options: joining option o (its cluster without the report)
    ln L(C∪i) − ln L(C) + ln S(n₋, K) = ``opt_delta[o] + log_s_stay``, then a new cluster
    ln L({i}) + ln S(n₋+1, K) (n₋ the number of clusters with the report removed)."""
    w = np.empty(opt_delta.size + 1)
    for o in range(opt_delta.size):
        w[o] = opt_delta[o] + log_s_stay
    w[opt_delta.size] = new_ll + log_s_new
    return w


@njit(cache=True)
def choose(w: np.ndarray, beta: float, u: float) -> int:
    """Option drawn ∝ exp(beta·w) by inverse CDF with uniform ``u``; beta = inf takes the first argmax."""
    m = -np.inf
    best = 0
    for o in range(w.size):
        if w[o] > m:
            m = w[o]
            best = o
    if not np.isfinite(beta) or m == -np.inf:
        return best
    total = 0.0
    for o in range(w.size):
        total += math.exp(beta * (w[o] - m))
    acc = 0.0
    for o in range(w.size):
        acc += math.exp(beta * (w[o] - m))
        if u * total < acc:
            return o
    return best


@njit(cache=True)
def select_round(own, ptr, cl, earlier, blocked, stamp):
    """Reports of a round (positions 0..m-1 in scan order) whose move can be applied now with
    sequential-scan semantics: none of its touched clusters (``own[p]`` and the gated ``cl[ptr[p]:ptr[p+1]]``)
    is touched by an earlier report of the round, and no earlier report's possible new clusters gate
    it or vice versa (``earlier``, from :func:`earlier_dependency`). ``blocked[c] == stamp`` marks
    clusters touched earlier in this round."""
    m = own.size
    sel = np.zeros(m, dtype=np.bool_)
    for p in range(m):
        ok = not earlier[p] and blocked[own[p]] != stamp
        if ok:
            for e in range(ptr[p], ptr[p + 1]):
                if blocked[cl[e]] == stamp:
                    ok = False
                    break
        blocked[own[p]] = stamp
        for e in range(ptr[p], ptr[p + 1]):
            blocked[cl[e]] = stamp
        sel[p] = ok
    return sel


@njit(cache=True)
def round_options(sel, own, ptr, cl, own_gated):
    """Options of the selected positions of a round, in scan order: the gated clusters
    ``cl[ptr[p]:ptr[p+1]]`` (ascending ids, own cluster excluded) with the own cluster inserted at its
    place when ``own_gated[p]``. Returns (CSR ``o_ptr`` over the selected, cluster ids, is-own flags,
    round position per option)."""
    n_sel = 0
    n_opt = 0
    for p in range(sel.size):
        if sel[p]:
            n_sel += 1
            n_opt += ptr[p + 1] - ptr[p] + (1 if own_gated[p] else 0)
    o_ptr = np.zeros(n_sel + 1, np.int64)
    o_cl = np.empty(n_opt, np.int64)
    o_own = np.zeros(n_opt, np.bool_)
    o_pos = np.empty(n_opt, np.int64)
    t = 0
    k = 0
    for p in range(sel.size):
        if not sel[p]:
            continue
        pending = own_gated[p]
        for e in range(ptr[p], ptr[p + 1]):
            if pending and own[p] < cl[e]:
                o_cl[k], o_own[k], o_pos[k] = own[p], True, p
                k += 1
                pending = False
            o_cl[k], o_pos[k] = cl[e], p
            k += 1
        if pending:
            o_cl[k], o_own[k], o_pos[k] = own[p], True, p
            k += 1
        t += 1
        o_ptr[t] = k
    return o_ptr, o_cl, o_own, o_pos


@njit(cache=True)
def apply_moves(reps, opt_ptr, opt_cl, opt_delta, opt_ll, own_minus_ll, single_ll, u, beta,
                labels, cnt, P, h, q, ld, logL, free, istate, s_cache, s_kind, s_param,
                vinv, hv, qv, ldv):
    """Apply the moves of ``reps`` (report ids, scan order) one after another. Option o of report
    j = reps[t] (o in opt_ptr[t]..opt_ptr[t+1]) joins cluster ``opt_cl[o]`` (its own cluster when that is
    the id the report is in) with ln L of the joined cluster ``opt_ll[o]``; the last option is a new
    cluster with ln L = ``single_ll[j]``. ``own_minus_ll[t]`` is ln L(own \\ j) (unused for singletons).
    The clusters of different reports are disjoint, so each precomputed delta is still exact when its
    report's turn comes; ln S(n₋, K) vs ln S(n₋+1, K) uses the current n. ``istate`` = [n clusters,
    free-stack top, K]. Returns the change of ln p(Λ|Z) and the number of reports that moved."""
    K = istate[2]
    d_lp = 0.0
    moved = 0
    for t in range(reps.size):
        j = reps[t]
        own = labels[j]
        n = istate[0]
        n_minus = n - 1 if cnt[own] == 1 else n
        s_stay = log_s_cached(s_cache, s_kind, s_param, n_minus, K)
        s_new = log_s_cached(s_cache, s_kind, s_param, n_minus + 1, K)
        lo, hi = opt_ptr[t], opt_ptr[t + 1]
        w = move_log_weights(opt_delta[lo:hi], single_ll[j], s_stay, s_new)
        o = choose(w, beta, u[j])
        if o < hi - lo:
            target = opt_cl[lo + o]
            if target == own:
                continue
        else:
            target = -1
            if cnt[own] == 1:
                continue  # a singleton staying a singleton: nothing changes
        # leave the own cluster
        d_lp -= logL[own]
        if cnt[own] == 1:
            cnt[own] = 0
            free[istate[1]] = own
            istate[1] += 1
            istate[0] -= 1
        else:
            cnt[own] -= 1
            P[own] -= vinv[j]
            h[own] -= hv[j]
            q[own] -= qv[j]
            ld[own] -= ldv[j]
            logL[own] = own_minus_ll[t]
            d_lp += logL[own]
        # join the target or open a cluster
        if target < 0:
            istate[1] -= 1
            target = free[istate[1]]
            istate[0] += 1
            cnt[target] = 1
            P[target] = vinv[j]
            h[target] = hv[j]
            q[target] = qv[j]
            ld[target] = ldv[j]
            logL[target] = single_ll[j]
            d_lp += single_ll[j]
        else:
            d_lp -= logL[target]
            cnt[target] += 1
            P[target] += vinv[j]
            h[target] += hv[j]
            q[target] += qv[j]
            ld[target] += ldv[j]
            logL[target] = opt_ll[lo + o]
            d_lp += logL[target]
        labels[j] = target
        d_lp += log_s_cached(s_cache, s_kind, s_param, istate[0], K) - log_s_cached(s_cache, s_kind, s_param, n, K)
        moved += 1
    return d_lp, moved


@njit(cache=True)
def _d2(rx: float, ry: float, s00: float, s01: float, s11: float) -> float:
    """d² = rᵀ S⁻¹ r of a 2-D offset r under a symmetric 2×2 S."""
    det = s00 * s11 - s01 * s01
    return (s11 * rx * rx - 2.0 * s01 * rx * ry + s00 * ry * ry) / det


@njit(cache=True)
def _info_gaussian(p00: float, p01: float, p11: float, h0: float, h1: float):
    """(b, B) of information sums (P, h): B = P⁻¹, b = B h, as (b0, b1, B00, B01, B11)."""
    det = p00 * p11 - p01 * p01
    B00, B01, B11 = p11 / det, -p01 / det, p00 / det
    return B00 * h0 + B01 * h1, B01 * h0 + B11 * h1, B00, B01, B11


@njit(cache=True)
def info_gaussians(P, h):
    """(b (n,2) m, B (n,2,2) m², det P (n,) per m⁴) of information sums P (n,2,2) per m², h (n,2) per m,
    by :func:`_info_gaussian` (the off-diagonal of P taken as the mean of its two entries)."""
    n = P.shape[0]
    b = np.empty((n, 2))
    B = np.empty((n, 2, 2))
    det = np.empty(n)
    for i in range(n):
        p00, p01, p11 = P[i, 0, 0], 0.5 * (P[i, 0, 1] + P[i, 1, 0]), P[i, 1, 1]
        b[i, 0], b[i, 1], B[i, 0, 0], B[i, 0, 1], B[i, 1, 1] = _info_gaussian(p00, p01, p11, h[i, 0], h[i, 1])
        B[i, 1, 0] = B[i, 0, 1]
        det[i] = p00 * p11 - p01 * p01
    return b, B, det


@njit(cache=True)
def own_without(reps, own, cnt, P, h, vinv, hv, zc, V, gamma):
    """Per round position p whose own cluster has other members (``multi``): the Gaussian (b, B) of
    the own cluster without report ``reps[p]`` (:func:`info_gaussians` of P − V⁻¹, h − V⁻¹z) and
    whether it gates the report (d² of z − b under B + V ≤ γ). Returns (multi (m,), positions of
    multi, b, B (as in :func:`info_gaussians`), own_gated (m,))."""
    m = reps.size
    multi = np.zeros(m, np.bool_)
    for p in range(m):
        multi[p] = cnt[own[p]] > 1
    mi = np.flatnonzero(multi)
    Pm = np.empty((mi.size, 2, 2))
    hm = np.empty((mi.size, 2))
    for t in range(mi.size):
        c, j = own[mi[t]], reps[mi[t]]
        for a in range(2):
            hm[t, a] = h[c, a] - hv[j, a]
            for e in range(2):
                Pm[t, a, e] = P[c, a, e] - vinv[j, a, e]
    bm, Bm, _ = info_gaussians(Pm, hm)
    own_gated = np.zeros(m, np.bool_)
    for t in range(mi.size):
        p = mi[t]
        own_gated[p] = _d2(zc[p, 0] - bm[t, 0], zc[p, 1] - bm[t, 1], Bm[t, 0, 0] + V[p, 0, 0],
                           Bm[t, 0, 1] + V[p, 0, 1], Bm[t, 1, 1] + V[p, 1, 1]) <= gamma
    return multi, mi, bm, Bm, own_gated


@njit(cache=True)
def _mark(owner, bx, by, B00, B01, B11, zc, V, lam_v_max, gamma, lo, cell, nx, ny, start, members, earlier) -> None:
    """Mark the gate links of one possible new cluster (mean b, covariance B) of round position ``owner``
    with the round's reports q (d² of z_q − b under B + V_q ≤ γ): the later of the two has an earlier
    dependency."""
    lam_b = 0.5 * (B00 + B11) + math.sqrt(0.25 * (B00 - B11) ** 2 + B01 * B01)
    reach = math.sqrt(gamma * (lam_b + lam_v_max)) * (1.0 + 1e-6)
    x0 = min(max(int(math.floor((bx - reach - lo[0]) / cell)), 0), nx - 1)
    x1 = min(max(int(math.floor((bx + reach - lo[0]) / cell)), 0), nx - 1)
    y0 = min(max(int(math.floor((by - reach - lo[1]) / cell)), 0), ny - 1)
    y1 = min(max(int(math.floor((by + reach - lo[1]) / cell)), 0), ny - 1)
    g = gamma * (1.0 + 1e-9) + 1e-9  # conservative: an extra link only delays a report to a later round
    for iy in range(y0, y1 + 1):
        for ix in range(x0, x1 + 1):
            k = iy * nx + ix
            for e in range(start[k], start[k + 1]):
                q = members[e]
                if q == owner:
                    continue
                if _d2(zc[q, 0] - bx, zc[q, 1] - by, B00 + V[q, 0, 0], B01 + V[q, 0, 1], B11 + V[q, 1, 1]) <= g:
                    earlier[max(q, owner)] = True


@njit(cache=True)
def earlier_dependency(zc, V, lam_v, gamma, multi_pos, bm, Bm, pair_pos, pair_cl, P, h, reps, vinv, hv):
    """Per round position p (scan order): True when a possible new cluster of an earlier position gates
    p's report, or one of p's gates an earlier report. The possible new clusters of position a are
    {a} (z_a, V_a), its own cluster without it (``bm``/``Bm`` at ``multi_pos``), and each gated cluster
    C with it (information sums P[C] + V⁻¹, h[C] + V⁻¹z of report ``reps[a]``, for the (``pair_pos``,
    ``pair_cl``) pairs). Positions in m relative to the chain's origin. The same links as gating every
    possible new cluster against the round's reports, without forming the pairs."""
    m = zc.shape[0]
    earlier = np.zeros(m, dtype=np.bool_)
    if m == 0:
        return earlier
    lo = np.array([zc[:, 0].min(), zc[:, 1].min()])
    span_x = zc[:, 0].max() - lo[0]
    span_y = zc[:, 1].max() - lo[1]
    lam_v_max = lam_v.max()
    cell = max(math.sqrt(gamma * 2.0 * lam_v_max), math.sqrt(max(span_x * span_y, 1e-18) / (4.0 * m)), 1e-9)
    nx = int(span_x / cell) + 1
    ny = int(span_y / cell) + 1
    key = np.empty(m, np.int64)
    for q in range(m):
        ix = min(int((zc[q, 0] - lo[0]) / cell), nx - 1)
        iy = min(int((zc[q, 1] - lo[1]) / cell), ny - 1)
        key[q] = iy * nx + ix
    members, start = counting_order(key, nx * ny)
    n_multi = multi_pos.size
    for t in range(m + n_multi + pair_pos.size):
        if t < m:
            a = t
            bx, by, B00, B01, B11 = zc[a, 0], zc[a, 1], V[a, 0, 0], V[a, 0, 1], V[a, 1, 1]
        elif t < m + n_multi:
            u = t - m
            a = multi_pos[u]
            bx, by, B00, B01, B11 = bm[u, 0], bm[u, 1], Bm[u, 0, 0], Bm[u, 0, 1], Bm[u, 1, 1]
        else:
            u = t - m - n_multi
            a, c = pair_pos[u], pair_cl[u]
            j = reps[a]
            bx, by, B00, B01, B11 = _info_gaussian(
                P[c, 0, 0] + vinv[j, 0, 0], 0.5 * (P[c, 0, 1] + P[c, 1, 0] + vinv[j, 0, 1] + vinv[j, 1, 0]),
                P[c, 1, 1] + vinv[j, 1, 1], h[c, 0] + hv[j, 0], h[c, 1] + hv[j, 1])
        _mark(a, bx, by, B00, B01, B11, zc, V, lam_v_max, gamma, lo, cell, nx, ny, start, members, earlier)
    return earlier
