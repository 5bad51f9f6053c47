"""Uniform-grid spatial hash (the coarse gate) fused with the exact per-pair test.

Points (one set, projected to a common time) are bucketed by their own radius contribution; each
bucket gets a grid of cubic cells (metres), sorted by linear cell key. Each query (the other set)
visits every cell its own radius can reach in every bucket, and runs the exact test on the points
found there. Work is O(n log n) to build plus O(cells visited + candidates) per query, parallel
over queries; nothing of size N_T x N_R is ever formed.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from tracker.gating.exact import RADIUS_SLACK, sym_d2_logdet
from tracker.gating.reach import projected_cov_entry

# Cells per axis are capped so that linear keys fit in int64 even in 3-D.
_MAX_AXIS_CELLS = 1 << 20
# A dense cell->start table is used while it has at most this many cells per point.
_DENSE_CELLS_PER_POINT = 8
# Work (queries + candidates scanned) per thread below which a parallel launch costs more than
# it saves (on a loaded machine a parallel region can wait tens of ms for a descheduled worker).
_WORK_PER_THREAD = 100_000
# Elements per thread of a gather (take_rows): a copy costs so little per element that a parallel
# launch pays off only for millions of them.
_GATHER_PER_THREAD = 1_000_000
# Runs of pairs of one track longer than this are merge-sorted instead of insertion-sorted.
_INSERTION_MAX = 32


@dataclass(frozen=True)
class Grid:
    """Bucketed grids over a point set (metres); bucket b owns slices [seg[b], seg[b+1])."""

    origin: np.ndarray     # (K, d) lower corner per bucket
    cell: np.ndarray       # (K,) cell edge per bucket
    dims: np.ndarray       # (K, d) int64 cells per axis
    seg: np.ndarray        # (K + 1,) offsets into keys / members
    keys: np.ndarray       # (n,) sorted linear cell keys, per bucket (zeros in dense buckets)
    members: np.ndarray    # (n,) global index of each sorted point
    dense: np.ndarray      # (K,) bool: bucket has a dense start table
    table_seg: np.ndarray  # (K + 1,) offsets into table
    table: np.ndarray      # concatenated cell-start tables (local offsets)


def build_grid(pos: np.ndarray, members: np.ndarray | None, bucket: np.ndarray, n_buckets: int,
               cell: np.ndarray) -> Grid:
    """Grid over points ``pos`` (n, d) with global ids ``members`` (None: their rows), bucket id
    per point and a preferred cell edge per bucket (enlarged when a dense table would need too
    many cells)."""
    dim = pos.shape[1]
    if n_buckets == 1:
        order, seg = np.arange(pos.shape[0]), np.array([0, pos.shape[0]], dtype=np.int64)
    else:
        order, seg = counting_order(bucket, n_buckets)
    origin = np.zeros((n_buckets, dim))
    cells = np.ones(n_buckets)
    dims = np.ones((n_buckets, dim), dtype=np.int64)
    dense = np.zeros(n_buckets, dtype=np.bool_)
    keys_all = np.zeros(pos.shape[0], dtype=np.int64)
    members_all = np.empty(pos.shape[0], dtype=np.int64)
    tables, table_seg = [], [0]
    for b in range(n_buckets):
        idx = order[seg[b]:seg[b + 1]]
        n = idx.size
        if n == 0:
            tables.append(np.zeros(0, dtype=np.int64))
            table_seg.append(table_seg[-1])
            continue
        p = pos if n_buckets == 1 else pos[idx]
        lo, hi = bounding_box(p)
        extent = hi - lo
        h = max(float(cell[b]), float(extent.max()) / _MAX_AXIS_CELLS, 1e-300)
        ncell = np.floor(extent / h).astype(np.int64) + 1
        budget = _DENSE_CELLS_PER_POINT * n + 64
        if np.prod(ncell.astype(float)) > budget:
            # A coarser grid with an O(1) start table beats binary search unless it is much coarser.
            h_dense = h
            while np.prod(np.floor(extent / h_dense) + 1) > budget:
                h_dense *= 1.25
            if h_dense <= 2.0 * h:
                h = h_dense
                ncell = np.floor(extent / h).astype(np.int64) + 1
        origin[b], cells[b], dims[b] = lo, h, ncell
        keys = cell_keys(p, lo, h, ncell)
        ntot = int(np.prod(ncell))
        dense[b] = ntot <= budget
        if dense[b]:
            o, start = counting_order(keys, ntot)
            tables.append(start)
        else:
            o = np.argsort(keys, kind="stable")
            tables.append(np.zeros(0, dtype=np.int64))
        if not dense[b]:  # a dense bucket is searched through its table alone
            keys_all[seg[b]:seg[b + 1]] = keys[o]
        rows = o if n_buckets == 1 else idx[o]
        members_all[seg[b]:seg[b + 1]] = rows if members is None else members[rows]
        table_seg.append(table_seg[-1] + tables[-1].size)
    return Grid(origin, cells, dims, seg, keys_all, members_all, dense,
                np.asarray(table_seg, dtype=np.int64),
                tables[0] if len(tables) == 1 else np.concatenate(tables))


@njit(cache=True)
def query_radii(s2_q, s2_b, u_q, u_b, g_q, g_b, coord_slack):
    """Coarse search radius (m) of each query in each bucket of the gridded set, (nq, K):
    (sqrt(max(g, 0) (s2_q + s2_b)) + u_q u_b) (1 + RADIUS_SLACK) + coord_slack with
    g = min(g_q, g_b) the pair's bound on gamma; -1 (skip the bucket) where g < 0 or the radius
    is not finite. s2: variances (m²) bounding λmax of each side, u_q u_b: the motion term (m)."""
    nq, nb = s2_q.shape[0], s2_b.shape[0]
    rad = np.empty((nq, nb))
    for i in range(nq):
        for b in range(nb):
            g = min(g_b[b], g_q[i])
            r = (math.sqrt(max(g, 0.0) * (s2_q[i] + s2_b[b])) + u_q[i] * u_b[b]) \
                * (1.0 + RADIUS_SLACK) + coord_slack
            rad[i, b] = r if g >= 0.0 and math.isfinite(r) else -1.0
    return rad


def take_rows(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """a[rows] for C-contiguous arrays of any rank (a flat gather; numpy's fancy indexing of
    3-D arrays is several times slower), on as many threads as its size warrants."""
    flat = np.ascontiguousarray(a).reshape(a.shape[0], int(np.prod(a.shape[1:])))
    with threads_for(rows.shape[0] * flat.shape[1], _GATHER_PER_THREAD):
        out = _take_rows(flat, rows)
    return out.reshape((rows.shape[0],) + a.shape[1:])


@njit(cache=True, parallel=True)
def _take_rows(a, rows):
    out = np.empty((rows.shape[0], a.shape[1]), a.dtype)
    for i in prange(rows.shape[0]):
        r = rows[i]
        for j in range(a.shape[1]):  # element by element: a row slice copy costs twice as much
            out[i, j] = a[r, j]
    return out


@njit(cache=True)
def bounding_box(pos):
    """Per-axis minimum and maximum of points (n, d), n > 0 (numpy's axis-0 reductions over
    narrow arrays are several times slower)."""
    lo = pos[0].copy()
    hi = pos[0].copy()
    for i in range(1, pos.shape[0]):
        for a in range(pos.shape[1]):
            lo[a] = min(lo[a], pos[i, a])
            hi[a] = max(hi[a], pos[i, a])
    return lo, hi


def cell_keys(p: np.ndarray, lo: np.ndarray, h: float, ncell: np.ndarray) -> np.ndarray:
    """Linear cell key (int64, x fastest) of each point (n, d) in a grid of ``ncell`` cells of
    edge h (m) from corner ``lo``, on as many threads as n warrants."""
    with threads_for(p.shape[0], _SORT_PER_THREAD):
        return _cell_keys(p, lo, h, ncell)


@njit(cache=True, parallel=True)
def _cell_keys(p, lo, h, ncell):
    n, dim = p.shape
    keys = np.empty(n, dtype=np.int64)
    for i in prange(n):
        k = 0
        for a in range(dim - 1, -1, -1):
            c = int(np.floor((p[i, a] - lo[a]) / h))
            c = min(max(c, 0), ncell[a] - 1)
            k = k * ncell[a] + c
        keys[i] = k
    return keys


@njit(cache=True, inline="always")
def _lower_bound(keys, lo, hi, key):
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, inline="always")
def _axis_range(x, r, h, n):
    """Cells [lo, hi] of an axis with n cells of edge h that [x - r, x + r] touches (empty:
    lo > hi)."""
    lo = np.floor((x - r) / h)
    hi = np.floor((x + r) / h)
    if hi < 0.0 or lo > n - 1:
        return 1, 0
    return int(max(lo, 0.0)), int(min(hi, n - 1.0))


@njit(cache=True, inline="always")
def _pair_test(t, r, tpos, tvel, tcov, ttime, tq, rpos, rcov, rtime, moving, gamma, w_logdet):
    """Exact gate of track t with report r at the report's own time: (d^2, passed)."""
    dim = rpos.shape[1]
    dt = rtime[r] - ttime[t] if moving else 0.0
    q = tq[t]
    v00 = projected_cov_entry(tcov, t, 0, 0, dt, q, dim, moving) + rcov[r, 0, 0]
    v01 = projected_cov_entry(tcov, t, 0, 1, dt, q, dim, moving) + rcov[r, 0, 1]
    v11 = projected_cov_entry(tcov, t, 1, 1, dt, q, dim, moving) + rcov[r, 1, 1]
    dx = rpos[r, 0] - tpos[t, 0] - dt * tvel[t, 0]
    dy = rpos[r, 1] - tpos[t, 1] - dt * tvel[t, 1]
    v02 = v12 = v22 = dz = 0.0
    if dim == 3:
        v02 = projected_cov_entry(tcov, t, 0, 2, dt, q, dim, moving) + rcov[r, 0, 2]
        v12 = projected_cov_entry(tcov, t, 1, 2, dt, q, dim, moving) + rcov[r, 1, 2]
        v22 = projected_cov_entry(tcov, t, 2, 2, dt, q, dim, moving) + rcov[r, 2, 2]
        dz = rpos[r, 2] - tpos[t, 2] - dt * tvel[t, 2]
    d2, ld = sym_d2_logdet(v00, v01, v02, v11, v12, v22, dx, dy, dz, dim, w_logdet != 0.0)
    return d2, d2 <= gamma - w_logdet * ld


