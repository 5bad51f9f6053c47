"""Numba kernels of the tracker's block walk: the sequential decisions of paper 1, Fig. 3, over a block
of reports whose gated pairs were scored in bulk (see :mod:`tracker.association.greedy`).

Block layout (all arrays, positions in metres, times in seconds):

* reports ``blk = (z (m,2), V (m,2,2), t (m,), log_unseen (m,), half_logdet_v (m,), conflicted (m,),
  assign (m,), order, starts, grid, scratch (m,))``: ``order`` sorts the block's reports by grid
  cell, those of cell c (= ix·ny + iy) are ``order[starts[c]:starts[c + 1]]``, ``grid`` = [x0, y0,
  cell, lam_v, nx, ny] (lam_v the largest report-covariance eigenvalue);
* pair pool ``pool = (p_h, p_score, p_mean, p_cov, p_logc, p_next, head)``: one linked list of scored
  (hypothesis, report) pairs per report, ``p_h = -1`` for a pair made stale by a later change;
* hypotheses ``hyp = (means, covs, log_c, counts, times, dirty, dirty_list, low, is_low)`` with spare
  capacity; ``low`` lists the hypotheses whose ln c may lie below ``fstate[0]`` (checked one by one by
  the gate bound), every other hypothesis has ln c >= ``fstate[0]``;
* ``istate = [N̂_D, n_dirty, k, pool size, n_low]``, ``fstate = [ln c floor, γ needed when widening,
  a lower bound on ln c over the low list]``;
* ``cfg = (gamma, terrain_ratio, log_rmax, s_kind, s_param, motion, q, vel_std)``.

A report is decided here only if no earlier decision of the block touched a hypothesis of its gate
(``conflicted``) or one of its scored candidates (``dirty``); otherwise the walk stops and the caller
refreshes the pairs of the remaining reports against the hypotheses changed since the last refresh.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from tracker.association.cell_lists import relink
from tracker.gating.grid import counting_order
from tracker.models.motion import MOTION_CV, MOTION_STATIC, cv_cov_entry, cv_mean_entry
from tracker.models.sfunc import KIND_EXP, log_s_ratio_code

DONE, CONFLICT, WIDEN = 0, 1, 2
_LOG_2PI = math.log(2.0 * math.pi)


def no_grid() -> tuple:
    """A hypothesis grid that holds nothing, of the same types as a real one (``_HypothesisGrid.arrays``):
    :func:`walk` takes either, so numba compiles it once, not once per case."""
    return (np.zeros(0), *(np.zeros(0, np.int64) for _ in range(4)), np.zeros(0))


@njit(cache=True, inline="always")
def _pos_at(Hm, Hc, Ht, h, t, motion, q):
    """Position mean and covariance (x, y, c00, c01, c11) of hypothesis h predicted to time t (CV: entries
    of the one formula, :func:`tracker.models.motion.cv_cov_entry`; the tracker's states are 2-D, d = 2)."""
    if motion != MOTION_CV:
        return Hm[h, 0], Hm[h, 1], Hc[h, 0, 0], Hc[h, 0, 1], Hc[h, 1, 1]
    dt = t - Ht[h]
    x = cv_mean_entry(Hm, h, 0, dt, 2)
    y = cv_mean_entry(Hm, h, 1, dt, 2)
    c00 = cv_cov_entry(Hc, h, 0, 0, dt, q, 2)
    c01 = cv_cov_entry(Hc, h, 0, 1, dt, q, 2)
    c11 = cv_cov_entry(Hc, h, 1, 1, dt, q, 2)
    return x, y, c00, c01, c11


@njit(cache=True, inline="always")
def _in_gate(Hm, Hc, Ht, h, z, V, k, t, motion, q, gamma):
    """Whether hypothesis h (current state) gates report k at d² <= gamma."""
    x, y, c00, c01, c11 = _pos_at(Hm, Hc, Ht, h, t[k], motion, q)
    s00 = c00 + V[k, 0, 0]
    s01 = c01 + V[k, 0, 1]
    s11 = c11 + V[k, 1, 1]
    det = s00 * s11 - s01 * s01
    dx = z[k, 0] - x
    dy = z[k, 1] - y
    return (s11 * dx * dx - 2.0 * s01 * dx * dy + s00 * dy * dy) <= gamma * det


@njit(cache=True, inline="always")
def _lam_max(c00, c01, c11):
    """Largest eigenvalue of a symmetric 2x2 matrix, rounded up a little."""
    m = 0.5 * (c00 + c11)
    return (m + math.sqrt(0.25 * (c00 - c11) ** 2 + c01 * c01)) * (1.0 + 1e-9)


@njit(cache=True, inline="always")
def _innovation(a0, a1, A00, A01, A10, A11, z, V, k):
    """ln G(z_k; a, A + V_k) of a position mean a and covariance A, with the entries (i00, i01, i11) of
    (A + V_k)⁻¹ and the residual (r0, r1) = z_k - a that the Kalman update needs. The one formula of
    the score: :func:`_pair_geom` and :func:`_static_log_g` give bit-identical ln G."""
    s00 = A00 + V[k, 0, 0]
    s01 = 0.5 * (A01 + A10) + V[k, 0, 1]
    s11 = A11 + V[k, 1, 1]
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    r0 = z[k, 0] - a0
    r1 = z[k, 1] - a1
    maha = r0 * (i00 * r0 + i01 * r1) + r1 * (i01 * r0 + i11 * r1)
    return -0.5 * (maha + math.log(det)) - _LOG_2PI, i00, i01, i11, r0, r1


@njit(cache=True, inline="always")
def _static_log_g(h, k, z, V, Hm, Hc):
    """ln G(z_k; a_h, A_h + V_k) of static hypothesis h: the score of :func:`_pair_geom` without the
    Gaussian product (needed only for the chosen hypothesis)."""
    return _innovation(Hm[h, 0], Hm[h, 1], Hc[h, 0, 0], Hc[h, 0, 1], Hc[h, 1, 0], Hc[h, 1, 1], z, V, k)[0]


@njit(cache=True, inline="always")
def _pair_geom(h, k, blk, hyp, cfg, out_m, out_c, out_pm, out_pc):
    """Kalman step of hypothesis h (current state) to report k: prediction to t_k (constant velocity),
    then the position update. Writes the posterior state/covariance into out_m (D,), out_c (D, D) and
    the predicted position mean/covariance into out_pm (2,), out_pc (2, 2); returns
    ln G(z_k; H a', H A' Hᵀ + V_k). Static: this is the Gaussian product of paper 1, eq. 15."""
    z, V, t = blk[0], blk[1], blk[2]
    Hm, Hc, Ht = hyp[0], hyp[1], hyp[4]
    motion, q = cfg[5], cfg[6]
    D = Hm.shape[1]
    if motion == MOTION_CV:
        dt = t[k] - Ht[h]
        d = D // 2
        a = np.empty(D)
        A = np.empty((D, D))
        for r in range(D):
            a[r] = cv_mean_entry(Hm, h, r, dt, d)
            for c in range(D):
                A[r, c] = cv_cov_entry(Hc, h, r, c, dt, q, d)
    else:
        a = Hm[h].copy()
        A = Hc[h].copy()
    log_g, i00, i01, i11, r0, r1 = _innovation(a[0], a[1], A[0, 0], A[0, 1], A[1, 0], A[1, 1], z, V, k)
    for i in range(2):
        out_pm[i] = a[i]
        for c in range(2):
            out_pc[i, c] = A[i, c]
    # K = A[:, :2] S⁻¹; posterior a + K r, A - K A[:2, :].
    for i in range(D):
        k0 = A[i, 0] * i00 + A[i, 1] * i01
        k1 = A[i, 0] * i01 + A[i, 1] * i11
        out_m[i] = a[i] + k0 * r0 + k1 * r1
        for c in range(D):
            out_c[i, c] = A[i, c] - (k0 * A[0, c] + k1 * A[1, c])
    for i in range(D):
        for c in range(i + 1, D):
            v = 0.5 * (out_c[i, c] + out_c[c, i])
            out_c[i, c] = v
            out_c[c, i] = v
    return log_g


@njit(cache=True, inline="always")
def _pair_outputs(n, D):
    """ln G (n,), posterior means (n, D) and covariances (n, D, D), predicted position means (n, 2) and
    covariances (n, 2, 2) of n pairs, to be filled."""
    return np.empty(n), np.empty((n, D)), np.empty((n, D, D)), np.empty((n, 2)), np.empty((n, 2, 2))


@njit(cache=True)
def pair_geometry(rep, h, blk, hyp, cfg):
    """Vectorised :func:`_pair_geom` over pairs (report rep[i], hypothesis h[i]): returns
    (ln G, posterior means, posterior covariances, predicted position means, predicted position covs)."""
    log_g, post_m, post_c, pred_m, pred_c = _pair_outputs(rep.shape[0], hyp[0].shape[1])
    for i in range(rep.shape[0]):
        log_g[i] = _pair_geom(h[i], rep[i], blk, hyp, cfg, post_m[i], post_c[i], pred_m[i], pred_c[i])
    return log_g, post_m, post_c, pred_m, pred_c


@njit(cache=True)
def needed_pairs(log_g, log_c_all, h, rep, log_unseen, log_rmax, tau, post_m, post_c):
    """TT with S = e^{-nτ}, static hypotheses: ln c of each pair's hypothesis, the pairs whose bound
    (ln G - ln c) + ln r_max reaches ln ∫G(z,V)r - τ (:meth:`~tracker.association.greedy.Tracker._needs_integral`,
    the same operations in the same order), their count, and their posterior position means (k, 2) and
    covariances (k, 2, 2), contiguous for the integrator: the numpy gathers of ``Tracker._score`` in one pass."""
    n = h.shape[0]
    log_c = np.empty(n)
    need = np.empty(n, dtype=np.bool_)
    k = 0
    for p in range(n):
        lc = log_c_all[h[p]]
        log_c[p] = lc
        need[p] = (log_g[p] - lc) + log_rmax >= log_unseen[rep[p]] - tau
        k += need[p]
    means = np.empty((k, 2))
    covs = np.empty((k, 2, 2))
    q = 0
    for p in range(n):
        if need[p]:
            means[q, 0] = post_m[p, 0]
            means[q, 1] = post_m[p, 1]
            covs[q, 0, 0] = post_c[p, 0, 0]
            covs[q, 0, 1] = post_c[p, 0, 1]
            covs[q, 1, 0] = post_c[p, 1, 0]
            covs[q, 1, 1] = post_c[p, 1, 1]
            q += 1
    return log_c, need, k, means, covs


@njit(cache=True)
def pair_scores(log_g, log_c, need, log_needed):
    """Scores (ln G + ln ∫G r) - ln c of the needed pairs whose ln ∫G r (``log_needed``, in pair order) is
    finite, -inf for the others, and ln ∫G r per pair (0 where not needed), as ``Tracker._score`` computes them."""
    n = log_g.shape[0]
    score = np.full(n, -np.inf)
    log_i = np.zeros(n)
    q = 0
    for p in range(n):
        if need[p]:
            li = log_needed[q]
            q += 1
            log_i[p] = li
            if np.isfinite(li):
                score[p] = log_g[p] + li - log_c[p]
    return score, log_i


@njit(cache=True, parallel=True)
def pair_geometry_parallel(rep, h, blk, hyp, cfg):
    """:func:`pair_geometry` with the pairs shared among numba's threads (the same numbers: each pair is
    its own :func:`_pair_geom`); for a block's pairs, not for a refresh's few."""
    log_g, post_m, post_c, pred_m, pred_c = _pair_outputs(rep.shape[0], hyp[0].shape[1])
    for i in prange(rep.shape[0]):
        log_g[i] = _pair_geom(h[i], rep[i], blk, hyp, cfg, post_m[i], post_c[i], pred_m[i], pred_c[i])
    return log_g, post_m, post_c, pred_m, pred_c


@njit(cache=True)
def half_log_det(V):
    """½ ln det V_k of 2x2 covariances V (m, 2, 2) (m², so the result is in ln m), from the determinant's
    formula: it only enters the gate bound of :func:`_choose`, where numpy's batched ``slogdet`` cost
    ~0.1 µs per report."""
    out = np.empty(V.shape[0])
    for k in range(V.shape[0]):
        out[k] = 0.5 * math.log(V[k, 0, 0] * V[k, 1, 1] - V[k, 0, 1] * V[k, 1, 0])
    return out


REPORT_CELLS = 16
"""Cells of a block's report grid per report at most (at least 65,536): the cell grows past √(2γλ)
on blocks spread far wider than their reports' covariances."""


@njit(cache=True)
def build_report_grid(z, V, gamma):
    """Sort the block's reports into square cells: returns (order, starts, grid) (see module doc)."""
    m = z.shape[0]
    lam_v = 0.0
    for k in range(m):
        lam_v = max(lam_v, _lam_max(V[k, 0, 0], V[k, 0, 1], V[k, 1, 1]))
    x0 = np.min(z[:, 0]) if m else 0.0
    y0 = np.min(z[:, 1]) if m else 0.0
    wx = np.max(z[:, 0]) - x0 if m else 0.0
    wy = np.max(z[:, 1]) - y0 if m else 0.0
    cell = max(math.sqrt(gamma * 2.0 * lam_v), 1e-3)
    max_cells = max(REPORT_CELLS * m, 65536)
    if (wx / cell + 1.0) * (wy / cell + 1.0) > max_cells:
        cell = max(cell, (wx + wy) / math.sqrt(max_cells) + 1e-3)
    nx = int(wx / cell) + 1
    ny = int(wy / cell) + 1
    keys = np.empty(m, np.int64)
    for k in range(m):
        keys[k] = int((z[k, 0] - x0) / cell) * ny + int((z[k, 1] - y0) / cell)
    order, starts = counting_order(keys, nx * ny)  # the order a stable argsort of the keys gives
    grid = np.array([x0, y0, cell, lam_v, float(nx), float(ny)])
    return order, starts, grid


@njit(cache=True, inline="always")
def _gated_reports(h, after, blk, hyp, cfg, out):
    """Reports k > after of the block in the gate of hypothesis h (current state), into ``out``;
    returns their number. Static: a grid query with radius √(γ(λ_max(A_h) + lam_v)), which contains
    every gated report. Constant velocity: a scan of the later reports."""
    z, V, t = blk[0], blk[1], blk[2]
    order, starts, grid = blk[7], blk[8], blk[9]
    Hm, Hc, Ht = hyp[0], hyp[1], hyp[4]
    gamma, motion, q = cfg[0], cfg[5], cfg[6]
    n = 0
    if motion == MOTION_CV:
        for k in range(after + 1, z.shape[0]):
            if _in_gate(Hm, Hc, Ht, h, z, V, k, t, motion, q, gamma):
                out[n] = k
                n += 1
        return n
    x0, y0, cell, lam_v = grid[0], grid[1], grid[2], grid[3]
    nx, ny = int(grid[4]), int(grid[5])
    radius = math.sqrt(gamma * (_lam_max(Hc[h, 0, 0], Hc[h, 0, 1], Hc[h, 1, 1]) + lam_v)) * (1.0 + 1e-9)
    cx0 = max(0, int(math.floor((Hm[h, 0] - radius - x0) / cell)))
    cx1 = min(nx - 1, int(math.floor((Hm[h, 0] + radius - x0) / cell)))
    cy0 = max(0, int(math.floor((Hm[h, 1] - radius - y0) / cell)))
    cy1 = min(ny - 1, int(math.floor((Hm[h, 1] + radius - y0) / cell)))
    if cy0 > cy1:  # off the block's rows (cx0 > cx1 leaves the loop empty)
        return 0
    for cx in range(cx0, cx1 + 1):
        for i in range(starts[cx * ny + cy0], starts[cx * ny + cy1 + 1]):
            k = order[i]
            if k > after and _in_gate(Hm, Hc, Ht, h, z, V, k, t, motion, q, gamma):
                out[n] = k
                n += 1
    return n


@njit(cache=True, inline="always")
def _choose(j, cand, nc, c_h, c_score, check_gate, blk, hyp, istate, fstate, cfg):
    """Fig. 3's choice for report j among candidate pairs ``cand[:nc]`` (indices into c_h, c_score):
    returns (DONE, the chosen pair or -1 for a new hypothesis), or (WIDEN, -1) when the gate bound fails."""
    z, V, t, log_unseen, half_logdet_v = blk[0], blk[1], blk[2], blk[3], blk[4]
    Hm, Hc, Hlogc, Ht, low = hyp[0], hyp[1], hyp[2], hyp[4], hyp[7]
    gamma, terrain_ratio, log_rmax, s_kind, s_param, motion, q = cfg[0], cfg[1], cfg[2], cfg[3], cfg[4], cfg[5], cfg[6]
    n = istate[0]
    best = -np.inf
    arg = -1
    for i in range(nc):
        p = cand[i]
        # Highest score; ties go to the lowest hypothesis index (the candidates come in any order).
        if c_score[p] > best or (arg >= 0 and c_score[p] == best and c_h[p] < c_h[arg]):
            best = c_score[p]
            arg = p
    unseen = log_unseen[j] + log_s_ratio_code(s_kind, s_param, n, istate[2] + 1)
    # TT with motion: the predicted normalisers c'_q are not bounded, so the bound proves nothing
    # there and the gate is the plain χ² gate (no widening).
    if check_gate and n > 0 and not (terrain_ratio and motion == MOTION_CV):
        # Out of the gate, score_q < -d²/2 - ln(2π√det V) + (ln r_max - ln c_q for TT): bound it with
        # d² > γ and ln c_q >= fstate[0] for most hypotheses, exactly for the listed low-c ones.
        base = -_LOG_2PI - half_logdet_v[j]
        top = max(best, unseen)
        need = 0.0
        glob = base
        # The low list one by one only when its least ln c could break the bound (d² > γ there too).
        if terrain_ratio:
            glob = base + log_rmax - fstate[0]
            for i in range(istate[4] if base - 0.5 * gamma + log_rmax - fstate[2] > top else 0):
                h = low[i]
                x, y, c00, c01, c11 = _pos_at(Hm, Hc, Ht, h, t[j], motion, q)
                s00, s01, s11 = c00 + V[j, 0, 0], c01 + V[j, 0, 1], c11 + V[j, 1, 1]
                dx, dy = z[j, 0] - x, z[j, 1] - y
                d2 = (s11 * dx * dx - 2.0 * s01 * dx * dy + s00 * dy * dy) / (s00 * s11 - s01 * s01)
                if d2 > gamma and base - 0.5 * d2 + log_rmax - Hlogc[h] > top:
                    need = max(need, d2)
        if glob - 0.5 * gamma > top:
            need = max(need, 2.0 * (glob - top))
        if need > 0.0:
            fstate[1] = need * (1.0 + 1e-12) + 1e-9
            return WIDEN, -1
    if arg < 0 or unseen > best:
        return DONE, -1
    return DONE, arg


@njit(cache=True, inline="always")
def _apply(j, h, c_mean, c_cov, p, log_c, mark, blk, hyp, istate, fstate, cfg):
    """The estimation step of report j: a new hypothesis (h = -1) from the report, else hypothesis h
    becomes the posterior of candidate p (c_mean[p] (D,), c_cov[p] (D, D), ln c). ``mark``: flag the later reports of the block
    in the changed hypothesis's gate as conflicted (block walk)."""
    z, V, t, log_unseen, conflicted, assign = blk[0], blk[1], blk[2], blk[3], blk[5], blk[6]
    Hm, Hc, Hlogc, Hcount, Ht, dirty, dirty_list, low, is_low = hyp
    motion, vel_std = cfg[5], cfg[7]
    D = Hm.shape[1]
    if h < 0:
        h = istate[0]
        for a in range(D):
            Hm[h, a] = 0.0
            for b in range(D):
                Hc[h, a, b] = 0.0
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
        istate[0] = h + 1
    else:
        for a in range(D):
            Hm[h, a] = c_mean[p, a]
            for b in range(D):
                Hc[h, a, b] = c_cov[p, a, b]
        Hlogc[h] = log_c
        Hcount[h] += 1
    Ht[h] = t[j]
    if Hlogc[h] < fstate[0] and not is_low[h]:
        low[istate[4]] = h
        is_low[h] = True
        istate[4] += 1
    if is_low[h]:
        fstate[2] = min(fstate[2], Hlogc[h])
    if not dirty[h]:
        dirty[h] = True
        dirty_list[istate[1]] = h
        istate[1] += 1
    if mark:
        buf = blk[10]
        for i in range(_gated_reports(h, j, blk, hyp, cfg, buf)):
            conflicted[buf[i]] = True
    istate[2] += 1
    assign[j] = h


@njit(cache=True, inline="always")
def decide(j, cand, nc, c_h, c_score, c_mean, c_cov, c_logc, check_gate, blk, hyp, istate, fstate, cfg, mark=True):
    """Decide report j among candidate pairs ``cand[:nc]`` (indices into the c_* arrays) and apply the
    estimation step; returns DONE, or WIDEN when the gate bound fails (nothing changed then). ``mark``:
    flag the later reports of the block in the changed hypothesis's gate as conflicted (block walk)."""
    status, arg = _choose(j, cand, nc, c_h, c_score, check_gate, blk, hyp, istate, fstate, cfg)
    if status != DONE:
        return status
    if arg < 0:
        _apply(j, -1, c_mean, c_cov, 0, 0.0, mark, blk, hyp, istate, fstate, cfg)
    else:
        _apply(j, c_h[arg], c_mean, c_cov, arg, c_logc[arg], mark, blk, hyp, istate, fstate, cfg)
    return DONE


@njit(cache=True)
def _decide_now(j, nc, blk, pool, hyp, istate, fstate, cfg):
    """Decide a conflicted report without leaving numba when no new integral is needed: the unchanged
    pairs of its list plus the changed hypotheses now in its gate, scored from the current state.
    UU/UT scores need no integral. TT (static): a changed hypothesis whose bound
    ln G + ln r_max - ln c_q (∫G(b,B) r <= r_max) is below previouslyUnseen can neither be chosen nor
    beat previouslyUnseen, so it needs no integral either; otherwise return CONFLICT, changing nothing."""
    p_h, p_score, p_mean, p_cov, p_logc, p_next, head = pool
    Hm, Hc, Hlogc, Ht, dirty, dirty_list = hyp[0], hyp[1], hyp[2], hyp[4], hyp[5], hyp[6]
    z, V, t = blk[0], blk[1], blk[2]
    gamma, motion, q = cfg[0], cfg[5], cfg[6]
    D = Hm.shape[1]
    n_fresh = 0
    for i in range(istate[1]):
        if _in_gate(Hm, Hc, Ht, dirty_list[i], z, V, j, t, motion, q, gamma):
            n_fresh += 1
    total = nc + n_fresh
    c_h = np.empty(total, np.int64)
    c_score = np.empty(total)
    c_mean = np.empty((total, D))
    c_cov = np.empty((total, D, D))
    c_logc = np.full(total, blk[3][j])  # UU/UT: ln u; TT fresh candidates here are never chosen
    pm = np.empty(2)
    pc = np.empty((2, 2))
    c = 0
    p = head[j]
    while p >= 0:
        if p_h[p] >= 0 and not dirty[p_h[p]]:
            c_h[c] = p_h[p]
            c_score[c] = p_score[p]
            c_mean[c] = p_mean[p]
            c_cov[c] = p_cov[p]
            c_logc[c] = p_logc[p]
            c += 1
        p = p_next[p]
    terrain, log_rmax, s_kind, s_param = cfg[1], cfg[2], cfg[3], cfg[4]
    if terrain and motion == MOTION_CV and n_fresh:
        return CONFLICT  # the predicted normaliser c'_q needs an integral
    unseen = blk[3][j] + log_s_ratio_code(s_kind, s_param, istate[0], istate[2] + 1)
    for i in range(istate[1]):
        h = dirty_list[i]
        if _in_gate(Hm, Hc, Ht, h, z, V, j, t, motion, q, gamma):
            c_h[c] = h
            log_g = _pair_geom(h, j, blk, hyp, cfg, c_mean[c], c_cov[c], pm, pc)
            if terrain:
                if log_g + log_rmax - Hlogc[h] >= unseen:
                    return CONFLICT
                c_score[c] = -np.inf
            else:
                c_score[c] = log_g
            c += 1
    return decide(j, np.arange(total), total, c_h, c_score, c_mean, c_cov, c_logc, True, blk, hyp, istate, fstate, cfg)


@njit(cache=True)
def walk(start, blk, pool, hyp, istate, fstate, cfg, hgrid, widened):
    """Decide reports start.. until one conflicts with an earlier decision of the block or needs a
    wider gate that :func:`_widen_here` cannot settle; returns (that report, CONFLICT or WIDEN) or
    (m, DONE). ``hgrid``: the static hypotheses' grid, or :func:`no_grid`; ``widened[0]`` counts the
    gates widened here."""
    p_h, p_score, p_mean, p_cov, p_logc, p_next, head = pool
    dirty = hyp[5]
    conflicted = blk[5]
    m = blk[0].shape[0]
    for j in range(start, m):
        stale = conflicted[j]
        nc = 0
        p = head[j]
        while p >= 0:
            if p_h[p] >= 0:
                if dirty[p_h[p]]:
                    stale = True
                else:
                    nc += 1
            p = p_next[p]
        if stale:
            status = _decide_now(j, nc, blk, pool, hyp, istate, fstate, cfg)
            if status == WIDEN and _widen_here(j, blk, hyp, istate, fstate, cfg, hgrid):
                widened[0] += 1
            elif status != DONE:
                return j, status
            continue
        cand = np.empty(nc, np.int64)
        nc = 0
        p = head[j]
        while p >= 0:
            if p_h[p] >= 0:
                cand[nc] = p
                nc += 1
            p = p_next[p]
        status = decide(j, cand, nc, p_h, p_score, p_mean, p_cov, p_logc, True, blk, hyp, istate, fstate, cfg)
        if status == WIDEN and _widen_here(j, blk, hyp, istate, fstate, cfg, hgrid):
            widened[0] += 1
        elif status != DONE:
            return j, status
    return m, DONE


@njit(cache=True)
def _widen_here(j, blk, hyp, istate, fstate, cfg, hgrid):
    """Report j's decision in its widened gate (γ = ``fstate[1]``) without leaving numba, when no
    integral is needed: TT, static, S = e^{-nτ}, and every hypothesis in that gate below the bound
    (ln G - ln c) + ln r_max < ln ∫G(z,V)r - τ (``needed_pairs``' test, in its order of operations),
    so each scores -inf as ``Tracker._score`` would score it. Returns whether it decided."""
    if hgrid[0].shape[0] == 0:
        return False
    terrain, log_rmax, s_kind, tau = cfg[1], cfg[2], cfg[3], cfg[4]
    if not terrain or s_kind != KIND_EXP:
        return False
    Hm, Hc, Hlogc = hyp[0], hyp[1], hyp[2]
    cand = widened_gate(j, fstate[1], blk[0], blk[1], blk[2], Hm, Hc, hyp[4], istate[0], blk[6], hgrid)
    nc = cand.shape[0]
    D = Hm.shape[1]
    c_score = np.full(nc, -np.inf)
    c_mean = np.empty((nc, D))
    c_cov = np.empty((nc, D, D))
    c_logc = np.zeros(nc)
    pm = np.empty(2)
    pc = np.empty((2, 2))
    for i in range(nc):
        log_g = _pair_geom(cand[i], j, blk, hyp, cfg, c_mean[i], c_cov[i], pm, pc)
        if (log_g - Hlogc[cand[i]]) + log_rmax >= blk[3][j] - tau:
            return False  # an integral decides: Tracker._block takes it
    return decide(j, np.arange(nc), nc, cand, c_score, c_mean, c_cov, c_logc, False, blk, hyp, istate, fstate, cfg) == DONE


@njit(cache=True)
def fresh_pairs(j, blk, hyp, istate, cfg):
    """(report, hypothesis) pairs in the gate between reports j.. and the hypotheses changed since the
    last refresh (one grid query per changed hypothesis)."""
    dirty_list = hyp[6]
    buf = blk[10]
    cap = 2 * istate[1] + 16
    rep = np.empty(cap, np.int64)
    hyp_idx = np.empty(cap, np.int64)
    c = 0
    for i in range(istate[1]):
        n = _gated_reports(dirty_list[i], j - 1, blk, hyp, cfg, buf)
        if c + n > cap:
            cap = max(2 * cap, c + n)
            rep = np.concatenate((rep[:c], np.empty(cap - c, np.int64)))
            hyp_idx = np.concatenate((hyp_idx[:c], np.empty(cap - c, np.int64)))
        rep[c : c + n] = buf[:n]
        hyp_idx[c : c + n] = dirty_list[i]
        c += n
    return rep[:c], hyp_idx[:c]


@njit(cache=True)
def link_pairs(j, pool, istate, f_rep, f_h, f_score, f_mean, f_cov, f_logc, hyp, conflicted):
    """Retire the pairs of reports j.. whose hypothesis changed, add the fresh ones (the pool has room),
    and start a new refresh period (no dirty hypotheses, no conflicted reports)."""
    p_h, p_score, p_mean, p_cov, p_logc, p_next, head = pool
    dirty, dirty_list = hyp[5], hyp[6]
    for k in range(j, head.shape[0]):
        p = head[k]
        while p >= 0:
            if p_h[p] >= 0 and dirty[p_h[p]]:
                p_h[p] = -1
            p = p_next[p]
        conflicted[k] = False
    c = istate[3]
    for i in range(f_rep.shape[0]):
        p_h[c] = f_h[i]
        p_score[c] = f_score[i]
        p_mean[c] = f_mean[i]
        p_cov[c] = f_cov[i]
        p_logc[c] = f_logc[i]
        p_next[c] = head[f_rep[i]]
        head[f_rep[i]] = c
        c += 1
    istate[3] = c
    for i in range(istate[1]):
        dirty[dirty_list[i]] = False
    istate[1] = 0


# ----------------------------------------------------------------------------- the hypotheses' grid
# Static hypotheses kept in a uniform grid of square cells across the tracker's whole run (``hgrid =
# (geo, head, nxt, prv, cell_of, cell_lam)``, geo = [x0, y0, cell, nx, ny, lam_a, lam_wide]): a
# hypothesis is linked into the list of the cell holding its mean (positions outside the grid go to
# its border cells, so a clamped query still finds them), lam_a bounds the largest eigenvalue of every
# listed hypothesis covariance (m²) and cell_lam[c] that of every hypothesis ever placed in cell c (a
# query skips a cell too far from the report for any of them to gate it). A hypothesis wider than lam_wide goes to one extra list (head[nx·ny])
# that every query scans, so one huge hypothesis cannot widen every query. A block's gate is then one
# query per report instead of a structure rebuilt over all hypotheses per block.


@njit(cache=True, inline="always")
def _cell_index(v, v0, cell, n):
    """Cell of coordinate v (m) on an axis of n cells from v0, clamped to the grid (float first: no overflow)."""
    c = math.floor((v - v0) / cell)
    return int(min(max(c, 0.0), n - 1.0))


@njit(cache=True, inline="always")
def grid_place(idx, Hm, Hc, hgrid):
    """(Re)link hypotheses ``idx`` into the cell of their current mean (or the wide list) and raise lam_a
    and their cells' cell_lam to cover them."""
    geo, head, nxt, prv, cell_of, cell_lam = hgrid
    x0, y0, cell, nx, ny = geo[0], geo[1], geo[2], geo[3], geo[4]
    for i in range(idx.shape[0]):
        h = idx[i]
        lam = _lam_max(Hc[h, 0, 0], Hc[h, 0, 1], Hc[h, 1, 1])
        if lam > geo[6]:
            c = int(nx) * int(ny)  # the wide list
        else:
            geo[5] = max(geo[5], lam)
            c = _cell_index(Hm[h, 0], x0, cell, nx) * int(ny) + _cell_index(Hm[h, 1], y0, cell, ny)
            cell_lam[c] = max(cell_lam[c], lam)
        if cell_of[h] != c:
            relink(head, nxt, prv, cell_of, h, c)


@njit(cache=True, inline="always")
def _scan(h, k, z, V, gamma, Hm, Hc, nxt, out, n):
    """The hypotheses of the list starting at h that gate report k at d² <= gamma, into ``out`` from n
    on (as many as fit); returns the new count."""
    while h >= 0:
        s00 = Hc[h, 0, 0] + V[k, 0, 0]
        s01 = Hc[h, 0, 1] + V[k, 0, 1]
        s11 = Hc[h, 1, 1] + V[k, 1, 1]
        dx = z[k, 0] - Hm[h, 0]
        dy = z[k, 1] - Hm[h, 1]
        if (s11 * dx * dx - 2.0 * s01 * dx * dy + s00 * dy * dy) <= gamma * (s00 * s11 - s01 * s01):
            if n < out.shape[0]:
                out[n] = h
            n += 1
        h = nxt[h]
    return n


@njit(cache=True, inline="always")
def _query_square(k, z, V, gamma, geo):
    """λ_max(V_k) and the cells (cx0, cx1, cy0, cy1) of the square of half-side √(γ(λ_max(V_k) + lam_a))
    around report k (see :func:`_grid_query`)."""
    x0, y0, cell, nx, ny = geo[0], geo[1], geo[2], geo[3], geo[4]
    lam_v = _lam_max(V[k, 0, 0], V[k, 0, 1], V[k, 1, 1])
    radius = math.sqrt(gamma * (lam_v + geo[5])) * (1.0 + 1e-9)
    return (lam_v, _cell_index(z[k, 0] - radius, x0, cell, nx), _cell_index(z[k, 0] + radius, x0, cell, nx),
            _cell_index(z[k, 1] - radius, y0, cell, ny), _cell_index(z[k, 1] + radius, y0, cell, ny))


@njit(cache=True, inline="always")
def _grid_query(k, z, V, gamma, Hm, Hc, hgrid, out):
    """Hypotheses of the grid gating report k at d² <= gamma, into ``out`` (as many as fit: pass an empty
    one to count); returns their number. A gated mean a is within √(γ(λ_max(V_k) + λ_max(A))) of z,
    since d² >= |z - a|² / λ_max(A + V): the query square has that half-side with lam_a, and a cell in
    it is scanned only if its distance from z is within that reach with the cell's cell_lam (border
    cells reach to infinity outwards: they hold the hypotheses off the grid). The wide list is scanned
    whole."""
    geo, head, nxt, cell_lam = hgrid[0], hgrid[1], hgrid[2], hgrid[5]
    x0, y0, cell, nx, ny = geo[0], geo[1], geo[2], geo[3], geo[4]
    lam_v, cx0, cx1, cy0, cy1 = _query_square(k, z, V, gamma, geo)
    # z in cell units, as _cell_index computes them; the 1e-8 slack covers their rounding (~1e-16 relative)
    u = (z[k, 0] - x0) / cell
    w = (z[k, 1] - y0) / cell
    reach = gamma * (1.0 + 1e-8) / (cell * cell)
    n = _scan(head[int(nx) * int(ny)], k, z, V, gamma, Hm, Hc, nxt, out, 0)
    for cx in range(cx0, cx1 + 1):
        gx = max(cx - u if cx > 0 else 0.0, u - (cx + 1) if cx < nx - 1 else 0.0, 0.0)
        for cy in range(cy0, cy1 + 1):
            c = cx * int(ny) + cy
            h = head[c]
            if h >= 0:
                gy = max(cy - w if cy > 0 else 0.0, w - (cy + 1) if cy < ny - 1 else 0.0, 0.0)
                if gx * gx + gy * gy <= reach * (lam_v + cell_lam[c]):
                    n = _scan(h, k, z, V, gamma, Hm, Hc, nxt, out, n)
    return n


@njit(cache=True)
def widened_gate(j, gamma, z, V, t, Hm, Hc, Ht, n, assign, hgrid):
    """Static hypotheses h < n gating report j of a block at d² <= gamma (a widened gate), ascending:
    the grid's query, plus the hypotheses assigned to the block's reports before j, tested one by one
    (the grid places them at the block's end, so it may hold them at a cell they have left, or not
    at all). A query square of more cells than there are hypotheses tests all n instead."""
    _, cx0, cx1, cy0, cy1 = _query_square(j, z, V, gamma, hgrid[0])
    if (cx1 - cx0 + 1) * (cy1 - cy0 + 1) > n:
        out = np.empty(n, np.int64)
        c = 0
        for h in range(n):
            if _in_gate(Hm, Hc, Ht, h, z, V, j, t, MOTION_STATIC, 0.0, gamma):
                out[c] = h
                c += 1
        return out[:c]
    cnt = _grid_query(j, z, V, gamma, Hm, Hc, hgrid, np.empty(0, np.int64))
    out = np.empty(cnt + j, np.int64)
    _grid_query(j, z, V, gamma, Hm, Hc, hgrid, out)
    c = cnt
    for i in range(j):
        if assign[i] >= 0 and _in_gate(Hm, Hc, Ht, assign[i], z, V, j, t, MOTION_STATIC, 0.0, gamma):
            out[c] = assign[i]
            c += 1
    return np.unique(out[:c])


GATE_SLOTS = 8
"""Hypotheses per report that :func:`grid_gate`'s first pass keeps (the bench stream gates 2.5 on average)."""


@njit(cache=True, parallel=True)
def grid_gate(z, V, gamma, Hm, Hc, hgrid):
    """Gated pairs of reports (m, 2) / (m, 2, 2) against the grid's static hypotheses, CSR by report:
    (ptr (m+1,), hypothesis per pair, in ascending order within each report). Both passes are parallel
    over reports (the grid is only read). The first keeps up to GATE_SLOTS hypotheses per report, so
    the second queries again only the reports that gate more."""
    m = z.shape[0]
    count = np.zeros(m + 1, np.int64)
    slots = np.empty(m * GATE_SLOTS, np.int64)
    for k in prange(m):
        count[k + 1] = _grid_query(k, z, V, gamma, Hm, Hc, hgrid, slots[k * GATE_SLOTS : (k + 1) * GATE_SLOTS])
    ptr = np.cumsum(count)
    p_h = np.empty(ptr[m], np.int64)
    for k in prange(m):
        n = ptr[k + 1] - ptr[k]
        if n <= GATE_SLOTS:
            p_h[ptr[k] : ptr[k + 1]] = slots[k * GATE_SLOTS : k * GATE_SLOTS + n]
        else:
            _grid_query(k, z, V, gamma, Hm, Hc, hgrid, p_h[ptr[k] : ptr[k + 1]])
        p_h[ptr[k] : ptr[k + 1]].sort()
    return ptr, p_h


@njit(cache=True)
def walk_sequential(blk, hyp, istate, fstate, cfg, hgrid):
    """UU/UT, static: the block's reports decided one by one against the current hypotheses, each gated
    with the hypotheses' grid, which is updated after every decision. This is the sequential algorithm
    itself (nothing is scored ahead, so nothing goes stale); a failed gate bound re-queries the grid
    with the γ that makes it hold (the widening of the block walk). A candidate's score is ln G alone
    (:func:`_static_log_g`); the Gaussian product is computed for the chosen one only, by the same
    :func:`_pair_geom` as the block walk. Returns the number of widened gates."""
    z, V, log_unseen, assign = blk[0], blk[1], blk[3], blk[6]
    Hm, Hc = hyp[0], hyp[1]
    D = Hm.shape[1]
    c_h = np.empty(64, np.int64)
    c_score = np.empty(64)
    idx = np.arange(64)
    post_m = np.empty((1, D))
    post_c = np.empty((1, D, D))
    pm = np.empty(2)
    pc = np.empty((2, 2))
    one = np.empty(1, np.int64)
    widened = 0
    for j in range(z.shape[0]):
        gamma = cfg[0]
        check = True
        while True:
            nc = _grid_query(j, z, V, gamma, Hm, Hc, hgrid, c_h)
            if nc > c_h.shape[0]:
                c_h, c_score, idx = np.empty(2 * nc, np.int64), np.empty(2 * nc), np.arange(2 * nc)
                _grid_query(j, z, V, gamma, Hm, Hc, hgrid, c_h)
            for i in range(nc):
                c_score[i] = _static_log_g(c_h[i], j, z, V, Hm, Hc)
            status, arg = _choose(j, idx, nc, c_h, c_score, check, blk, hyp, istate, fstate, cfg)
            if status == DONE:
                break
            gamma = fstate[1]
            check = False
            widened += 1
        if arg < 0:
            _apply(j, -1, post_m, post_c, 0, 0.0, False, blk, hyp, istate, fstate, cfg)
        else:
            h = c_h[arg]
            _pair_geom(h, j, blk, hyp, cfg, post_m[0], post_c[0], pm, pc)
            _apply(j, h, post_m, post_c, 0, log_unseen[j], False, blk, hyp, istate, fstate, cfg)  # ln u
        one[0] = assign[j]
        grid_place(one, Hm, Hc, hgrid)
    return widened


@njit(cache=True)
def least_k(values, k):
    """Indices of the ``k`` least of ``values`` (ascending index order; ties with the (k+1)-th least
    taken by a max-heap's pass, any of them) and the least value of the others (+inf if none): what
    ``np.argpartition(values, k)`` gives, in one pass with a bounded heap. On a TT stream's block of
    100,000 ln c, many of them tied, introselect took 2.7 ms against 0.16 ms; on distinct random
    values both take ~0.1 ms at k = 256. ``values`` without NaN (ln c may be -inf); 0 < k <= values.size."""
    heap = np.empty(k, np.int64)  # a max-heap on values[heap]
    size = 0
    floor = np.inf
    for i in range(values.shape[0]):
        x = values[i]
        if size < k:  # sift up
            c = size
            size += 1
            while c > 0:
                p = (c - 1) // 2
                if values[heap[p]] >= x:
                    break
                heap[c] = heap[p]
                c = p
            heap[c] = i
            continue
        top = values[heap[0]]
        if x >= top:
            if x < floor:
                floor = x
            continue
        if top < floor:
            floor = top
        c = 0  # the root replaced by i, sifted down
        while True:
            left = 2 * c + 1
            if left >= k:
                break
            big = left
            if left + 1 < k and values[heap[left + 1]] > values[heap[left]]:
                big = left + 1
            if values[heap[big]] <= x:
                break
            heap[c] = heap[big]
            c = big
        heap[c] = i
    return np.sort(heap), floor
