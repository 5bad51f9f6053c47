"""Bearing-only gating against a dense brute force in the sensor's angle coordinate."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.gating.test_oracle import random_covs
from tracker.gating.bearing import gate_bearings, track_bearings


def _brute(tm, tc, sensor, theta, sig, gamma):
    d = tm - sensor
    beta = np.arctan2(d[:, 1], d[:, 0])
    # independent linearisation: numerical Jacobian of atan2 by central differences
    eps = 1e-6 * np.linalg.norm(d, axis=1)
    jac = np.stack([
        (np.arctan2(d[:, 1], d[:, 0] + eps) - np.arctan2(d[:, 1], d[:, 0] - eps)) / (2 * eps),
        (np.arctan2(d[:, 1] + eps, d[:, 0]) - np.arctan2(d[:, 1] - eps, d[:, 0])) / (2 * eps),
    ], axis=1)
    var = np.einsum("ni,nij,nj->n", jac, tc, jac)
    resid = np.angle(np.exp(1j * (theta[None, :] - beta[:, None])))
    return resid**2 / (var[:, None] + sig[None, :] ** 2)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), nt=st.integers(0, 40), nr=st.integers(0, 40),
       gamma=st.floats(0.0, 25.0), near=st.booleans())
def test_bearing_gate_matches_brute_force(seed, nt, nr, gamma, near):
    rng = np.random.default_rng(seed)
    sensor = rng.uniform(-100, 100, 2)
    scale = 50.0 if near else 5000.0  # near the sensor angular sigmas get huge
    tm = sensor + rng.uniform(-scale, scale, (nt, 2))
    tm[np.linalg.norm(tm - sensor, axis=1) < 1.0] += 10.0
    tc = random_covs(rng, nt, 2, 1.0, 200.0, 1e3)
    theta = rng.uniform(-4.0, 4.0, nr)  # also outside (-pi, pi]
    sig = np.exp(rng.uniform(np.log(1e-3), np.log(0.5), nr))
    t_idx, r_idx, d2 = gate_bearings(tm, tc, sensor, theta, sig, threshold=gamma, return_d2=True)
    want = _brute(tm, tc, sensor, theta, sig, gamma)
    got = np.zeros(want.shape, bool)
    got[t_idx, r_idx] = True
    border = np.abs(want - gamma) <= 1e-5 * max(gamma, 1.0)
    assert not (got & ~(want <= gamma) & ~border).any()
    assert not (~got & (want <= gamma) & ~border).any()
    np.testing.assert_allclose(d2, want[t_idx, r_idx], rtol=1e-5)
    assert np.all(np.diff(t_idx * max(nr, 1) + r_idx) > 0)


def test_wraparound_pair_found():
    sensor = np.zeros(2)
    tm = np.array([[-1000.0, 1e-3], [-1000.0, -1e-3]])  # bearings just below +pi / above -pi
    tc = np.tile(np.eye(2), (2, 1, 1))
    beta, _ = track_bearings(tm, tc, sensor)
    assert beta[0] > 3.14 and beta[1] < -3.14
    t_idx, r_idx = gate_bearings(tm, tc, sensor, np.array([-np.pi + 1e-4]), np.array([1e-3]),
                                 prob=0.99)
    assert t_idx.tolist() == [0, 1] and r_idx.tolist() == [0, 0]


def test_bearing_errors():
    tm, tc = np.array([[1.0, 1.0], [0.0, 0.0]]), np.tile(np.eye(2), (2, 1, 1))
    with pytest.raises(ValueError, match=r"sensor position.*\[1\]"):
        gate_bearings(tm, tc, [0.0, 0.0], [0.1], [0.01], threshold=4.0)
    with pytest.raises(ValueError, match="bearing_sigmas"):
        gate_bearings(tm[:1], tc[:1], [0.0, 0.0], [0.1], [0.0], threshold=4.0)
    with pytest.raises(ValueError, match="bearings"):
        gate_bearings(tm[:1], tc[:1], [0.0, 0.0], [np.nan], [0.1], threshold=4.0)
    with pytest.raises(ValueError, match="threshold"):
        gate_bearings(tm[:1], tc[:1], [0.0, 0.0], [0.1], [0.1], threshold=-4.0)
    with pytest.raises(ValueError, match="sensor"):
        gate_bearings(tm[:1], tc[:1], [0.0], [0.1], [0.1], threshold=4.0)
    with pytest.raises(ValueError, match=r"track_covs.*\[0\]"):
        gate_bearings(tm[:1], -tc[:1], [0.0, 0.0], [0.1], [0.1], threshold=4.0)
