"""The lazy, tiled pyramid against the whole in-memory pyramid: the same integrals, bit for bit.

Oracle: :class:`tracker.integrate.scalespace.Pyramid` (itself checked against direct sums and the
dense reference in test_scalespace.py), on small priors cut into tiny tiles (one or two 32-node
blocks) with caches small enough to evict.
"""

from __future__ import annotations

import threading
import warnings
from pathlib import Path

import numba as nb
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.prior import TerrainPrior
from tests.tracker.integrate.test_terraces import (
    CELL,
    GRID,
    ROUGH,
    H,
    W,
    random_gaussians,
    rough_field,
    thin_gaussians,
)
from tracker.integrate import integrate, lazy, scalespace
from tracker.integrate.terraces import pixel_gaussians


def pixel_batch(shape: tuple[int, int], n: int, seed: int, smallest: float = 0.3, largest: float = 30.0):
    """``n`` Gaussians in pixel units over (and a little beyond) a grid of ``shape``: σ log-uniform in
    [smallest, largest] cells, eccentricity up to e³, any angle."""
    rng = np.random.default_rng(seed)
    h, w = shape
    uc, vc = rng.uniform(-5, w + 5, n), rng.uniform(-5, h + 5, n)
    sig = np.exp(rng.uniform(np.log(smallest), np.log(largest), n))
    ecc, th = np.exp(rng.uniform(0, 3, n)), rng.uniform(0, np.pi, n)
    c, s = np.cos(th), np.sin(th)
    l1, l2 = (sig * ecc) ** 2, sig**2
    return uc, vc, c * c * l1 + s * s * l2, c * s * (l1 - l2), s * s * l1 + c * c * l2


def whole_integrals(field: np.ndarray, px) -> tuple[np.ndarray, np.ndarray]:
    """The whole pyramid's integrals of ``field`` (the path of scalespace.integrate_pixels), on one
    thread (these grids are small: parallel launches would cost more than the work)."""
    threads = nb.get_num_threads()
    nb.set_num_threads(1)
    try:
        return _whole(field, px)
    finally:
        nb.set_num_threads(threads)


def _whole(field: np.ndarray, px) -> tuple[np.ndarray, np.ndarray]:
    pyr = scalespace.Pyramid(field)
    n = px[0].shape[0]
    smin, keys = np.empty(n), np.empty(n, np.int64)
    scalespace._order_keys(*px, *field.shape, scalespace.ORDER_TILE, smin, keys)
    p = pyr.levels(float(smin.max()))
    out, counts = np.empty(n), np.empty(n, np.int64)
    slots, offset = pyr.slots(p)
    scalespace._kernel(pyr.field, scalespace.whole_frame(pyr.field), scalespace.ALL_FRAME_0, scalespace.PHI_TABLE, p.coef, slots, p.scale, p.step, p.u0, p.v0,
                       p.nu, p.nv, offset, *px, np.argsort(keys), out, counts, 1)
    return out, counts


class Mosaic:
    """A cell source that is not an array: one tile repeated, read window by window."""

    def __init__(self, tile: np.ndarray, reps: tuple[int, int]) -> None:
        self.tile = tile
        self.shape = (tile.shape[0] * reps[0], tile.shape[1] * reps[1])
        self.dtype = tile.dtype

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = (np.arange(*k.indices(n)) for k, n in zip(key, self.shape, strict=True))
        return self.tile[np.ix_(rows % self.tile.shape[0], cols % self.tile.shape[1])]


@settings(max_examples=15, deadline=None)
@given(
    shape=st.tuples(st.integers(8, 90), st.integers(8, 120)),
    seed=st.integers(0, 2**16),
    blocks=st.sampled_from([1, 2]),
    squared=st.booleans(),
)
def test_lazy_tiles_equal_the_whole_pyramid(shape, seed, blocks, squared) -> None:
    field = rough_field(seed=seed % 7, shape=shape)
    values = field * field if squared else field
    px = pixel_batch(shape, 200, seed)
    want, want_counts = whole_integrals(values, px)
    pyr = lazy.LazyPyramid(field, squared, cache_bytes=4 << 20, field=values, blocks=blocks)
    got, counts = pyr.integrate_pixels(*px)
    np.testing.assert_array_equal(counts, want_counts)
    ok = counts > 0
    np.testing.assert_array_equal(got[ok], want[ok])


