"""Numba kernels of the batch associator (:mod:`tracker.association.batch`): round selection and the
sequential application of precomputed collapsed-Gibbs moves.

The cluster state lives in flat arrays indexed by cluster id (capacity K): ``cnt`` reports per cluster,
the information sums ``P`` = Σ V⁻¹ (per m², stored as P00, P01, P11), ``h`` = Σ V⁻¹z (per m),
``q`` = Σ zᵀV⁻¹z, ``ld`` = Σ ln det V (ln m⁴), and ``logL`` the cluster's ln L_C. Free ids are a stack.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

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
def select_round(touched_ptr, touched_cl, dep_ptr, dep_pos, blocked, stamp):
    """Reports of a round (positions 0..m-1 in scan order) whose move can be applied now with
    sequential-scan semantics: none of its touched clusters (own and gated) is touched by an earlier
    report of the round, and no earlier report's possible new clusters gate it or vice versa
    (``dep_pos`` lists, per position, the positions it depends on). ``blocked[c] == stamp`` marks
    clusters touched earlier in this round."""
    m = touched_ptr.size - 1
    sel = np.zeros(m, dtype=np.bool_)
    for p in range(m):
        ok = True
        for e in range(dep_ptr[p], dep_ptr[p + 1]):
            if dep_pos[e] < p:
                ok = False
                break
        if ok:
            for e in range(touched_ptr[p], touched_ptr[p + 1]):
                if blocked[touched_cl[e]] == stamp:
                    ok = False
                    break
        for e in range(touched_ptr[p], touched_ptr[p + 1]):
            blocked[touched_cl[e]] = stamp
        sel[p] = ok
    return sel


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
