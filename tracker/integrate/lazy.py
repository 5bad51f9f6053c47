"""The prior's Gaussian pyramid built lazily, tile by tile, only where Gaussians fall, in a bounded cache.

:class:`~tracker.integrate.scalespace.Pyramid` builds every level of a whole prior in memory (~17
float32 per cell: 40 GiB for 50,000² cells). :class:`LazyPyramid` keeps the same lattices (level k:
nodes ``origin_k + h_k j``, :func:`~tracker.integrate.scalespace.lattice`) but computes their cubic
B-spline coefficients per tile (:data:`SIDE` nodes a side at levels 0-3, fewer above) when an integral first needs them,
and keeps them in a fixed pool of :data:`~tracker.integrate.scalespace.TILE`-node blocks (the layout
the kernel reads), evicting the least recently used tiles when the pool is full.

Why a tile equals the whole pyramid's nodes: a node of a level k < ``CELL_LEVELS`` (s_k <= 16 cells)
is an exact sum over the cells within ±(8 s_k + 1) of it, a node of a higher level a trapezoid sum
over the level-(k-1) node values within ±(10 d + 1) nodes (:func:`~tracker.integrate.scalespace._gauss_weights`),
and a coefficient the finite prefilter over ±``FIR`` = 14 value nodes
(:func:`~tracker.integrate.scalespace._fir_weights`). A tile reads exactly those cells or nodes, with the
whole lattice's band starts and weights, so its sums are the same numbers in the same order: the
coefficients, and the integrals from them, are the whole pyramid's bit for bit
(tests/tracker/integrate/test_lazy.py).

The dependency cone: a tile of a cell level needs only cells (its extent plus 14 h_k + 8 s_k a side);
a tile above the cell levels needs the level below on its extent plus ~34 nodes a side, down to the
16-cell level. Tiles hold 256 nodes a side up to level 3 and fewer above (``blocks >> (k // 4)``
kernel blocks, at least one), so a tile covers 215-362 cells a side up to s = 16 cells and the
cells a cold tile reads stay near the area a stream touches. Cost is per tile touched, not per
cell of the prior. Units as in
:mod:`tracker.integrate.scalespace` (pixels; values in the prior's units).
"""

from __future__ import annotations

import functools
import itertools
import math
import mmap
import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TYPE_CHECKING, Protocol

import numba as nb
import numpy as np

from pipeline.prior import TerrainPrior
from tracker.integrate import scalespace as ss
from tracker.integrate.scalespace import GH_SPAN

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["BLOCKS", "CACHE_BYTES", "SIDE", "CellSource", "LazyPyramid", "cell_tiles", "home_blocks", "huge_zeros", "lazy_pyramid",
           "rectangles", "tile_client"]

BLOCKS = 8
"""Kernel blocks (:data:`~tracker.integrate.scalespace.TILE` nodes) per tile side at levels 0-3; levels
4-7 have half as many, 8-11 a quarter, and so on down to one (see :meth:`LazyPyramid.level_blocks`)."""
SIDE = BLOCKS * ss.TILE
"""Nodes per tile side at level 0 (256: 215 cells, 1.3 MB of its float64 temporaries)."""
CACHE_BYTES = 1 << 30
"""Default size of the block pool, bytes (3,400 tiles of 256² nodes)."""
_T = ss.TILE
_BLOCK = ss.BLOCK
BORDER = 1e-9
"""Relative margin around S0 within which a Gaussian's smaller σ may fall on either side of the
kernel's fine/pyramid test (its rounding): it is planned both ways."""
FINE_BLOCK = 1024
"""Cells per side of the blocks of means whose Gaussians finer than level 0 read one window of the
source together (without an in-memory field): the window spans the block's Gaussians, not the block."""
STACK_BYTES = 16 << 20
"""Bytes of the windows of cells stacked for one kernel call of fine Gaussians: below glibc's largest
mmap threshold (32 MiB), so the stack reuses heap pages rather than faulting fresh ones on every call."""
CELL_BLOCK = 256
"""Cells per side of the source blocks cached for the fine Gaussians (without a field)."""
PAD = 32
"""Cells a side around each :data:`CELL_BLOCK` block kept with it as one window (:meth:`LazyPyramid._padded_runs`):
the fine Gaussians whose reach fits it read it in place, with no window made per batch."""
CELL_CACHE_BYTES = 256 << 20
"""Bytes of float64 source blocks kept for the fine Gaussians that no padded block holds."""
PAD_CACHE_BYTES = 768 << 20
"""Bytes of float64 padded blocks (:data:`PAD`) kept for the fine Gaussians (940: a stream over 100
squares of 250 cells, the tracker bench's targets spread over a 50,000² prior, needs 400-900)."""
SERIAL_BELOW = 1024
"""Batches of fewer integrals run on one thread (as the tracker's small integrator calls do)."""
RECTANGLE = 4
"""Most tiles a side of a rectangle of cell-level tiles built together (:func:`rectangles`): adjacent
tiles share the cells and margins they read (8 s + 14 h + 2 cells a side, more than a tile at s = 16)."""
MISSING = 0
"""The pool's slot that the block tables point at for a block not built (or evicted): all NaN, so a
look-up there gives NaN (the kernel needs no test; the caller builds the tiles and asks again)."""


class CellSource(Protocol):
    """What a lazy pyramid reads the prior from: an (H, W) ``shape`` and 2-D slicing that returns the
    cells' values (per m², any float dtype) as an array; a numpy array or memmap is one."""

    shape: tuple[int, ...]

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray: ...