def test_coefficients_equal_the_whole_pyramid_level_by_level() -> None:
    field = rough_field(seed=3, shape=(70, 90))
    p = scalespace.Pyramid(field).levels(20.0)
    pyr = lazy.LazyPyramid(field, cache_bytes=64 << 20, blocks=1)
    pyr._grow(20.0)
    assert pyr.levels_built() == p.scale.size
    for k in range(p.scale.size):
        nv, nu = int(p.nv[k]), int(p.nu[k])
        whole = scalespace._untile(p.coef[p.offset[k] : p.offset[k + 1]], (nv, nu))
        got = pyr.window(k, 0, nv, 0, nu)
        # Cell sums, trapezoid sums and the finite prefilter are local: the same numbers everywhere.
        np.testing.assert_array_equal(got, whole, err_msg=f"level {k}")


def test_an_evicting_cache_rebuilds_the_same_numbers() -> None:
    field = rough_field(seed=2, shape=(80, 110))
    px = pixel_batch(field.shape, 300, seed=5, smallest=1.0, largest=6.0)
    want, _ = whole_integrals(field, px)
    roomy = lazy.LazyPyramid(field, cache_bytes=64 << 20, blocks=1)
    tight = lazy.LazyPyramid(field, cache_bytes=400_000, blocks=1)
    for pyr in (roomy, tight):
        for _ in range(2):  # a second pass finds its tiles cached, or rebuilds the evicted ones
            got, counts = pyr.integrate_pixels(*px)
            np.testing.assert_array_equal(got[counts > 0], want[counts > 0])
    assert tight.tiles_built > roomy.tiles_built  # it did evict and rebuild
    assert tight.pool.nbytes <= 400_000


def test_a_source_read_window_by_window_gives_the_same_integrals() -> None:
    tile = rough_field(seed=4, shape=(23, 31))
    mosaic = Mosaic(tile, (3, 4))
    field = np.tile(tile, (3, 4))
    px = pixel_batch(field.shape, 200, seed=7, smallest=1.0)  # no Gaussian finer than level 0: no field needed
    got, counts = lazy.LazyPyramid(mosaic, blocks=2).integrate_pixels(*px)
    want, want_counts = whole_integrals(field, px)
    np.testing.assert_array_equal(counts, want_counts)
    np.testing.assert_array_equal(got[counts > 0], want[counts > 0])


@pytest.mark.parametrize(("cache_blocks", "stack_bytes", "fine_block", "pad"),
                         [(None, None, 128, "off"), (1, None, 128, "off"), (None, 1, 128, "off"), (None, 1_000_000, 128, "off"),
                          (None, None, 1, "off"), (None, None, 128, 4), (None, None, 128, None), (1, None, 128, 200)])
