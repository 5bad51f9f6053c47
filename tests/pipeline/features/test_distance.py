"""distance_m against a brute-force minimum over all target cells (metres, non-square cells)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.features.distance import distance_m


def brute_force(mask: np.ndarray, dx: float, dy: float) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    r, c = np.indices(mask.shape)
    if rows.size == 0:
        return np.full(mask.shape, np.inf)
    d2 = ((r[..., None] - rows) * dy) ** 2 + ((c[..., None] - cols) * dx) ** 2
    return np.sqrt(d2.min(axis=-1))


masks = st.tuples(st.integers(1, 14), st.integers(1, 14)).flatmap(
    lambda shape: arrays(np.bool_, shape, elements=st.booleans())
)
cell = st.floats(0.25, 50.0)


@settings(max_examples=100, deadline=None)
@given(mask=masks, dx=cell, dy=cell)
def test_matches_brute_force(mask, dx, dy):
    np.testing.assert_allclose(distance_m(mask, dx, dy), brute_force(mask, dx, dy), rtol=1e-12, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(mask=masks, dx=cell, dy=cell, cap=st.floats(0.0, 200.0))
def test_cap(mask, dx, dy, cap):
    expected = np.minimum(brute_force(mask, dx, dy), cap)
    np.testing.assert_allclose(distance_m(mask, dx, dy, max_distance=cap), expected, rtol=1e-12, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), shape=st.tuples(st.integers(1, 120), st.integers(1, 120)),
       density=st.sampled_from([0.001, 0.01, 0.1]), dx=cell, dy=cell, cap_rows=st.floats(0.0, 40.0))
def test_capped_transform_is_the_uncapped_one_capped_bit_for_bit(seed, shape, density, dx, dy, cap_rows):
    """Under a cap the work array is uint16 and drops columns whose targets lie beyond it: the
    distances are the uncapped transform's (int32 work array, every column) capped, to the bit."""
    mask = np.random.default_rng(seed).random(shape) < density
    cap = cap_rows * dy
    np.testing.assert_array_equal(distance_m(mask, dx, dy, max_distance=cap), np.minimum(distance_m(mask, dx, dy), cap))


def test_sparse_random_grids_float32():
    rng = np.random.default_rng(7)
    for _ in range(20):
        mask = rng.random((40, 33)) < 0.01
        dx, dy = rng.uniform(1, 30, 2)
        got = distance_m(mask, dx, dy, dtype=np.float32)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, brute_force(mask, dx, dy), rtol=1e-6)


def test_single_target_is_hypot():
    mask = np.zeros((9, 12), dtype=bool)
    mask[3, 5] = True
    r, c = np.indices(mask.shape)
    np.testing.assert_allclose(distance_m(mask, 20.0, 7.5), np.hypot((c - 5) * 20.0, (r - 3) * 7.5))


def test_all_false():
    mask = np.zeros((4, 6), dtype=bool)
    assert np.isinf(distance_m(mask, 1.0, 1.0)).all()
    np.testing.assert_array_equal(distance_m(mask, 1.0, 1.0, max_distance=500.0), 500.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mask": np.zeros(5, dtype=bool)}, "2-D"),
        ({"mask": np.zeros((3, 3), dtype=np.uint8)}, "boolean"),
        ({"dx": 0.0}, "dx"),
        ({"dy": np.nan}, "dy"),
        ({"max_distance": -1.0}, "max_distance"),
        ({"dtype": np.int32}, "dtype"),
        ({"window": (1, 0, 3, 3)}, "window"),
        ({"window": (0, -1, 2, 2)}, "window"),
    ],
)
def test_bad_arguments(kwargs, match):
    args = {"mask": np.zeros((3, 3), dtype=bool), "dx": 1.0, "dy": 1.0} | kwargs
    with pytest.raises(ValueError, match=match):
        distance_m(**args)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 12), st.integers(1, 12), st.floats(0.5, 30.0), st.floats(0.5, 30.0),
       st.data())
def test_window_is_the_same_numbers_as_a_slice_of_the_whole(seed, h, w, dx, dy, data):
    """The padded-mask path of the distance feature: a window's distances are the whole grid's, bit for bit."""
    mask = np.random.default_rng(seed).random((h, w)) < 0.1
    r0, c0 = data.draw(st.integers(0, h - 1)), data.draw(st.integers(0, w - 1))
    wh, ww = data.draw(st.integers(0, h - r0)), data.draw(st.integers(0, w - c0))
    for cap in (None, 25.0):
        whole = distance_m(mask, dx, dy, cap)
        got = distance_m(mask, dx, dy, cap, window=(r0, c0, wh, ww))
        np.testing.assert_array_equal(got, whole[r0:r0 + wh, c0:c0 + ww])