class LazyPyramid:
    """f_{s_k} = r ⊛ G_{s_k} on the lattices of :class:`~tracker.integrate.scalespace.Pyramid`,
    computed per tile on demand and cached in ``cache_bytes`` of float32 blocks (thread-safe).

    ``source`` holds r per cell (:class:`CellSource`); ``squared`` integrates r² instead; a tile of
    levels 0-3 is ``blocks`` x ``blocks`` kernel blocks (:data:`SIDE` nodes a side by default), fewer
    above (:meth:`level_blocks`). ``tiles_built`` and ``cells_read`` count the work so far. ``field``,
    the (H, W) float64 values (r or r²) in memory, serves Gaussians narrower than the finest level
    (smoothed on the fly from the cells, as the whole pyramid does); without it they are smoothed
    from windows of ``source`` around them, with the same numbers. With a ``client``
    (``dask.distributed``), the cell-level tiles a batch needs are built on its workers (``source``
    must then be picklable and readable there: a windowed density of a file on a shared path is).
    """

    def __init__(self, source: CellSource, squared: bool = False, cache_bytes: int = CACHE_BYTES,
                 field: np.ndarray | None = None, blocks: int = BLOCKS, client: Client | None = None) -> None:
        if len(source.shape) != 2:
            raise ValueError(f"LazyPyramid: the source must be 2-D, got shape {source.shape}")
        self.source = source
        self.shape = (int(source.shape[0]), int(source.shape[1]))
        self.squared = squared
        self.field = field
        self.blocks = int(blocks)
        self.n_slots = max(int(cache_bytes) // (4 * _BLOCK) - 1, 4 * self.blocks**2)  # besides MISSING
        self.pool = huge_zeros((self.n_slots + 1, _BLOCK), np.float32)
        self.pool[MISSING] = np.nan
        self._free = [s for s in range(self.n_slots, -1, -1) if s != MISSING]
        self._tiles: dict[tuple[int, int, int], np.ndarray] = {}  # built tiles: their positions in slots
        # Per tile of every level (:meth:`_tile_ids`): when it was last used (for least-recently-used
        # eviction) and whether the batch being integrated needs it (pinned: not evicted).
        self._tile_offset = np.zeros(0, np.int64)  # per level: its first tile's id
        self._tiles_across = np.zeros(0, np.int64)  # per level: tiles per row
        self._used = np.zeros(0, np.int64)
        self._pinned = np.zeros(0, bool)
        self._pinned_ids: list[np.ndarray] = []
        self._clock = 0
        self._pinned_blocks = 0  # pool slots the pinned tiles hold (at most)
        self._geometry: list[tuple[float, float, float, int, int, int, int]] = []  # s, h, origin, nu, nv, nbu, table offset
        self.slots = np.full(0, MISSING, np.int32)
        self._packed: ss.Packed | None = None  # packed()'s arrays for the levels so far
        self.tiles_built = 0
        self.cells_read = 0
        self.client = client
        self._scattered = None  # (client, the source scattered to its workers)
        self._cell_blocks: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()  # for the fine Gaussians
        self._pads = np.empty((0, 0))  # padded blocks kept as the fine Gaussians' windows (:meth:`_padded_runs`)
        self._pad_frames = np.zeros((0, 4), np.int64)
        self._pad_slot_of = np.zeros(0, np.int64)  # per padded block of the grid: its slot, or -1
        self._pad_key = np.zeros(0, np.int64)  # per slot: the block it holds, or -1
        self._pad_used = np.zeros(0, np.int64)  # per slot: the run that last used it
        self._pad_clock = 0
        self._lock = threading.RLock()

    # --- levels and tiles -------------------------------------------------------------------

    def _grow(self, top_scale: float) -> None:
        """Add levels (empty tables) up to the first with s_k >= ``top_scale``, as the whole pyramid does."""
        if self._geometry and self._geometry[-1][0] >= top_scale:
            return
        tables = [self.slots]
        size = self.slots.size
        while not self._geometry or self._geometry[-1][0] < top_scale:
            s, h, origin, nu, nv = ss.lattice(len(self._geometry), self.shape)
            nbu, nbv = -(-nu // ss.TILE), -(-nv // ss.TILE)
            self._geometry.append((s, h, origin, nu, nv, nbu, size))
            tables.append(np.full(nbu * nbv, MISSING, np.int32))
            size += nbu * nbv
        if len(tables) > 1:
            self.slots = np.concatenate(tables)
            grid = [(-(-g[3] // self._side(k)), -(-g[4] // self._side(k))) for k, g in enumerate(self._geometry)]
            self._tiles_across = np.array([across for across, _ in grid], np.int64)
            self._tile_offset = np.cumsum([0] + [across * down for across, down in grid])
            grown = int(self._tile_offset[-1]) - self._used.size
            self._used = np.concatenate([self._used, np.zeros(grown, np.int64)])
            self._pinned = np.concatenate([self._pinned, np.zeros(grown, bool)])

    def _cells(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The float64 values (r or r²) of cells [r0, r1) x [c0, c1)."""
        values = read_cells(self.source, self.squared, r0, r1, c0, c1)
        self.cells_read += values.size
        return values

    def _cached_cells(self, r0: int, r1: int, c0: int, c1: int, out: np.ndarray | None = None) -> np.ndarray:
        """:meth:`_cells` assembled from :data:`CELL_BLOCK`-square blocks of the source kept in an LRU
        cache of :data:`CELL_CACHE_BYTES` (the fine Gaussians of a stream return to the same cells, and
        a windowed file decompresses a window on every read): the same values, into ``out`` if given."""
        b = CELL_BLOCK
        out = np.empty((r1 - r0, c1 - c0)) if out is None else out
        for br in range(r0 // b, (r1 - 1) // b + 1):
            for bc in range(c0 // b, (c1 - 1) // b + 1):
                block = self._cell_blocks.get((br, bc))
                if block is None:
                    block = self._cells(br * b, min((br + 1) * b, self.shape[0]), bc * b, min((bc + 1) * b, self.shape[1]))
                    self._cell_blocks[(br, bc)] = block
                    while len(self._cell_blocks) * b * b * 8 > CELL_CACHE_BYTES:
                        self._cell_blocks.popitem(last=False)
                self._cell_blocks.move_to_end((br, bc))
                i0, i1 = max(r0, br * b), min(r1, br * b + block.shape[0])
                j0, j1 = max(c0, bc * b), min(c1, bc * b + block.shape[1])
                out[i0 - r0 : i1 - r0, j0 - c0 : j1 - c0] = block[i0 - br * b : i1 - br * b, j0 - bc * b : j1 - bc * b]
        return out

    def level_blocks(self, k: int) -> int:
        """Kernel blocks per tile side at level k: ``blocks`` halved every 4 levels (one octave), at least
        one, so tiles cover about the same cells (16 s_k cells a block) up to where they reach one block."""
        return max(1, self.blocks >> (k // 4))

    def _side(self, k: int) -> int:
        """Nodes per tile side at level k."""
        return self.level_blocks(k) * _T

    def _value_span(self, k: int, lo: int, hi: int, axis: int) -> tuple[int, int]:
        """The level-k value nodes [w0, w1) on ``axis`` (0 rows, 1 columns) whose prefilter gives the
        coefficients that tiles spanning nodes [lo, hi) store (their nodes with the one-before,
        two-after apron)."""
        n = self._geometry[k][4] if axis == 0 else self._geometry[k][3]
        start, weights = ss._fir_weights(max(lo - 1, 0), min(hi + 2, n), n)
        return int(start[0]), int(start[-1]) + weights.shape[1]

    def _needs(self, k: int, lo: int, hi: int, axis: int) -> tuple[int, int]:
        """The level-(k-1) coefficient nodes [c0, c1) on ``axis`` that the values of level k >= CELL_LEVELS
        at nodes [lo, hi) read (the smoothing band, and one node more each side for node values)."""
        s, h, origin, nu, nv = self._geometry[k][:5]
        ps, ph, po, pnu, pnv = self._geometry[k - 1][:5]
        pn = pnv if axis == 0 else pnu
        ends = origin + h * np.array([lo, hi - 1])
        start, weights = ss._gauss_weights(ends, po, pn, np.sqrt(s * s - ps * ps), ph)
        return max(int(start[0]) - 1, 0), min(int(start[1]) + weights.shape[1] + 1, pn)

    def _prepare(self, k: int, tv: int, tu: int) -> None:
        """Build tile (tv, tu) of level k after the tiles below it that are missing, lowest level first:
        each is then built once, not once per tile above it that reads it. Tiles of the cell levels
        read cells only."""
        plan = [(k, tv, tv, tu, tu)]
        while plan[-1][0] >= ss.CELL_LEVELS:
            m, v0, v1, u0, u1 = plan[-1]
            side, below_side = self._side(m), self._side(m - 1)
            j0, j1 = self._needs(m, *self._value_span(m, v0 * side, (v1 + 1) * side, 0), 0)
            i0, i1 = self._needs(m, *self._value_span(m, u0 * side, (u1 + 1) * side, 1), 1)
            below = (m - 1, j0 // below_side, (j1 - 1) // below_side, i0 // below_side, (i1 - 1) // below_side)
            if all((below[0], a, b) in self._tiles for a in range(below[1], below[2] + 1) for b in range(below[3], below[4] + 1)):
                break
            plan.append(below)
        # Two consecutive levels' rectangles must fit beside the pinned tiles, or building one level
        # would evict the tiles below it that the next build reads (and rebuild them, again and again).
        sizes = [(v1 - v0 + 1) * (u1 - u0 + 1) * self.level_blocks(m) ** 2 for m, v0, v1, u0, u1 in plan]
        need = max(a + b for a, b in zip(sizes, [*sizes[1:], 0], strict=True)) + self._pinned_blocks
        if need > self.n_slots:
            raise MemoryError(f"LazyPyramid: a cache of {self.pool.nbytes / 2**20:.0f} MiB cannot hold the tiles one batch needs "
                              f"({need} blocks at once)")
        # A tile's kernels take ~50 µs on one thread; a parallel launch can cost more than that on busy cores.
        with _threads(1):
            for m, v0, v1, u0, u1 in reversed(plan):
                for a in range(v0, v1 + 1):
                    for b in range(u0, u1 + 1):
                        if (m, a, b) not in self._tiles:
                            self._build(m, a, b)

    def _values(self, k: int, j0: int, j1: int, i0: int, i1: int) -> np.ndarray:
        """f_{s_k} (float64) at the nodes [j0, j1) x [i0, i1) of a level k >= CELL_LEVELS: the trapezoid
        rule on the level below, with the whole lattice's band starts and weights."""
        s, h, origin = self._geometry[k][:3]
        u = origin + h * np.arange(i0, i1)
        v = origin + h * np.arange(j0, j1)
        ps, ph, po, pnu, pnv = self._geometry[k - 1][:5]
        d = np.sqrt(s * s - ps * ps)
        su, wu = ss._gauss_weights(u, po, pnu, d, ph)
        sv, wv = ss._gauss_weights(v, po, pnv, d, ph)
        a0, a1 = int(su.min()), int(su.max()) + wu.shape[1]
        b0, b1 = int(sv.min()), int(sv.max()) + wv.shape[1]
        # node values need one coefficient beyond each end (or the lattice's mirrored end)
        (cj0, cj1), (ci0, ci1) = self._needs(k, j0, j1, 0), self._needs(k, i0, i1, 1)
        nodes = ss._node_values(self.window(k - 1, cj0, cj1, ci0, ci1))[b0 - cj0 : b1 - cj0, a0 - ci0 : a1 - ci0]
        return ss._separable(np.ascontiguousarray(nodes), su - a0, wu, sv - b0, wv)

    def _build(self, k: int, tv: int, tu: int) -> None:
        """Coefficients of tile (tv, tu) of level k, into free blocks of the pool."""
        if k < ss.CELL_LEVELS:
            (padded,), cells = cell_tiles(self.source, self.squared, self.shape, k, tv, tv, tu, tu, self._side(k))
            self.cells_read += cells
        else:
            nu, nv = self._geometry[k][3:5]
            values = _prefiltered(lambda *window: self._values(k, *window), nu, nv)
            (padded,) = _padded_coefficients(values, nu, nv, self._side(k), tv, tv, tu, tu)
        self._insert(k, tv, tu, padded)

    def _insert(self, k: int, tv: int, tu: int, padded: np.ndarray) -> None:
        """Tile (tv, tu) of level k (its coefficients with their aprons, :func:`_padded_coefficients`) into
        free blocks of the pool."""
        claim = slots, _, keep_v, keep_u = self._claim(k, tv, tu)
        _store_blocks(self.pool, slots, padded, keep_v, keep_u)
        self._register((k, tv, tu), claim)

    def _claim(self, k: int, tv: int, tu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Free pool slots for tile (tv, tu) of level k's blocks within the lattice (evicting if need
        be), not yet in the tables: (slots, their positions in :attr:`slots`, the tile's block rows and
        columns kept)."""
        nu, nv, nbu, toff = self._geometry[k][3:]
        blocks = self.level_blocks(k)
        nbv = -(-nv // ss.TILE)
        gbv = tv * blocks + np.arange(blocks)
        gbu = tu * blocks + np.arange(blocks)
        keep_v, keep_u = np.flatnonzero(gbv < nbv), np.flatnonzero(gbu < nbu)
        n = keep_v.size * keep_u.size
        self._make_room(n)
        slots = np.array([self._free.pop() for _ in range(n)], np.int32)
        return slots, toff + (gbv[keep_v][:, None] * nbu + gbu[keep_u][None, :]).ravel(), keep_v, keep_u

    def _register(self, key: tuple[int, int, int], claim: tuple[np.ndarray, ...]) -> None:
        """Tile ``key``, whose :meth:`_claim`-ed slots hold its blocks, into the tables: built, and the
        most recently used until its batch pins it."""
        slots, table = claim[:2]
        self.slots[table] = slots
        self._tiles[key] = table
        self._used[self._tile_ids(*key)] = self._clock
        self._clock += 1
        self.tiles_built += 1

    def _build_cell_tiles(self, keys: list[tuple[int, int, int]]) -> None:
        """The missing cell-level tiles among ``keys``, built by rectangles of adjacent tiles of a level
        (:func:`rectangles`, at most :data:`RECTANGLE` a side: their cells and margins read once,
        :func:`cell_tiles`): on the workers of :attr:`client` (``dask.distributed``) if there is one,
        else on this process's threads (numba's thread count; the kernels release the GIL). Their pool
        slots are claimed first, so each thread also copies its tiles into the pool (the first touches
        of fresh pages run in parallel too); the tables point at them once all are in. The tiles above
        the cell levels read the pool, so :meth:`tile` builds those here."""
        todo = rectangles([key for key in keys if key[0] < ss.CELL_LEVELS and key not in self._tiles], RECTANGLE)
        if not todo:
            return
        keys_of = [[(k, tv, tu) for tv in range(tv0, tv1 + 1) for tu in range(tu0, tu1 + 1)] for k, tv0, tv1, tu0, tu1 in todo]
        claims: list[list[tuple[np.ndarray, ...]]] = []
        args = [(self.squared, self.shape, *rect, self._side(rect[0])) for rect in todo]

        def store(tiles: list[np.ndarray], claim: list[tuple[np.ndarray, ...]]) -> None:
            for padded, (slots, _, keep_v, keep_u) in zip(tiles, claim, strict=True):
                _store_blocks(self.pool, slots, padded, keep_v, keep_u)

        def build(a: tuple, claim: list[tuple[np.ndarray, ...]]) -> int:
            tiles, cells = cell_tiles(self.source, *a)
            store(tiles, claim)
            return cells

        try:
            for rect in keys_of:  # one claim at a time, so a MemoryError part-way frees those made
                claims.append([])
                for key in rect:
                    claims[-1].append(self._claim(*key))
            if self.client is not None:
                if self._scattered is None or self._scattered[0] is not self.client:
                    self._scattered = (self.client, self.client.scatter(self.source, broadcast=True))
                futures = self.client.map(cell_tiles, [self._scattered[1]] * len(todo), *zip(*args, strict=True), pure=False)
                cells = []
                for (tiles, n), claim in zip(self.client.gather(futures), claims, strict=True):
                    store(tiles, claim)
                    cells.append(n)
            elif nb.get_num_threads() > 1 and len(todo) > 1:
                cells = list(_tile_threads(nb.get_num_threads()).map(build, args, claims))
            else:
                cells = [build(a, claim) for a, claim in zip(args, claims, strict=True)]
        except BaseException:
            self._free.extend(int(slot) for claim in claims for c in claim for slot in c[0])
            raise
        self.cells_read += sum(cells)
        for rect, claim in zip(keys_of, claims, strict=True):
            for key, c in zip(rect, claim, strict=True):
                self._register(key, c)

    def _make_room(self, n: int) -> None:
        """Free ``n`` slots, evicting the least recently used tiles that are not pinned (and a
        64th of the pool more, so that a stream past the cache's size sorts its tiles once per
        many builds, not once per build)."""
        if len(self._free) >= n:
            return
        keys = list(self._tiles)
        ids = self._tile_ids(*np.array(keys, np.int64).reshape(-1, 3).T)
        for i in np.argsort(self._used[ids], kind="stable").tolist():
            if self._pinned[ids[i]]:
                continue
            table = self._tiles.pop(keys[i])
            self._free.extend(self.slots[table].tolist())
            self.slots[table] = MISSING
            if len(self._free) >= n + self.n_slots // 64:
                return
        if len(self._free) < n:
            raise MemoryError(f"LazyPyramid: a cache of {self.pool.nbytes / 2**20:.0f} MiB cannot hold the tiles one batch needs")

    def _tile_ids(self, k: np.ndarray, tv: np.ndarray, tu: np.ndarray) -> np.ndarray:
        """Ids of tiles (k, tv, tu) (arrays): level k's first tile's id plus tv · tiles per row + tu."""
        return self._tile_offset[k] + tv * self._tiles_across[k] + tu

    def _pin(self, ids: np.ndarray, blocks: np.ndarray) -> None:
        """Mark the built tiles ``ids`` (:meth:`_tile_ids`) of ``blocks`` kernel blocks each used now and
        needed by the batch: not evicted until :meth:`_unpin`."""
        fresh = ~self._pinned[ids]
        self._pinned[ids] = True
        self._pinned_ids.append(ids)
        self._pinned_blocks += int(blocks[fresh].sum())
        self._used[ids] = self._clock
        self._clock += 1

    def _unpin(self) -> None:
        """No tile pinned (:meth:`_pin`)."""
        if self._pinned_ids:
            self._pinned[np.concatenate(self._pinned_ids)] = False
        self._pinned_ids = []
        self._pinned_blocks = 0

    def tile(self, k: int, tv: int, tu: int) -> np.ndarray:
        """Positions in :attr:`slots` of tile (tv, tu) of level k's blocks, built if missing; marks it recently used."""
        key = (k, tv, tu)
        with self._lock:
            table = self._tiles.get(key)
            if table is None:
                self._prepare(k, tv, tu)
                table = self._tiles[key]
            self._used[self._tile_ids(k, tv, tu)] = self._clock
            self._clock += 1
            return table

    def window(self, k: int, j0: int, j1: int, i0: int, i1: int) -> np.ndarray:
        """Level k's coefficients at nodes [j0, j1) x [i0, i1) of its lattice (float32), from its tiles."""
        with self._lock:
            out = np.empty((j1 - j0, i1 - i0), np.float32)
            side, blocks = self._side(k), self.level_blocks(k)
            for tv in range(j0 // side, (j1 - 1) // side + 1):
                for tu in range(i0 // side, (i1 - 1) // side + 1):
                    self.tile(k, tv, tu)
                    _copy_blocks(self.pool, self.slots, self._geometry[k][6], self._geometry[k][5], blocks, tv, tu, j0, j1, i0, i1, out)
            return out

    def levels_built(self) -> int:
        """How many levels have lattices so far."""
        return len(self._geometry)

    def packed(self) -> ss.Packed:
        """The levels' geometry as the kernel reads it, with ``coef`` the pool and ``offset`` into :attr:`slots`
        (made again only when :meth:`_grow` has added levels)."""
        if self._packed is not None and self._packed.scale.size == len(self._geometry):
            return self._packed
        g = self._geometry
        col = [np.array([x[i] for x in g]) for i in range(5)]
        self._packed = ss.Packed(col[0], col[1], col[2], col[2].copy(), col[3].astype(np.int64), col[4].astype(np.int64),
                                 np.array([x[6] for x in g], np.int64), self.pool.reshape(-1))
        return self._packed

    # --- integrals --------------------------------------------------------------------------

    def integrate_pixels(self, uc: np.ndarray, vc: np.ndarray, cuu: np.ndarray, cuv: np.ndarray, cvv: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """As :func:`tracker.integrate.scalespace.integrate_pixels`: (values, look-ups per integral),
        look-ups 0 for Gaussians left to the caller (too eccentric)."""
        n = uc.shape[0]
        out = np.zeros(n)
        counts = np.zeros(n, np.int64)
        if n == 0:
            return out, counts
        smin = np.empty(n)
        keys = np.empty(n, np.int64)
        h, w = self.shape
        ss._order_keys(uc, vc, cuu, cuv, cvv, h, w, ss.ORDER_TILE, smin, keys)
        with self._lock:
            self._grow(float(smin.max(initial=0.0)))
            order = np.argsort(keys)
            # The kernel's own test (λ₂ < S0², in its rounding) may go either way within 1e-9 of S0:
            # such Gaussians get level-0 tiles planned (_tiles_of) and, without a field, come back
            # with look-ups -1 when the kernel found them finer (no cells given: NO_CELLS).
            if self.field is not None:
                self._tiled(self.field, ss.whole_frame(self.field), order, uc, vc, cuu, cuv, cvv, out, counts)
            else:
                surely = smin[order] < ss.S0 * (1.0 - BORDER)
                coarse = order[~surely]
                self._tiled(np.zeros((1, 1)), ss.NO_CELLS, coarse, uc, vc, cuu, cuv, cvv, out, counts)
                self._fine(np.concatenate([order[surely], coarse[counts[coarse] == -1]]), uc, vc, cuu, cuv, cvv, out, counts)
        return out, counts

    def integrate_small(self, prior: TerrainPrior, means: np.ndarray, covs: np.ndarray, max_rho: float, max_spread: float
                        ) -> np.ndarray | None:
        """:func:`~tracker.integrate.scalespace.integrate_small` on this pyramid: the integrals of a small
        batch of checked Gaussians (metres, on ``prior``'s grid, whose pyramid this is) when every one is finer than level 0,
        near the grid and not tiny, and the cells it reads are in memory (the field, or a padded block
        already held); ``None`` otherwise, and the caller takes the general path. The same kernel on the
        same pixel Gaussians and windows as :meth:`_fine`, so the same numbers; it skips the general
        path's sort, grouping and numpy steps (~45 µs a call against ~13 µs on a whole pyramid: the
        tracker's refreshes and widened gates make ~14,000 such calls on a 1 M-report stream)."""
        n = means.shape[0]
        top, px = ss.small_batch_pixels(prior, means, covs, max_rho, max_spread)
        if not (0.0 <= top < ss.S0 * (1.0 - BORDER)):
            return None
        uc, vc, cuu, cuv, cvv = px
        with self._lock:
            if not self._geometry:
                return None
            if self.field is not None:
                values, frames, which = self.field, ss.whole_frame(self.field), ss.ALL_FRAME_0
            else:
                if self._pads.shape[0] == 0:
                    return None
                block, fits = self._home_blocks(uc, vc, ss.fine_reach(cuu, cuv, cvv))
                which = self._pad_slot_of[block]
                if not fits.all() or which.min() < 0:
                    return None
                self._pad_clock += 1
                self._pad_used[which] = self._pad_clock
                values, frames = self._pads, self._pad_frames
            p = self.packed()
            out = np.empty(n)
            counts = np.empty(n, np.int64)
            ss._kernel(values, frames, which, ss.PHI_TABLE, p.coef, self.slots, p.scale, p.step, p.u0, p.v0, p.nu, p.nv,
                       p.offset, uc, vc, cuu, cuv, cvv, np.arange(n), out, counts, nb.get_num_threads())
        if counts.min() <= 0 or not np.isfinite(out).all():
            return None
        return out

    def _tiled(self, values, frames, todo, uc, vc, cuu, cuv, cvv, out, counts) -> None:
        """Integrals ``todo`` (kernel order) with their tiles built, widening the plan for any whose
        look-ups found a block missing (NaN); ``values``/``frames``: the cells for Gaussians finer than
        level 0 (:func:`~tracker.integrate.scalespace._window`)."""
        if not todo.size:
            return
        with _threads(_threads_for(todo.size)):
            for widen in (0, 1, 2):
                if not todo.size:
                    break
                self._run(values, frames, todo, uc, vc, cuu, cuv, cvv, widen, out, counts)
                todo = todo[np.isnan(out[todo]) & (counts[todo] >= 0)]
        if todo.size:
            raise RuntimeError(f"LazyPyramid: {todo.size} integrals still miss tiles after widening the plan")

    def _fine(self, idx: np.ndarray, uc, vc, cuu, cuv, cvv, out, counts) -> None:
        """Integrals ``idx``, which the kernel takes as finer than level 0 (they read cells, no tiles),
        smoothed from windows of the source: those whose reach (:func:`~tracker.integrate.scalespace.fine_reach`)
        fits the padded block of their mean from the kept padded blocks (:meth:`_padded_runs`), the
        others from windows made for them (:meth:`_fine_windows`); one kernel call per run or stack."""
        if not idx.size:
            return
        p = self.packed()
        reach = ss.fine_reach(cuu[idx], cuv[idx], cvv[idx])
        block, fits = self._home_blocks(uc[idx], vc[idx], reach)
        runs = itertools.chain(self._padded_runs(idx[fits], block[fits]),
                               self._fine_windows(idx[~fits], uc, vc, reach[~fits]))
        for values, frames, order, which in runs:
            with _threads(_threads_for(order.size)):
                ss._kernel(values, frames, which, ss.PHI_TABLE, p.coef, self.slots, p.scale, p.step, p.u0, p.v0, p.nu, p.nv,
                           p.offset, uc, vc, cuu, cuv, cvv, order, out, counts, nb.get_num_threads())

    def _home_blocks(self, u: np.ndarray, v: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point (pixels): its :data:`CELL_BLOCK` block (row-major number) and whether the cells within
        ``reach`` of it (the window :func:`window_groups` would give it alone) lie in that block padded by
        :data:`PAD` cells a side (clipped to the grid); :func:`home_blocks`."""
        return home_blocks(u, v, reach, self.shape[0], self.shape[1], CELL_BLOCK, PAD)

    def _padded_runs(self, idx: np.ndarray, block: np.ndarray) -> Iterator[tuple[np.ndarray, ...]]:
        """(values, frames, order, which) for the Gaussians ``idx`` by their padded blocks ``block``: runs
        of at most the pool's blocks, each block made once from the source into a slot of a pool kept
        between batches (least recently used out first), the pool and its frames the kernel's ``values``
        and ``frames``, ``which`` each Gaussian's slot. A batch whose blocks are all held is one run
        with no grouping (the common case of a stream that stays where it was)."""
        if not idx.size:
            return
        b, side = CELL_BLOCK, CELL_BLOCK + 2 * PAD
        (h, w), across = self.shape, (self.shape[1] - 1) // CELL_BLOCK + 1
        if self._pads.shape[0] == 0:
            n = max(PAD_CACHE_BYTES // (8 * side * side), 2)
            self._pads = huge_zeros((n * side, side), np.float64)
            self._pad_frames = np.zeros((n, 4), np.int64)
            self._pad_slot_of = np.full(((h - 1) // b + 1) * across, -1, np.int64)
            self._pad_key = np.full(n, -1, np.int64)
            self._pad_used = np.zeros(n, np.int64)
        n = self._pad_frames.shape[0]
        held = self._pad_slot_of[block]
        if held.min() >= 0:
            self._pad_clock += 1
            self._pad_used[held] = self._pad_clock
            yield self._pads, self._pad_frames, idx, held
            return
        blocks, which = np.unique(block, return_inverse=True)
        order = np.argsort(which, kind="stable")
        first = np.searchsorted(which[order], np.arange(blocks.size + 1))
        for lo in range(0, blocks.size, n):
            hi = min(lo + n, blocks.size)
            self._pad_clock += 1
            slots = self._pad_slot_of[blocks[lo:hi]]
            self._pad_used[slots[slots >= 0]] = self._pad_clock
            miss = np.flatnonzero(slots < 0)
            # empty slots first, then the least recently used of those this run does not hold
            free = np.flatnonzero(self._pad_used < self._pad_clock)
            free = free[np.lexsort((self._pad_used[free], self._pad_key[free] >= 0))][: miss.size]
            fills = []
            for i, slot in zip(miss.tolist(), free.tolist(), strict=True):
                if self._pad_key[slot] >= 0:  # its block is overwritten: no longer held
                    self._pad_slot_of[self._pad_key[slot]] = -1
                    self._pad_key[slot] = -1
                br, bc = divmod(int(blocks[lo + i]), across)
                r0, r1 = max(br * b - PAD, 0), min(br * b + b + PAD, h)
                c0, c1 = max(bc * b - PAD, 0), min(bc * b + b + PAD, w)
                fills.append((self._pads[slot * side : slot * side + r1 - r0, : c1 - c0], r0, r1, c0, c1))
                self._pad_frames[slot] = (r0 - slot * side, c0, h, w)
                slots[i] = slot
            self._fill(fills)
            for i in miss.tolist():  # held only once filled, so a failed read leaves no block half-made
                slot, key = slots[i], int(blocks[lo + i])
                self._pad_key[slot], self._pad_slot_of[key], self._pad_used[slot] = key, slot, self._pad_clock
            members = order[first[lo] : first[hi]]
            yield self._pads, self._pad_frames, idx[members], slots[which[members] - lo]

    def _fill(self, fills: list[tuple[np.ndarray, int, int, int, int]]) -> None:
        """Each (view, r0, r1, c0, c1): the values (r or r²) of cells [r0, r1) x [c0, c1) read straight
        into ``view`` (a padded block's slot), on the tile threads when there are several (the reads
        and the first touches of the slots' pages then use both cores)."""
        def fill(job: tuple[np.ndarray, int, int, int, int]) -> None:
            view, r0, r1, c0, c1 = job
            read_cells(self.source, self.squared, r0, r1, c0, c1, out=view)

        threads = nb.get_num_threads()
        list(_tile_threads(threads).map(fill, fills) if threads > 1 and len(fills) > 1 else map(fill, fills))  # raises the first error
        self.cells_read += sum(view.size for view, *_ in fills)

    def _fine_windows(self, idx: np.ndarray, uc, vc, reach: np.ndarray) -> Iterator[tuple[np.ndarray, ...]]:
        """The Gaussians ``idx`` (finer than level 0) grouped by block of :data:`FINE_BLOCK` cells of
        their means, each group with the source's cells that its Gaussians' on-the-fly smoothing reads
        (``reach``, :func:`~tracker.integrate.scalespace.fine_reach`: 5 σ_minor around its rule's
        points), so they are the numbers of the whole field. Yields (values, frames,
        order, which) per run of groups whose windows fit :data:`STACK_BYTES` (or one larger window):
        their windows stacked (:func:`~tracker.integrate.scalespace.stacked_frames`), their Gaussians
        in group order and the frame of each."""
        if not idx.size:
            return
        order, group, bounds = window_groups(uc[idx], vc[idx], reach, reach, self.shape, FINE_BLOCK)
        size = 8 * (bounds[:, 1] - bounds[:, 0]) * (bounds[:, 3] - bounds[:, 2])
        first = np.searchsorted(group, np.arange(bounds.shape[0] + 1))  # each group's first position in order
        lo = 0
        while lo < bounds.shape[0]:
            hi = lo + max(1, int(np.searchsorted(np.cumsum(size[lo:]), STACK_BYTES, side="right")))
            values, frames, views = ss.stacked_frames(bounds[lo:hi], self.shape)
            for view, (r0, r1, c0, c1) in zip(views, bounds[lo:hi].tolist(), strict=True):
                if r1 > r0 and c1 > c0:
                    self._cached_cells(r0, r1, c0, c1, view)
            yield values, frames, idx[order[first[lo] : first[hi]]], group[first[lo] : first[hi]] - lo
            lo = hi

    def _tiles_of(self, idx: np.ndarray, uc, vc, cuu, cuv, cvv, widen: int) -> np.ndarray:
        """Keys k << 40 | tv << 20 | tu of the tiles the Gaussians ``idx`` read (their level ± ``widen``),
        sorted, each once (:func:`_plan`)."""
        g = self._geometry
        geometry = np.array([(x[0], x[1], x[2], x[3], x[4], self._side(k)) for k, x in enumerate(g)], np.float64)
        keys = _plan(uc, vc, cuu, cuv, cvv, idx, geometry, widen, (ss.S0 * (1.0 - BORDER)) ** 2)
        return np.unique(keys)

    def _run(self, field, frames, todo, uc, vc, cuu, cuv, cvv, widen, out, counts) -> None:
        """Integrals ``todo`` (in kernel order), in chunks whose tiles fit half the pool at once; ``field``
        and ``frames``: the cells fine Gaussians read (:func:`~tracker.integrate.scalespace._window`)."""
        room = self.n_slots // 2
        side = np.array([self.level_blocks(k) for k in range(len(self._geometry))], np.int64)  # blocks per tile side
        blocks = side**2
        toff = np.array([g[6] for g in self._geometry], np.int64)
        nbu = np.array([g[5] for g in self._geometry], np.int64)
        stack = [todo]
        while stack:
            chunk = stack.pop()
            need = self._tiles_of(chunk, uc, vc, cuu, cuv, cvv, widen)
            if blocks[need >> 40].sum() > room and chunk.size > 1:
                half = chunk.size // 2
                stack += [chunk[half:], chunk[:half]]
                continue
            k, tv, tu = need >> 40, (need >> 20) & 0xFFFFF, need & 0xFFFFF
            # a tile is built when its first block is (they are put in and evicted together)
            built = self.slots[toff[k] + tv * side[k] * nbu[k] + tu * side[k]] != MISSING
            ids = self._tile_ids(k, tv, tu)
            try:
                # The tiles already built are pinned first, so building the others cannot evict them.
                self._pin(ids[built], blocks[k[built]])
                missing = [(int(a), int(b), int(c)) for a, b, c in zip(k[~built], tv[~built], tu[~built], strict=True)]
                self._build_cell_tiles(missing)
                for key, i in zip(missing, ids[~built], strict=True):
                    self.tile(*key)
                    self._pin(i[None], blocks[key[0] : key[0] + 1])
                p = self.packed()
                out[chunk] = np.nan  # stays NaN only if the kernel found a block missing
                ss._kernel(field, frames, ss.ALL_FRAME_0, ss.PHI_TABLE, p.coef, self.slots, p.scale, p.step, p.u0, p.v0, p.nu, p.nv, p.offset,
                           uc, vc, cuu, cuv, cvv, chunk, out, counts, nb.get_num_threads())
            finally:
                self._unpin()


@contextmanager
def _threads(n: int) -> Iterator[None]:
    """numba's thread count set to ``n`` within the block (numba keeps it per calling thread)."""
    before = nb.get_num_threads()
    if n == before:  # the common case of small batches on one thread: setting it costs ~4 µs a call
        yield
        return
    nb.set_num_threads(n)
    try:
        yield
    finally:
        nb.set_num_threads(before)


@functools.cache
def _tile_threads(n: int) -> ThreadPoolExecutor:
    """The ``n`` threads the lazy pyramids build their cell-level tiles on (made once, kept)."""
    return ThreadPoolExecutor(n, thread_name_prefix="lazy-tiles")


def _threads_for(size: int) -> int:
    """Threads for a kernel call of ``size`` integrals: one below :data:`SERIAL_BELOW` (a parallel launch
    costs more than small batches), else the caller's."""
    return 1 if size < SERIAL_BELOW else nb.get_num_threads()


def window_groups(u: np.ndarray, v: np.ndarray, reach_u: np.ndarray, reach_v: np.ndarray, shape: tuple[int, int],
                  block: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points (u, v) (pixels) grouped by the ``block``-cell square of the grid they fall in (off-grid
    ones in the border squares): (order, group, bounds). ``order`` lists the points group by group,
    ``group[i]`` is the group of point ``order[i]``, and ``bounds[g]`` = (r0, r1, c0, c1) the window of
    cells, clipped to the (H, W) grid, that covers every point of group g ± its reach (cells
    [floor(v - reach_v), floor(v + reach_v)] ...)."""
    h, w = shape
    keys = np.clip(np.floor(v / block), -1, h // block + 1) * (w // block + 3) + np.clip(np.floor(u / block), -1, w // block + 1)
    order = np.argsort(keys, kind="stable")
    new = np.r_[True, np.diff(keys[order]) != 0] if order.size else np.zeros(0, bool)
    starts = np.flatnonzero(new)
    group = np.cumsum(new) - 1
    uo, vo, ru, rv = u[order], v[order], reach_u[order], reach_v[order]
    bounds = np.empty((starts.size, 4), np.int64)
    if starts.size:
        bounds[:, 0] = np.clip(np.floor(np.minimum.reduceat(vo - rv, starts)), 0, h)
        bounds[:, 1] = np.clip(np.floor(np.maximum.reduceat(vo + rv, starts)) + 1, bounds[:, 0], h)
        bounds[:, 2] = np.clip(np.floor(np.minimum.reduceat(uo - ru, starts)), 0, w)
        bounds[:, 3] = np.clip(np.floor(np.maximum.reduceat(uo + ru, starts)) + 1, bounds[:, 2], w)
    return order, group, bounds


@nb.njit(cache=True, inline="always")
def _home_axis(x: float, reach: float, n: int, b: int, pad: int):
    """One axis of :func:`home_blocks`: the block of x and whether [floor(x - reach), floor(x + reach) + 1),
    clipped to [0, n], lies within that block's cells padded by ``pad`` (clipped to [0, n])."""
    k = int(min(max(math.floor(x / b), 0.0), float((n - 1) // b)))
    lo = min(max(math.floor(x - reach), 0.0), float(n))
    hi = min(max(math.floor(x + reach) + 1.0, 0.0), float(n))
    return k, lo >= max(k * b - pad, 0) and hi <= min(k * b + b + pad, n)


@nb.njit(cache=True)
def home_blocks(u, v, reach, h: int, w: int, b: int, pad: int):
    """(block, fits) of :meth:`LazyPyramid._home_blocks` for points (u, v) (pixels) on an (h, w) grid of
    ``b``-cell blocks (row-major block numbers; :func:`_home_axis` per axis)."""
    m = u.shape[0]
    block = np.empty(m, np.int64)
    fits = np.empty(m, np.bool_)
    across = (w - 1) // b + 1
    for i in range(m):
        kv, fit_v = _home_axis(v[i], reach[i], h, b, pad)
        ku, fit_u = _home_axis(u[i], reach[i], w, b, pad)
        block[i] = kv * across + ku
        fits[i] = fit_v and fit_u
    return block, fits


def huge_zeros(shape: tuple[int, ...], dtype) -> np.ndarray:
    """A zeroed array on private anonymous memory advised for transparent huge pages (Linux ``madvise``
    mode): a pool filled block by block then faults 2 MiB pages, not 4 KiB ones (first touches are much
    of a cold tile's insertion; 1 GiB touched again: 0.10 s against 0.58 s on the bench VM). Private,
    because a shared anonymous mapping is shmem, whose huge pages are off by default."""
    count = int(np.prod(shape))
    size = max(count * np.dtype(dtype).itemsize, 1)
    buf = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS) if hasattr(mmap, "MAP_PRIVATE") else mmap.mmap(-1, size)
    if hasattr(mmap, "MADV_HUGEPAGE"):
        buf.madvise(mmap.MADV_HUGEPAGE)
    return np.frombuffer(buf, dtype, count=count).reshape(shape)


def read_cells(source: CellSource, squared: bool, r0: int, r1: int, c0: int, c1: int, out: np.ndarray | None = None
               ) -> np.ndarray:
    """The float64 values (r, or r² when ``squared``) of cells [r0, r1) x [c0, c1) of ``source``; read
    straight into ``out`` (float64, that shape) if given."""
    if out is None:
        values = np.ascontiguousarray(source[r0:r1, c0:c1], dtype=np.float64)
        return values * values if squared else values
    out[...] = source[r0:r1, c0:c1]
    return np.multiply(out, out, out=out) if squared else out


def _prefiltered(values, nu: int, nv: int):
    """``coefficients(r_lo, r_hi, c_lo, c_hi)`` for :func:`_padded_coefficients` from the node values of
    a level with an (nv, nu) lattice on a window, ``values(j0, j1, i0, i1)``: the finite prefilter over
    them (float32)."""

    def coefficients(r_lo: int, r_hi: int, c_lo: int, c_hi: int) -> np.ndarray:
        fsv, fwv = ss._fir_weights(r_lo, r_hi, nv)
        fsu, fwu = ss._fir_weights(c_lo, c_hi, nu)
        w_v0, w_u0 = int(fsv[0]), int(fsu[0])
        window = values(w_v0, int(fsv[-1]) + fwv.shape[1], w_u0, int(fsu[-1]) + fwu.shape[1])
        return ss._separable(window, fsu - w_u0, fwu, fsv - w_v0, fwv).astype(np.float32)

    return coefficients


def _padded_coefficients(coefficients, nu: int, nv: int, side: int, tv0: int, tv1: int, tu0: int, tu1: int) -> list[np.ndarray]:
    """Tiles (tv, tu), tv0 <= tv <= tv1, tu0 <= tu <= tu1 (``side`` nodes a side, rows first) of a level
    with an (nv, nu) lattice: their cubic B-spline coefficients with the one-before, two-after apron,
    zeros beyond the lattice (as ``scalespace._tile``), float32 (side + 3)² each, from one call of
    ``coefficients(r_lo, r_hi, c_lo, c_hi)`` (float32 at those nodes: :func:`_prefiltered`, or
    ``scalespace.fused_coefficients``) for the rectangle (each node's bands and weights are the whole
    lattice's, so a rectangle's tiles are the numbers of tiles built one by one)."""
    # The rectangle's coefficient nodes with their aprons, within the lattice.
    r_lo, r_hi = max(tv0 * side - 1, 0), min((tv1 + 1) * side + 2, nv)
    c_lo, c_hi = max(tu0 * side - 1, 0), min((tu1 + 1) * side + 2, nu)
    coef = coefficients(r_lo, r_hi, c_lo, c_hi)
    tiles = []
    for tv in range(tv0, tv1 + 1):
        av = tv * side
        a0, a1 = max(av - 1, 0), min(av + side + 2, nv)
        for tu in range(tu0, tu1 + 1):
            au = tu * side
            b0, b1 = max(au - 1, 0), min(au + side + 2, nu)
            padded = np.zeros((side + 3, side + 3), np.float32)
            padded[a0 - av + 1 : a1 - av + 1, b0 - au + 1 : b1 - au + 1] = coef[a0 - r_lo : a1 - r_lo, b0 - c_lo : b1 - c_lo]
            tiles.append(padded)
    return tiles


def cell_tiles(source: CellSource, squared: bool, shape: tuple[int, int], k: int, tv0: int, tv1: int, tu0: int, tu1: int,
               side: int) -> tuple[list[np.ndarray], int]:
    """Tiles (tv, tu), tv0 <= tv <= tv1, tu0 <= tu <= tu1 (rows first) of a cell level k < CELL_LEVELS of
    the lazy pyramid of ``source`` (r, or r² when ``squared``) on an (H, W) grid, from the source's cells
    alone, read once for the rectangle: (:func:`_padded_coefficients`, cells read). A pure function of
    its arguments, so a Dask worker can build it (a windowed density is picklable: the worker reopens
    the file)."""
    s, h, origin, nu, nv = ss.lattice(k, shape)
    read = [0]

    def cells(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        window = read_cells(source, squared, r0, r1, c0, c1)
        read[0] += window.size
        return window

    def values(j0: int, j1: int, i0: int, i1: int) -> np.ndarray:
        su, wu = ss._box_weights(origin + h * np.arange(i0, i1), shape[1], s)
        sv, wv = ss._box_weights(origin + h * np.arange(j0, j1), shape[0], s)
        c0, r0 = int(su.min()), int(sv.min())
        return ss._separable(cells(r0, int(sv.max()) + wv.shape[1], c0, int(su.max()) + wu.shape[1]), su - c0, wu, sv - r0, wv)

    if k < ss.FUSED_LEVELS:
        def coefficients(r_lo: int, r_hi: int, c_lo: int, c_hi: int) -> np.ndarray:
            return ss.fused_coefficients(cells, k, shape, (r_lo, r_hi), (c_lo, c_hi))
    else:
        coefficients = _prefiltered(values, nu, nv)
    with _threads(1):  # a tile's kernels are short: one thread each (a worker's threads share the cores)
        return _padded_coefficients(coefficients, nu, nv, side, tv0, tv1, tu0, tu1), read[0]


def rectangles(keys: list[tuple[int, int, int]], most: int) -> list[tuple[int, int, int, int, int]]:
    """Tiles (k, tv, tu) as rectangles (k, tv0, tv1, tu0, tu1) of at most ``most`` tiles a side that
    cover exactly them: runs along rows, then runs of equal rows stacked."""
    runs: list[list[int]] = []
    for k, tv, tu in sorted(set(keys)):
        last = runs[-1] if runs else None
        if last and (last[0], last[1]) == (k, tv) and last[3] == tu - 1 and tu - last[2] < most:
            last[3] = tu
        else:
            runs.append([k, tv, tu, tu])
    out: dict[tuple[int, int, int], list[int]] = {}  # open rectangles by (level, first and last column)
    done = []
    for k, tv, tu0, tu1 in runs:
        rect = out.get((k, tu0, tu1))
        if rect and rect[2] == tv - 1 and tv - rect[1] < most:
            rect[2] = tv
        else:
            if rect:
                done.append(rect)
            out[(k, tu0, tu1)] = [k, tv, tv, tu0, tu1]
    return [tuple(r) for r in done + list(out.values())]


@nb.njit(cache=True, nogil=True)
def _plan(uc, vc, cuu, cuv, cvv, idx, geometry, widen, fine2):
    """Keys k << 40 | tv << 20 | tu of the tiles each Gaussian ``idx[i]`` reads at its level ± ``widen``
    (rows of ``geometry``: s, h, origin, nu, nv, tile side in nodes per level), with repeats: a
    Gaussian's level from its smaller σ (the kernel's rule), its reach GH_SPAN (1 + widen) times the
    leftover σ along both axes, plus 3 h and the spline's 2-before, 3-after nodes. Gaussians with
    λ₂ < ``fine2`` read cells, not tiles. A range equal to the one before it on its level (the
    kernel's order puts neighbours together) is not emitted again."""
    top = geometry.shape[0] - 1
    log_ratio = np.log(ss.RATIO)
    out = np.empty(max(64, 4 * idx.shape[0]), np.int64)
    n_out = 0
    last = np.full((geometry.shape[0], 4), -1, np.int64)
    for i in range(idx.shape[0]):
        n = idx[i]
        a, b, c = cuu[n], cuv[n], cvv[n]
        m = 0.5 * (a + c)
        dd = 0.5 * (a - c)
        rad = np.sqrt(dd * dd + b * b)
        lam1 = m + rad
        lam2 = max(m - rad, 0.0)
        if lam2 < fine2:
            continue
        k0 = min(max(int(np.floor(np.log(np.sqrt(lam2) / ss.S0) / log_ratio + 1e-9)), 0), top)
        for dk in range(-widen, widen + 1):
            k = min(max(k0 + dk, 0), top)
            s, h, origin, nu, nv, side = geometry[k]
            r = GH_SPAN * (1 + widen) * (np.sqrt(max(lam1 - s * s, 0.0)) + np.sqrt(max(lam2 - s * s, 0.0))) + 3 * h
            lo_u = int(min(max(np.floor((uc[n] - r - origin) / h) - 2, 0.0), nu - 1)) // int(side)
            hi_u = int(min(max(np.floor((uc[n] + r - origin) / h) + 3, 0.0), nu - 1)) // int(side)
            lo_v = int(min(max(np.floor((vc[n] - r - origin) / h) - 2, 0.0), nv - 1)) // int(side)
            hi_v = int(min(max(np.floor((vc[n] + r - origin) / h) + 3, 0.0), nv - 1)) // int(side)
            if last[k, 0] == lo_u and last[k, 1] == hi_u and last[k, 2] == lo_v and last[k, 3] == hi_v:
                continue
            last[k, 0], last[k, 1], last[k, 2], last[k, 3] = lo_u, hi_u, lo_v, hi_v
            grow = (hi_u - lo_u + 1) * (hi_v - lo_v + 1)
            if n_out + grow > out.shape[0]:
                bigger = np.empty(2 * (n_out + grow), np.int64)
                bigger[:n_out] = out[:n_out]
                out = bigger
            for tv in range(lo_v, hi_v + 1):
                for tu in range(lo_u, hi_u + 1):
                    out[n_out] = (np.int64(k) << 40) | (np.int64(tv) << 20) | tu
                    n_out += 1
    return out[:n_out]


@nb.njit(cache=True, nogil=True)
def _store_blocks(pool, slots, padded, keep_v, keep_u):
    """Blocks (a, b), a in ``keep_v``, b in ``keep_u`` (rows first), of a tile's ``padded`` coefficients
    (:func:`_padded_coefficients`: each block its :data:`~tracker.integrate.scalespace.TILE` nodes and
    the 3-node apron) into pool rows ``slots``, in that order."""
    t = _T
    width = t + 3
    n = 0
    for a in keep_v:
        for b in keep_u:
            row = pool[slots[n]]
            for r in range(width):
                for c in range(width):
                    row[r * width + c] = padded[a * t + r, b * t + c]
            n += 1


@nb.njit(cache=True)
def _copy_blocks(pool, slots, toff, nbu, blocks, tv, tu, j0, j1, i0, i1, out):
    """Copy the interiors of tile (tv, tu)'s ``blocks`` x ``blocks`` blocks that fall in nodes [j0, j1) x [i0, i1) into ``out``."""
    t = _T
    width = t + 3
    for bv in range(tv * blocks, (tv + 1) * blocks):
        for bu in range(tu * blocks, (tu + 1) * blocks):
            if bu >= nbu:
                continue
            rv0, rv1 = max(bv * t, j0), min(bv * t + t, j1)
            ru0, ru1 = max(bu * t, i0), min(bu * t + t, i1)
            if rv0 >= rv1 or ru0 >= ru1:
                continue
            slot = slots[toff + bv * nbu + bu]
            for r in range(rv0, rv1):
                base = (r - bv * t + 1) * width + 1 - bu * t
                for c in range(ru0, ru1):
                    out[r - j0, c - i0] = pool[slot, base + c]


_LAZY: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_LAZY_LOCK = threading.Lock()


_CLIENT: list[Client | None] = [None]


@contextmanager
def tile_client(client: Client | None) -> Iterator[None]:
    """Within the block, the lazy pyramids of :func:`lazy_pyramid` build their cell-level tiles on
    ``client``'s workers (None: in this process, the default)."""
    before = _CLIENT[0]
    _CLIENT[0] = client
    try:
        yield
    finally:
        _CLIENT[0] = before


def lazy_pyramid(prior: TerrainPrior, squared: bool) -> LazyPyramid:
    """The prior's lazy pyramid of r (or r²), made once per prior object and kept while it lives; its
    cells are read from ``prior.density`` (an array, a memmap or a windowed density). Gaussians finer
    than the finest level read the density in memory as the whole pyramid does, or windows of a
    windowed density around them (the same numbers)."""
    with _LAZY_LOCK:
        per_prior = _LAZY.setdefault(prior, {})
        if squared not in per_prior:
            field = None
            if isinstance(prior.density, np.ndarray):
                field = np.asarray(prior.density, dtype=np.float64)
                field = field * field if squared else field
            per_prior[squared] = LazyPyramid(prior.density, squared, field=field)
        per_prior[squared].client = _CLIENT[0]
        return per_prior[squared]