@pytest.mark.parametrize("squared", [False, True])
def test_without_a_field_fine_gaussians_read_windows_of_the_source(squared, cache_blocks, stack_bytes, fine_block, pad,
                                                                   monkeypatch) -> None:
    """A source that is not an array (a prior read window by window): Gaussians finer than the pyramid
    are smoothed from windows of it (assembled from cached source blocks, evicted when the cache holds
    one), in several blocks of means, stacked for one kernel call, one per call or a few, with the
    whole field's numbers; with one-cell blocks, nearly every window is one Gaussian's own reach
    (scalespace.fine_reach), stacked between others: any cell read beyond it would be another's. With
    padded blocks (``pad`` cells; None: the default), the Gaussians whose reach fits read them in
    place: none ("off": no block can hold a window), some (4), most, or all from a pool of two (evicting)."""
    monkeypatch.setattr(lazy, "FINE_BLOCK", fine_block)
    if pad is not None:
        monkeypatch.setattr(lazy, "PAD", -(10**6) if pad == "off" else pad)
    if stack_bytes:
        monkeypatch.setattr(lazy, "STACK_BYTES", stack_bytes)
    if cache_blocks:
        monkeypatch.setattr(lazy, "CELL_CACHE_BYTES", cache_blocks * lazy.CELL_BLOCK**2 * 8)
        monkeypatch.setattr(lazy, "PAD_CACHE_BYTES", cache_blocks * (lazy.CELL_BLOCK + 2 * lazy.PAD) ** 2 * 8)
    tile = rough_field(seed=1, shape=(61, 70))
    source = Mosaic(tile, (7, 6))
    field = source[0 : source.shape[0], 0 : source.shape[1]]
    assert field.shape[0] > 1.5 * 128 and field.shape[1] > 1.5 * 128
    px = pixel_batch(field.shape, 3000, seed=3, smallest=0.1, largest=3.0)
    want, want_counts = whole_integrals(field * field if squared else field, px)
    pyr = lazy.LazyPyramid(source, squared, cache_bytes=1 << 24)
    got, counts = pyr.integrate_pixels(*px)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(counts, want_counts)
    smin = np.sqrt(0.5 * (px[2] + px[4]) - np.sqrt(0.25 * (px[2] - px[4]) ** 2 + px[3] ** 2))
    assert (smin < scalespace.S0).sum() > 1000 and pyr.cells_read < 40 * field.size
    assert bool((pyr._pad_key >= 0).any()) == (pad != "off")
    for lo in range(0, 3000, 1000):  # again, in batches: the padded blocks held (or evicted, from a pool of two)
        got, _ = pyr.integrate_pixels(*(a[lo : lo + 1000] for a in px))
        np.testing.assert_array_equal(got, want[lo : lo + 1000])


def test_a_failed_read_of_a_padded_block_holds_no_block() -> None:
    """A source read that fails while the padded blocks of a run are filled: the error reaches the
    caller, no slot claims the block it was filling, and the same batch again has the whole field's
    numbers."""

    class Flaky:
        def __init__(self, inner) -> None:
            self.inner, self.shape, self.failed = inner, inner.shape, False

        def __getitem__(self, key):
            window = (key[0].start, key[0].stop, key[1].start, key[1].stop)
            if not self.failed and window == (0, lazy.CELL_BLOCK + lazy.PAD, 0, lazy.CELL_BLOCK + lazy.PAD):
                self.failed = True
                raise OSError("read failed")
            return self.inner[key]

    inner = Mosaic(rough_field(seed=1, shape=(61, 70)), (7, 6))
    field = inner[0 : inner.shape[0], 0 : inner.shape[1]]
    px = pixel_batch(field.shape, 3000, seed=3, smallest=0.1, largest=3.0)
    want, _ = whole_integrals(field, px)
    source = Flaky(inner)
    pyr = lazy.LazyPyramid(source, cache_bytes=1 << 24)
    with pytest.raises(OSError, match="read failed") as failure:
        pyr.integrate_pixels(*px)
    assert source.failed and "_fill" in [entry.name for entry in failure.traceback]
    held = np.flatnonzero(pyr._pad_key >= 0)
    assert (pyr._pad_slot_of[pyr._pad_key[held]] == held).all()
    assert ((pyr._pad_slot_of < 0) | (pyr._pad_key[pyr._pad_slot_of.clip(0)] == np.arange(pyr._pad_slot_of.size))).all()
    assert pyr._pad_slot_of[0] == -1  # the block whose read failed
    got, _ = pyr.integrate_pixels(*px)
    np.testing.assert_array_equal(got, want)


def test_a_cache_too_small_for_one_gaussian_says_so() -> None:
    field = rough_field(seed=1, shape=(300, 300))
    px = pixel_batch(field.shape, 1, seed=1, smallest=60.0, largest=60.0)
    with pytest.raises(MemoryError, match="a cache of 0 MiB cannot hold the tiles one batch needs"):
        lazy.LazyPyramid(field, cache_bytes=1, blocks=1).integrate_pixels(*px)


def test_cell_tiles_past_the_pool_free_the_slots_they_claimed() -> None:
    """More missing cell-level tiles than the pool holds: MemoryError part-way through claiming their
    slots, with every slot free again and no tile in the tables."""
    pyr = lazy.LazyPyramid(rough_field(seed=1, shape=(300, 300)), cache_bytes=1 << 16, blocks=1)
    pyr._grow(1.0)
    free = len(pyr._free)
    keys = [(0, tv, tu) for tv in range(5) for tu in range(5)]
    assert len(keys) > pyr.n_slots
    with pytest.raises(MemoryError, match="cannot hold the tiles one batch needs"):
        pyr._build_cell_tiles(keys)
    assert len(pyr._free) == free and not pyr._tiles and (pyr.slots == lazy.MISSING).all()