def query_grid(*args):
    """Exact-gated pairs between queries and a grid's points (arguments of
    :func:`_fill_kernel` after ``cand``), each pass on as many threads as its work warrants.

    Three passes: count the candidates of each query (points in the cells it visits; no
    tests), test each candidate once writing the passing pairs into the query's candidate
    slots, and compact. The number of threads of the test pass follows from its candidates,
    not from the number of queries (a few queries with huge radii are as much work as many
    small ones)."""
    nq = args[0].shape[0]
    with threads_for(nq):
        cand = _scan_kernel(*args)
    with threads_for(nq + int(cand[-1])):
        return _fill_kernel(cand, *args)


@contextmanager
def threads_for(work: int, per_thread: int = _WORK_PER_THREAD):
    """Run the parallel kernels of the block on as many threads as ``work`` (items) warrants:
    one per ``per_thread`` items, at most the ones numba has."""
    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(before, work // per_thread)))
    try:
        yield
    finally:
        numba.set_num_threads(before)


@njit(cache=True, parallel=True)
def _scan_kernel(qpos, qrad, query_is_track, q_ids, q_rank, p_ids, origin, cell, dims, seg, keys, dense,
                 table_seg, table, tpos, tvel, tcov, ttime, tq, rpos, rcov, rtime, moving, gamma,
                 w_logdet):
    """Offsets (nq + 1,) of each query's candidates (cumulative counts)."""
    nq = qpos.shape[0]
    counts = np.zeros(nq + 1, dtype=np.int64)
    no_i, no_f = np.empty(0, np.int64), np.empty(0)
    for i in prange(nq):
        counts[i + 1] = _visit(i, qpos, qrad, query_is_track, p_ids, origin, cell, dims, seg,
                               keys, dense, table_seg, table, tpos, tvel, tcov, ttime, tq, rpos,
                               rcov, rtime, moving, gamma, w_logdet, no_i, no_f, 0, _SCAN)
    return np.cumsum(counts)


@njit(cache=True, parallel=True)
def _fill_kernel(cand, qpos, qrad, query_is_track, q_ids, q_rank, p_ids, origin, cell, dims, seg, keys,
                 dense, table_seg, table, tpos, tvel, tcov, ttime, tq, rpos, rcov, rtime, moving,
                 gamma, w_logdet):
    """Exact-gated pairs between queries (rows of qpos, radius per bucket qrad (nq, K); a
    negative radius skips the bucket) and the grid's points; ``cand`` from :func:`_scan_kernel`.

    The query set's arrays (tracks when ``query_is_track``) are indexed by query row, the
    point set's arrays by sorted grid position, so candidates in a cell are contiguous in
    memory. Returns (track id, report id, d^2) with the ids taken from ``q_ids`` (per query row)
    and ``p_ids`` (per grid position), grouped by query (by report id within a track query).
    """
    nq = qpos.shape[0]
    buf_p = np.empty(cand[-1], dtype=np.int64)
    buf_d2 = np.empty(cand[-1])
    found = np.zeros(nq, dtype=np.int64)
    for i in prange(nq):
        found[i] = _visit(i, qpos, qrad, query_is_track, p_ids, origin, cell, dims, seg, keys,
                          dense, table_seg, table, tpos, tvel, tcov, ttime, tq, rpos, rcov, rtime,
                          moving, gamma, w_logdet, buf_p, buf_d2, cand[i], _FILL)
        if query_is_track and found[i] > 1:  # in parallel here, so that sorted_pairs finds sorted runs
            _sort_run(buf_p, buf_d2, cand[i], cand[i] + found[i])
    # Compact in query order first (sequential), then reorder by q_rank within the compacted
    # pairs, which fit in cache: reordering straight from the candidate slots costs a cache
    # miss per array and query with pairs.
    hits = np.nonzero(found)[0]
    n_hit = hits.shape[0]
    h_off = np.zeros(n_hit + 1, dtype=np.int64)
    h_off[1:] = np.cumsum(found[hits])
    c_p = np.empty(h_off[-1], dtype=np.int64)
    c_d2 = np.empty(h_off[-1])
    for h in prange(n_hit):
        s = cand[hits[h]] - h_off[h]
        for k in range(h_off[h], h_off[h + 1]):  # element loops: a slice copy costs ~100 ns
            c_p[k] = buf_p[s + k]
            c_d2[k] = buf_d2[s + k]
    by_rank = counting_order(q_rank[hits], nq)[0]
    offs = np.zeros(n_hit + 1, dtype=np.int64)
    for k in range(n_hit):
        h = by_rank[k]
        offs[k + 1] = offs[k] + h_off[h + 1] - h_off[h]
    out_q = np.empty(offs[-1], dtype=np.int64)
    out_p = np.empty(offs[-1], dtype=np.int64)
    out_d2 = np.empty(offs[-1])
    for k in prange(n_hit):
        h = by_rank[k]
        q, at = q_ids[hits[h]], offs[k] - h_off[h]
        for j in range(h_off[h], h_off[h + 1]):
            out_q[at + j] = q
            out_p[at + j] = c_p[j]
            out_d2[at + j] = c_d2[j]
    if query_is_track:
        return out_q, out_p, out_d2
    return out_p, out_q, out_d2


# What _visit does with the points in the cells it visits.
_SCAN, _FILL = 0, 1


@njit(cache=True, inline="always")
def _visit(i, qpos, qrad, query_is_track, p_ids, origin, cell, dims, seg, keys, dense,
           table_seg, table, tpos, tvel, tcov, ttime, tq, rpos, rcov, rtime, moving, gamma,
           w_logdet, out_p, out_d2, at, mode):
    """Query i against the grid: the number of candidates (``_SCAN``), or the number of exact
    pairs, their points' ids and d² written from ``at`` on (``_FILL``)."""
    dim = qpos.shape[1]
    n_buckets = cell.shape[0]
    found = 0
    i = np.int64(i)  # parfor indices are unsigned; keep (t, r) integer when unified with m
    for b in range(n_buckets):
        r = qrad[i, b]
        if r < 0.0 or seg[b + 1] == seg[b]:
            continue
        h = cell[b]
        x_lo, x_hi = _axis_range(qpos[i, 0] - origin[b, 0], r, h, dims[b, 0])
        y_lo, y_hi = _axis_range(qpos[i, 1] - origin[b, 1], r, h, dims[b, 1])
        z_lo, z_hi = 0, 0
        if dim == 3:
            z_lo, z_hi = _axis_range(qpos[i, 2] - origin[b, 2], r, h, dims[b, 2])
        for cz in range(z_lo, z_hi + 1):
            for cy in range(y_lo, y_hi + 1):
                if x_lo > x_hi:
                    break
                row = (cz * dims[b, 1] + cy) * dims[b, 0]
                k_lo, k_hi = row + x_lo, row + x_hi
                if dense[b]:
                    s = seg[b] + table[table_seg[b] + k_lo]
                    e = seg[b] + table[table_seg[b] + k_hi + 1]
                else:
                    s = _lower_bound(keys, seg[b], seg[b + 1], k_lo)
                    e = _lower_bound(keys, s, seg[b + 1], k_hi + 1)
                if mode == _SCAN:
                    found += e - s
                    continue
                for m in range(np.int64(s), np.int64(e)):
                    t, rep = (i, m) if query_is_track else (m, i)
                    d2, ok = _pair_test(t, rep, tpos, tvel, tcov, ttime, tq, rpos, rcov, rtime,
                                        moving, gamma, w_logdet)
                    if ok:
                        out_p[at + found] = p_ids[m]
                        out_d2[at + found] = d2
                        found += 1
    return found


@njit(cache=True)
def counting_order(keys, n_keys):
    """Stable permutation sorting integer keys in [0, n_keys) (O(n + n_keys)), and the start
    offset of each key (n_keys + 1,).

    Small inputs, one counting sort; more than _FLAT_KEYS keys and values, two (the high bits of
    the key, then the low bits within each high value), so that every count lives in cache: one
    counting sort over millions of keys spends its time on cache misses. From _SORT_PER_THREAD
    keys on, both digits run on several threads."""
    if n_keys <= _FLAT_KEYS or keys.shape[0] <= _FLAT_KEYS:
        return _counting_order_flat(keys, n_keys)
    # slices of the input, one per thread at most (fewer threads run several in turn; reading
    # numba's thread count here would keep the function out of the cache)
    chunks = max(1, min(_SORT_MAX_SLICES, keys.shape[0] // _SORT_PER_THREAD))
    return _counting_order_split(keys, n_keys, chunks)


# Key ranges and inputs both above this are sorted in two digits by counting_order.
_FLAT_KEYS = 1 << 16
# Keys per thread of counting_order's two-digit sort (about 5 ms of work on one core).
_SORT_PER_THREAD = 400_000
_SORT_MAX_SLICES = 16


@njit(cache=True)
def _counting_order_flat(keys, n_keys):
    start = np.zeros(n_keys + 1, dtype=np.int64)
    for k in keys:
        start[k + 1] += 1
    for k in range(n_keys):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(keys.shape[0], dtype=np.int64)
    for i in range(keys.shape[0]):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    return order, start


@njit(cache=True, parallel=True)
def _counting_order_split(keys, n_keys, chunks):
    """counting_order in two digits on ``chunks`` threads: stably by key >> shift, then within
    each high value by the low bits (the same permutation and offsets as one counting sort).

    First digit: each thread counts and scatters one contiguous slice of the input, its
    elements of each high value placed after those of the slices before it (so stable).
    Second digit: each thread sorts a contiguous range of high values (disjoint output)."""
    n = keys.shape[0]
    shift = 0
    while (1 << (2 * shift)) < n_keys:
        shift += 1
    base = np.int64(1) << shift
    mask = base - 1
    n_hi = (n_keys + base - 1) >> shift
    cut = np.empty(chunks + 1, dtype=np.int64)  # input slice of each thread
    for c in range(chunks + 1):
        cut[c] = c * n // chunks
    hist = np.zeros((chunks, n_hi), dtype=np.int64)
    for c in prange(chunks):
        for i in range(cut[c], cut[c + 1]):
            hist[c, keys[i] >> shift] += 1
    hi_start = np.empty(n_hi + 1, dtype=np.int64)
    at = 0
    for h in range(n_hi):
        hi_start[h] = at
        for c in range(chunks):
            at, hist[c, h] = at + hist[c, h], at  # hist becomes each slice's fill position
    hi_start[n_hi] = n
    by_hi = np.empty(n, dtype=np.int64)
    lo = np.empty(n, dtype=np.int64)
    for c in prange(chunks):
        for i in range(cut[c], cut[c + 1]):
            h = keys[i] >> shift
            by_hi[hist[c, h]] = i
            lo[hist[c, h]] = keys[i] & mask
            hist[c, h] += 1
    h_cut = np.empty(chunks + 1, dtype=np.int64)  # high values of each thread, ~n / chunks keys each
    for c in range(chunks + 1):
        h_cut[c] = np.searchsorted(hi_start, c * n // chunks)
    h_cut[chunks] = n_hi
    start = np.empty(n_keys + 1, dtype=np.int64)
    start[n_keys] = n
    order = np.empty(n, dtype=np.int64)
    for c in prange(chunks):
        count = np.empty(base, dtype=np.int64)
        for h in range(h_cut[c], h_cut[c + 1]):
            s, e = hi_start[h], hi_start[h + 1]
            k0 = h << shift
            m = min(base, n_keys - k0)
            count[:m] = 0
            for a in range(s, e):
                count[lo[a]] += 1
            at2 = s
            for j in range(m):
                start[k0 + j] = at2
                at2 += count[j]
                count[j] = start[k0 + j]
            for a in range(s, e):
                order[count[lo[a]]] = by_hi[a]
                count[lo[a]] += 1
    return order, start


def spatial_order(pos: np.ndarray) -> np.ndarray:
    """Permutation putting points (n, d) in row-major order of a grid with about n cells, so
    that neighbours sit close in memory (O(n))."""
    n = pos.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    lo, hi = bounding_box(pos)
    extent = hi - lo
    if not extent.max() > 0.0:
        return np.arange(n)
    # at most n^(1/d) cells along the longest axis, so at most ~n cells in all
    h = float(extent.max()) / np.ceil(n ** (1.0 / pos.shape[1]))
    ncell = np.floor(extent / h).astype(np.int64) + 1
    return counting_order(cell_keys(pos, lo, h, ncell), int(np.prod(ncell)))[0]


@njit(cache=True)
def sort_pairs(t, r, n_t, n_r):
    """Permutation sorting pairs (t in [0, n_t), r in [0, n_r)) by (t, r), as
    ``np.lexsort((r, t))`` for pairs without duplicates (:func:`sorted_pairs`)."""
    return _sort_pairs(t, r, n_t, n_r)[0]


@njit(cache=True)
def sorted_pairs(t, r, d2, n_t, n_r):
    """Pairs (t, r, d2) in (t, r) order, in O(pairs log(pairs per track)).

    A counting sort on t, then per track :func:`_sort_run` on its reports (runs the kernel sorted
    already cost one comparison per pair). When most pairs sit in long unsorted runs, two
    counting sorts (r, then stably t: O(pairs + n_t + n_r)) replace the per-track sorts."""
    order, r_sorted, start = _sort_pairs(t, r, n_t, n_r)
    t_sorted = np.empty(t.shape[0], np.int64)
    for k in range(n_t):
        t_sorted[start[k]:start[k + 1]] = k
    return t_sorted, r_sorted, d2[order]


@njit(cache=True)
def _sort_pairs(t, r, n_t, n_r):
    """(permutation, r permuted, start offset of each t) of :func:`sorted_pairs`."""
    order, start = counting_order(t, n_t)
    keys = r[order]
    unsorted_long = 0
    for k in range(n_t):
        s, e = start[k], start[k + 1]
        if e - s > _INSERTION_MAX:
            for a in range(s + 1, e):
                if keys[a] < keys[a - 1]:
                    unsorted_long += e - s
                    break
    if unsorted_long > t.shape[0] // 2:
        by_r = counting_order(r, n_r)[0]
        order = by_r[counting_order(t[by_r], n_t)[0]]
        return order, r[order], start
    for k in range(n_t):
        _sort_run(keys, order, start[k], start[k + 1])
    return order, keys, start


@njit(cache=True)
def _sort_run(keys, sat, s, e):
    """Sort keys[s:e] ascending in place, moving sat[s:e] alongside: insertion sort for short
    or sorted runs, merge sort (O(k log k)) otherwise."""
    if e - s > _INSERTION_MAX:
        for a in range(s + 1, e):
            if keys[a] < keys[a - 1]:
                o = np.argsort(keys[s:e], kind="mergesort")
                keys[s:e] = keys[s:e][o]
                sat[s:e] = sat[s:e][o]
                return
        return
    for a in range(s + 1, e):
        x, y = keys[a], sat[a]
        b = a - 1
        while b >= s and keys[b] > x:
            keys[b + 1] = keys[b]
            sat[b + 1] = sat[b]
            b -= 1
        keys[b + 1] = x
        sat[b + 1] = y
