"""The tracker's one positive-definite checker (check_gaussians): both numba passes against the numpy
formula (finite means, finite covariances, symmetry within 1e-9 of the largest entry, smallest
eigenvalue > 0, the first that fails)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tracker.types.reports import (
    _PARALLEL_FROM,
    _flags,
    _flags_2d,
    _flags_2d_parallel,
    check_gaussians,
)


def numpy_flags(means: np.ndarray, covs: np.ndarray) -> np.ndarray:
    flags = np.zeros(means.shape[0], dtype=np.int8)
    finite_c = np.isfinite(covs).all(axis=(1, 2))
    scale = np.abs(np.where(finite_c[:, None, None], covs, 0.0)).max(axis=(1, 2), initial=0.0)
    asym = np.abs(covs - covs.transpose(0, 2, 1)).max(axis=(1, 2), initial=0.0)
    ok = finite_c & ~(asym > 1e-9 * np.maximum(scale, 1e-300))
    eig_min = np.full(means.shape[0], np.nan)
    if ok.any():
        eig_min[ok] = np.linalg.eigvalsh(covs[ok])[:, 0]
    flags[~(eig_min > 0)] = 4
    flags[~ok & finite_c] = 3
    flags[~finite_c] = 2
    flags[~np.isfinite(means).all(axis=1)] = 1
    return flags


def gaussians(seed: int, n: int, d: int):
    """Clearly good and clearly bad Gaussians of every kind (no matrix near the PD boundary)."""
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(n, d, d))
    covs = L @ L.transpose(0, 2, 1) + 0.1 * np.eye(d)
    means = rng.normal(size=(n, d))
    kind = rng.integers(0, 6, n)
    for i in np.flatnonzero(kind == 1):
        means[i, rng.integers(d)] = rng.choice([np.nan, np.inf])
    for i in np.flatnonzero(kind == 2):
        covs[i, rng.integers(d), rng.integers(d)] = np.nan
    for i in np.flatnonzero(kind == 3):
        covs[i, 0, d - 1] += 0.5
    for i in np.flatnonzero(kind == 4):
        covs[i] -= (np.linalg.eigvalsh(covs[i])[0] + 1.0) * np.eye(d)  # one eigenvalue -1
    return means, covs


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(0, 40), d=st.sampled_from([2, 3, 4, 6]))
def test_numba_flags_follow_the_numpy_formula(seed, n, d):
    means, covs = gaussians(seed, n, d)
    want = numpy_flags(means, covs)
    np.testing.assert_array_equal(_flags(means, covs), want)
    if d == 2:
        np.testing.assert_array_equal(_flags_2d(means, covs), want)
        np.testing.assert_array_equal(_flags_2d_parallel(means, covs), want)


def test_parallel_2d_pass_matches_the_serial_one_on_a_large_batch():
    # check_gaussians switches to the parallel kernel from _PARALLEL_FROM Gaussians on
    means, covs = gaussians(7, _PARALLEL_FROM + 1, 2)
    covs[::97] = np.array([[1.0, 1.0 - 1e-13], [1.0 - 1e-13, 1.0]])  # too ill-conditioned (5)
    want = _flags_2d(means, covs)
    assert set(np.unique(want)) == {0, 1, 2, 3, 4, 5}
    np.testing.assert_array_equal(_flags_2d_parallel(means, covs), want)


def test_messages_name_the_argument_and_indices():
    means, covs = np.zeros((3, 4)), np.tile(np.eye(4), (3, 1, 1))
    covs[2] *= -1.0
    with pytest.raises(ValueError, match=r"gate: track_covs not positive definite at indices \[2\]"):
        check_gaussians(means, covs, "gate", means_name="track_means", covs_name="track_covs")
    with pytest.raises(ValueError, match=r"reports: covariances not positive definite at indices \[2\]"):
        check_gaussians(means, covs, "reports")