def test_priors_above_the_size_limit_get_the_lazy_pyramid(monkeypatch) -> None:
    """integrate() on a grid above MAX_CELLS: the lazy pyramid, no warning, the whole pyramid's integrals."""
    means, covs = random_gaussians(GRID, 200, seed=4)
    want = integrate(ROUGH, means, covs)
    want2 = integrate(ROUGH, means, covs, squared=True)
    monkeypatch.setattr(scalespace, "MAX_CELLS", ROUGH.grid.height * ROUGH.grid.width - 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = integrate(ROUGH, means, covs)
        got2 = integrate(ROUGH, means, covs, squared=True)
    assert lazy.lazy_pyramid(ROUGH, False).tiles_built > 0
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got2, want2)
    assert pixel_gaussians(ROUGH, means, covs)[0].shape == (200,)


@pytest.mark.parametrize("windowed", [False, True])
def test_small_batches_on_the_lazy_pyramid_equal_the_general_path(windowed, monkeypatch) -> None:
    """LazyPyramid.integrate_small (batches under SMALL_BATCH on a prior above MAX_CELLS) gives the
    general path's values bit for bit, which are the whole in-memory pyramid's, from the field or (a
    windowed density) from the padded blocks held; it leaves to the general path every batch with a
    Gaussian it does not take: tiny, off the grid, coarser than level 0, before any level is made, or
    (windowed) reading a padded block not held."""
    field = rough_field(seed=4)
    means, covs = thin_gaussians(300, seed=6)
    r_means, r_covs = random_gaussians(GRID, 100, seed=5, max_sigma=30.0)
    means, covs = np.concatenate([means, r_means]), np.concatenate([covs, r_covs])
    in_memory = TerrainPrior.from_array(field, GRID)
    want = {sq: integrate(in_memory, means, covs, sq) for sq in (False, True)}  # the whole pyramid
    monkeypatch.setattr(scalespace, "MAX_CELLS", H * W - 1)
    monkeypatch.setattr(lazy, "CELL_BLOCK", 32)  # 3 x 4 padded blocks
    monkeypatch.setattr(lazy, "PAD", 8)
    prior = TerrainPrior(GRID, Mosaic(in_memory.density, (1, 1)), None, None) if windowed else TerrainPrior.from_array(field, GRID)
    for squared in (False, True):
        pyr = lazy.lazy_pyramid(prior, squared)
        assert pyr.integrate_small(prior, means[:5], covs[:5], 0.5, 4.0) is None  # no level made yet
        if windowed:
            # one corner visited: the padded blocks elsewhere are not held
            corner = np.flatnonzero(((means - [GRID.transform.c, GRID.transform.f]) * [1, -1] < 8 * CELL).all(axis=1))
            assert corner.size >= 1
            integrate(prior, np.repeat(means[corner], 300, axis=0), np.repeat(covs[corner], 300, axis=0), squared)
            far = np.flatnonzero(((means - [GRID.transform.c, GRID.transform.f]) * [1, -1] > 64 * CELL).all(axis=1))[:1]
            assert far.size == 1 and pyr.integrate_small(prior, means[far], covs[far], 0.5, 4.0) is None
        got = integrate(prior, means, covs, squared)  # >= SMALL_BATCH: the general path
        np.testing.assert_array_equal(got, want[squared])
        if windowed:  # held now
            np.testing.assert_array_equal(pyr.integrate_small(prior, means[far], covs[far], 0.5, 4.0), want[squared][far])
        taken = 0
        for i in range(0, 300, 7):  # the thin ones, seven at a time
            part = pyr.integrate_small(prior, means[i : i + 7], covs[i : i + 7], 0.5, 4.0)
            if part is not None:
                taken += 1
                np.testing.assert_array_equal(part, want[squared][i : i + 7])
            np.testing.assert_array_equal(integrate(prior, means[i : i + 7], covs[i : i + 7], squared), want[squared][i : i + 7])
        assert taken >= 20
        tiny = np.diag([(0.01 * CELL) ** 2, (0.02 * CELL) ** 2])[None]
        off = means[:1] + np.array([[-10 * W * CELL, 0.0]])
        coarse = np.diag([(3.0 * CELL) ** 2, (2.5 * CELL) ** 2])[None]
        for m, cv in ((means[:1], tiny), (off, covs[:1]), (means[:1], coarse)):
            assert pyr.integrate_small(prior, np.concatenate([means[1:4], m]), np.concatenate([covs[1:4], cv]), 0.5, 4.0) is None


@pytest.mark.parametrize("sigma", [2.0, 4.0, 8.0, 16.0])
def test_a_cell_level_tile_reads_only_its_own_cells(sigma) -> None:
    """No dependency cone below 16 cells: one round Gaussian on a cold pyramid builds only tiles of its
    own level, each reading at most its extent plus the prefilter's and the cell sum's reach."""
    tile = rough_field(seed=5, shape=(64, 64))
    pyr = lazy.LazyPyramid(Mosaic(tile, (40, 40)))  # 2,560² cells, never held whole
    c = np.array([sigma * sigma])
    _, counts = pyr.integrate_pixels(np.array([1280.3]), np.array([1279.6]), c, np.zeros(1), c)
    assert counts[0] > 0
    k = int(np.floor(np.log(sigma / scalespace.S0) / np.log(scalespace.RATIO) + 1e-9))
    s, h = scalespace.lattice(k, pyr.shape)[:2]
    assert {key[0] for key in pyr._tiles} == {k}
    # per tile: its nodes with the apron, FIR value nodes a side, then 8 s + 2 cells of the cell sums
    side_cells = (pyr.level_blocks(k) * scalespace.TILE + 3 + 2 * scalespace.FIR) * h + 2 * (8 * s + 3)
    assert pyr.cells_read <= pyr.tiles_built * side_cells**2


def test_a_gaussian_on_the_finest_scale_is_planned_both_ways() -> None:
    """Smaller σ = 1 cell to rounding (found by bench_lazy at 50,000²): the sort keys said level 0,
    the kernel's own test said finer, and no tile was planned. Now: the whole pyramid's integral with
    the field, and without it (smoothed from a window of the source)."""
    field = rough_field(seed=2, shape=(100, 100))
    px = tuple(np.array([x]) for x in (50.3, 40.7, 2.5867815085773938, -0.9542262325096359, 1.5738330689433557))
    want, want_counts = whole_integrals(field, px)
    got, counts = lazy.LazyPyramid(field, field=field).integrate_pixels(*px)
    np.testing.assert_array_equal(counts, want_counts)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(lazy.LazyPyramid(field).integrate_pixels(*px)[0], want)


def test_cell_tiles_built_on_dask_workers_are_the_same_tiles() -> None:
    """A local Dask cluster builds the cell-level tiles (a pickled source per worker): the same
    integrals, tiles and cells read as building them in this process."""
    from common.dask import get_client

    source = Mosaic(rough_field(seed=4, shape=(64, 80)), (5, 4))
    px = pixel_batch(source.shape, 2000, seed=8, smallest=0.5, largest=20.0)
    serial = lazy.LazyPyramid(source, blocks=1, cache_bytes=1 << 24)
    with lazy._threads(1):  # one thread: every tile built by tile(), in this thread
        want, want_counts = serial.integrate_pixels(*px)
    with get_client(threads=2) as client:
        spread = lazy.LazyPyramid(source, blocks=1, cache_bytes=1 << 24, client=client)
        got, counts = spread.integrate_pixels(*px)
        assert client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.transition_counter) > 0  # work was sent
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(counts, want_counts)
    assert spread.tiles_built == serial.tiles_built and spread.cells_read == serial.cells_read
    assert {k for k, _, _ in spread._tiles} & set(range(scalespace.CELL_LEVELS))


@pytest.mark.skipif(nb.config.NUMBA_NUM_THREADS < 2, reason="numba has one thread here")
def test_cell_tiles_built_on_threads_are_the_same_tiles(monkeypatch) -> None:
    """Without a client, the missing cell-level tiles of a batch are built on the process's threads:
    the same integrals, tiles and cells read as building them one by one."""
    source = Mosaic(rough_field(seed=4, shape=(64, 80)), (5, 4))
    px = pixel_batch(source.shape, 2000, seed=8, smallest=0.5, largest=20.0)
    serial = lazy.LazyPyramid(source, blocks=1, cache_bytes=1 << 24)
    with lazy._threads(1):
        want, want_counts = serial.integrate_pixels(*px)
    names: list[str] = []
    build = lazy.cell_tiles

    def spy(*args):
        names.append(threading.current_thread().name)
        return build(*args)

    monkeypatch.setattr(lazy, "cell_tiles", spy)
    threaded = lazy.LazyPyramid(source, blocks=1, cache_bytes=1 << 24)
    with lazy._threads(2):
        got, counts = threaded.integrate_pixels(*px)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(counts, want_counts)
    assert threaded.tiles_built == serial.tiles_built and threaded.cells_read == serial.cells_read
    assert sum(name.startswith("lazy-tiles") for name in names) > 3


def test_a_failed_threaded_build_leaves_the_pool_as_it_was() -> None:
    """A source read that fails on a tile thread: the error reaches the caller, the slots claimed for
    the batch are free again, no tile half-written is in the tables, and the next batch builds them."""

    class Flaky:
        def __init__(self, inner, fail: int) -> None:
            self.inner, self.shape, self.fail, self.calls = inner, inner.shape, fail, 0

        def __getitem__(self, key):
            self.calls += 1
            if self.calls == self.fail:
                self.failed_on = threading.current_thread().name
                raise OSError("read failed")
            return self.inner[key]

    inner = Mosaic(rough_field(seed=4, shape=(64, 80)), (5, 4))
    px = pixel_batch(inner.shape, 2000, seed=8, smallest=1.5, largest=20.0)
    want, _ = lazy.LazyPyramid(inner, blocks=1, cache_bytes=1 << 24).integrate_pixels(*px)
    flaky = Flaky(inner, fail=3)
    pyr = lazy.LazyPyramid(flaky, blocks=1, cache_bytes=1 << 24)
    free = len(pyr._free)
    with lazy._threads(2), pytest.raises(OSError, match="read failed"):
        pyr.integrate_pixels(*px)
    assert flaky.failed_on.startswith("lazy-tiles")
    assert len(pyr._free) == free and not pyr._tiles and (pyr.slots == lazy.MISSING).all()
    with lazy._threads(2):
        got, _ = pyr.integrate_pixels(*px)
    np.testing.assert_array_equal(got, want)


def test_tile_client_reaches_the_priors_lazy_pyramids(monkeypatch) -> None:
    monkeypatch.setattr(scalespace, "MAX_CELLS", ROUGH.grid.height * ROUGH.grid.width - 1)
    sentinel = object()
    with lazy.tile_client(sentinel):
        assert lazy.lazy_pyramid(ROUGH, False).client is sentinel
    assert lazy.lazy_pyramid(ROUGH, False).client is None


def planned_tiles(pyr: lazy.LazyPyramid, px, widen: int) -> set[int]:
    """The tiles a batch reads, by the formula in numpy (the oracle of the compiled planner): each
    Gaussian's level (from its smaller σ) ± ``widen``, its reach GH_SPAN (1 + widen) leftover σ
    along both axes plus 3 h, and the spline's 2 nodes before and 3 after, in tiles."""
    uc, vc, cuu, cuv, cvv = px
    m, dd = 0.5 * (cuu + cvv), 0.5 * (cuu - cvv)
    rad = np.sqrt(dd * dd + cuv * cuv)
    lam1, lam2 = m + rad, np.maximum(m - rad, 0.0)
    coarse = lam2 >= (scalespace.S0 * (1.0 - lazy.BORDER)) ** 2
    top = pyr.levels_built() - 1
    keys: set[int] = set()
    for n in np.flatnonzero(coarse):
        k0 = int(np.clip(np.floor(np.log(np.sqrt(lam2[n]) / scalespace.S0) / np.log(scalespace.RATIO) + 1e-9), 0, top))
        for k in {int(np.clip(k0 + dk, 0, top)) for dk in range(-widen, widen + 1)}:
            s, h, origin, nu, nv = scalespace.lattice(k, pyr.shape)
            r = scalespace.GH_SPAN * (1 + widen) * (np.sqrt(max(lam1[n] - s * s, 0.0)) + np.sqrt(max(lam2[n] - s * s, 0.0))) + 3 * h
            side = pyr.level_blocks(k) * scalespace.TILE
            span = [int(np.clip(np.floor((x + sign * r - origin) / h) + pad, 0, top_node)) // side
                    for x, top_node in ((uc[n], nu - 1), (vc[n], nv - 1)) for sign, pad in ((-1, -2), (1, 3))]
            keys |= {k << 40 | tv << 20 | tu for tv in range(span[2], span[3] + 1) for tu in range(span[0], span[1] + 1)}
    return keys


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), widen=st.integers(0, 2), blocks=st.sampled_from([1, 2, 8]))
def test_the_compiled_plan_lists_the_tiles_of_the_formula(seed, widen, blocks) -> None:
    pyr = lazy.LazyPyramid(np.zeros((700, 900)), blocks=blocks)
    px = pixel_batch(pyr.shape, 60, seed=seed, smallest=0.5, largest=40.0)
    order = np.argsort(px[0])  # neighbours together, as the kernel's order puts them (repeats skipped)
    pyr._grow(40.0)
    got = pyr._tiles_of(order, *px, widen)
    assert np.all(np.diff(got) > 0)
    assert set(got.tolist()) == planned_tiles(pyr, px, widen)


def test_eviction_takes_the_least_recently_used_tiles_and_never_a_pinned_one() -> None:
    field = rough_field(seed=3, shape=(400, 400))
    pyr = lazy.LazyPyramid(field, blocks=1, cache_bytes=7 * 4 * scalespace.BLOCK)  # 6 one-block tiles
    assert pyr.n_slots == 6

    def use(u: float, v: float) -> set:
        c = np.array([4.0])
        before = set(pyr._tiles)
        pyr.integrate_pixels(np.array([u]), np.array([v]), c, np.zeros(1), c)
        return set(pyr._tiles) - before

    level = int(round(4 * np.log2(2.0 / scalespace.S0)))  # σ = 2 cells: its level's tiles are one 32-node block
    _, h, origin = scalespace.lattice(level, pyr.shape)[:3]

    def centre(t: int) -> float:
        return origin + h * (32 * t + 16.3)

    first, second = use(centre(2), centre(2)), use(centre(6), centre(6))
    assert len(first) == len(second) == 1
    use(centre(2), centre(2))  # the first area again: now the second is the least recently used
    for t in range(5):
        assert len(use(centre(t), centre(9))) == 1
    assert not second <= set(pyr._tiles) and first <= set(pyr._tiles)
    # a batch whose tiles would need the slots of pinned ones is refused, and nothing pinned is evicted
    pinned = set(pyr._tiles)
    pyr._pin(pyr._tile_ids(*np.array(list(pinned)).T), np.ones(len(pinned), np.int64))
    with pytest.raises(MemoryError, match="cannot hold"):
        use(centre(8), centre(2))
    assert pinned <= set(pyr._tiles)
    pyr._unpin()
    assert not pyr._pinned.any() and pyr._pinned_blocks == 0


def test_stacked_windows_read_each_windows_own_cells() -> None:
    """One kernel call over many windows: frame i maps window i's cells into the stack."""
    rng = np.random.default_rng(0)
    grid = rng.uniform(size=(50, 60))
    bounds = np.array([[3, 10, 5, 30], [20, 21, 0, 60], [40, 50, 55, 60], [7, 7, 2, 2]], np.int64)
    values, frames, views = scalespace.stacked_frames(bounds, grid.shape)
    for view, (r0, r1, c0, c1) in zip(views, bounds.tolist(), strict=True):
        view[...] = grid[r0:r1, c0:c1]
    for (r0, r1, c0, c1), frame in zip(bounds.tolist(), frames, strict=True):
        assert tuple(frame[2:]) == grid.shape
        for j in range(r0, r1):
            for i in range(c0, c1):
                assert values[j - frame[0], i - frame[1]] == grid[j, i]


@settings(max_examples=60, deadline=None)
@given(keys=st.sets(st.tuples(st.integers(0, 2), st.integers(0, 9), st.integers(0, 9)), max_size=80), most=st.integers(1, 5))
def test_rectangles_cover_exactly_the_tiles_asked_for(keys, most) -> None:
    rects = lazy.rectangles(list(keys), most)
    covered = [(k, tv, tu) for k, tv0, tv1, tu0, tu1 in rects for tv in range(tv0, tv1 + 1) for tu in range(tu0, tu1 + 1)]
    assert sorted(covered) == sorted(keys)  # every tile once, no other
    assert all(0 <= tv1 - tv0 < most and 0 <= tu1 - tu0 < most for _, tv0, tv1, tu0, tu1 in rects)


def test_a_rectangle_of_tiles_is_the_tiles_built_one_by_one() -> None:
    source = Mosaic(rough_field(seed=6, shape=(50, 70)), (6, 5))
    for k in (0, 5, 12):
        side = lazy.LazyPyramid(source, blocks=2).level_blocks(k) * scalespace.TILE
        nu, nv = scalespace.lattice(k, source.shape)[3:5]
        tv1, tu1 = min(2, (nv - 1) // side), min(3, (nu - 1) // side)
        tiles, cells = lazy.cell_tiles(source, False, source.shape, k, 0, tv1, 1 if tu1 > 1 else 0, tu1, side)
        singles = [lazy.cell_tiles(source, False, source.shape, k, tv, tv, tu, tu, side)
                   for tv in range(tv1 + 1) for tu in range(1 if tu1 > 1 else 0, tu1 + 1)]
        for got, (want, _) in zip(tiles, singles, strict=True):
            np.testing.assert_array_equal(got, want[0])
        assert len(tiles) > 1 and cells < sum(c for _, c in singles)


def test_huge_zeros_is_a_writable_zeroed_array_of_its_shape() -> None:
    a = lazy.huge_zeros((3, 5), np.float32)
    assert a.shape == (3, 5) and a.dtype == np.float32 and a.flags.writeable and not a.any()
    a[2, 4] = 7.0
    assert a.sum() == 7.0
    assert lazy.huge_zeros((0, 4), np.float64).shape == (0, 4)


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs Linux's /proc/self/maps")
def test_huge_zeros_is_private_memory() -> None:
    """Private, not shared, anonymous memory: shmem gets no transparent huge pages by default."""
    a = lazy.huge_zeros((1024, 1024), np.float32)
    address = a.__array_interface__["data"][0]
    for line in Path("/proc/self/maps").read_text().splitlines():
        lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
        if lo <= address < hi:
            assert line.split()[1] == "rw-p", line
            return
    pytest.fail("the array's mapping is not in /proc/self/maps")


def _home_blocks_numpy(u, v, reach, h, w, b, pad):
    """The padded-block formula in numpy (the oracle of lazy.home_blocks)."""
    br = np.clip(np.floor(v / b), 0, (h - 1) // b).astype(np.int64)
    bc = np.clip(np.floor(u / b), 0, (w - 1) // b).astype(np.int64)
    fits = np.ones(u.shape[0], bool)
    for x, first, n in ((v, br * b, h), (u, bc * b, w)):
        fits &= np.clip(np.floor(x - reach), 0, n) >= np.maximum(first - pad, 0)
        fits &= np.clip(np.floor(x + reach) + 1, 0, n) <= np.minimum(first + b + pad, n)
    return br * ((w - 1) // b + 1) + bc, fits


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), h=st.integers(1, 2000), w=st.integers(1, 2000), b=st.sampled_from([1, 7, 64, 256]),
       pad=st.sampled_from([-5, 0, 3, 32]))
def test_home_blocks_follow_the_numpy_formula(seed, h, w, b, pad) -> None:
    rng = np.random.default_rng(seed)
    n = 300
    u = rng.uniform(-0.1 * w, 1.1 * w, n)
    v = rng.uniform(-0.1 * h, 1.1 * h, n)
    u[:20] = np.round(u[:20])  # on cell and block edges
    v[:20] = np.round(v[:20] / b) * b
    reach = rng.uniform(0.0, 3.0 * b, n)
    reach[20:40] = np.round(reach[20:40])
    got = lazy.home_blocks(u, v, reach, h, w, b, pad)
    want = _home_blocks_numpy(u, v, reach, h, w, b, pad)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
