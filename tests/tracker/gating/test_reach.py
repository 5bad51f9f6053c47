"""Constant-velocity projection, reach bounds, eigenvalue bounds and the M_D cost model."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar

from tests.tracker.gating.test_oracle import random_covs
from tracker.gating import costmodel
from tracker.gating.exact import lambda_max_bound
from tracker.gating.reach import ReachBound, ball_volume, project, project_states


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), dim=st.sampled_from([2, 3]), q=st.floats(0.0, 10.0))
def test_project_matches_transition_matrices(seed, dim, q):
    rng = np.random.default_rng(seed)
    n = 5
    x = rng.normal(0, 100, (n, 2 * dim))
    p = random_covs(rng, n, 2 * dim, 0.5, 50.0, 100.0)
    dt = rng.uniform(-10, 10, n)
    pos, cov = project(x, p, dt, q, dim)
    states, state_covs = project_states(x, p, dt, q, dim)
    for i in range(n):
        f = np.eye(2 * dim)
        f[:dim, dim:] = dt[i] * np.eye(dim)
        a = abs(dt[i])
        # the cross term keeps dt's sign (retrodiction: see tracker.models.motion)
        qm = q * np.block([[a**3 / 3 * np.eye(dim), dt[i] * a / 2 * np.eye(dim)],
                           [dt[i] * a / 2 * np.eye(dim), a * np.eye(dim)]])
        full = f @ p[i] @ f.T + qm
        np.testing.assert_allclose(pos[i], (f @ x[i])[:dim], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(cov[i], full[:dim, :dim], rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(states[i], f @ x[i], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(state_covs[i], full, rtol=1e-10, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), dim=st.sampled_from([2, 3]), q=st.floats(0.0, 10.0),
       cond=st.sampled_from([1.0, 1e4]))
def test_reach_bound_dominates_projected_spread(seed, dim, q, cond):
    rng = np.random.default_rng(seed)
    n = 20
    p = random_covs(rng, n, 2 * dim, 0.5, 50.0, cond)
    reach = ReachBound.from_covs(p, np.full(n, q), dim, moving=True)
    for dt in (0.0, 0.3, -2.0, 7.5):
        _, cov = project(np.zeros((n, 2 * dim)), p, dt, q, dim)
        true = np.sqrt(np.linalg.eigvalsh(cov)[:, -1])
        assert np.all(reach.sigma(abs(dt)) >= true * (1 - 1e-12))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), dim=st.sampled_from([2, 3]),
       cond=st.sampled_from([1.0, 1e3, 1e8]))
def test_lambda_max_bound_is_tight_upper_bound(seed, dim, cond):
    rng = np.random.default_rng(seed)
    c = random_covs(rng, 50, dim, 1e-2, 1e3, cond)
    true = np.linalg.eigvalsh(c)[:, -1]
    got = lambda_max_bound(c)
    assert np.all(got >= true)
    np.testing.assert_allclose(got, true, rtol=1e-7)


def test_expected_volume_long_scan_limit_and_monte_carlo():
    """R0 -> 0 gives eq. A5, gamma(l) (a w)^l / (l + 1); otherwise a Monte Carlo mean."""
    a, tau = np.array([200.0]), 10.0
    for dim in (2, 3):
        m = np.array([1, 4])
        w = tau / (2 * m)
        got = costmodel.expected_volume(m, np.array([1e-9]), a, tau, dim)
        np.testing.assert_allclose(got, ball_volume(dim) * (a * w) ** dim / (dim + 1), rtol=1e-6)
        r0 = np.array([300.0])
        u = np.random.default_rng(0).uniform(0, w[1], 400_000)
        mc = ball_volume(dim) * np.mean((r0 + a * u) ** dim)
        got = costmodel.expected_volume(np.array([4]), r0, a, tau, dim)[0]
        assert got == pytest.approx(mc, rel=2e-3)


def test_md0_closed_form_minimises_the_long_scan_cost():
    c = costmodel.CostConstants(b_tracks=1.2e-7, b_reports=2e-7, r_tracks=1e-7, r_reports=2e-8,
                                c_c=3e-7)
    n_t, n_r, rho, a, tau = 50_000, 80_000, 1e-6, 250.0, 10.0
    for dim in (2, 3):
        m0 = costmodel.md0_closed_form(n_t, n_r, rho, a, tau, dim, c)
        k1 = n_t * c.b_tracks
        k2 = c.c_c * n_r * rho * ball_volume(dim) * (a * tau / 2) ** dim / (dim + 1)
        res = minimize_scalar(lambda m, d=dim, k1=k1, k2=k2: m * k1 + k2 * m ** (-d), bounds=(1e-3, 1e4),
                              method="bounded", options={"xatol": 1e-8})
        assert m0 == pytest.approx(res.x, rel=1e-4)


def test_predicted_cost_trades_projections_against_candidates():
    c = costmodel.CostConstants(b_tracks=1.2e-7, b_reports=2e-7, r_tracks=1e-7, r_reports=2e-8,
                                c_c=3e-7)
    m = np.arange(1, 65, dtype=float)
    vol = costmodel.expected_volume(m, np.full(100, 300.0), np.full(100, 300.0), 10.0, 2)
    assert np.all(np.diff(vol) < 0)
    dense = costmodel.predict(100_000, 100_000, 1e10 * vol / 1e9, 1e10 * vol / 1e9, m, c)
    sparse = costmodel.predict(100_000, 100_000, 1e10 * vol / 1e13, 1e10 * vol / 1e13, m, c)
    for cost in dense:
        assert 0 < int(np.argmin(cost)) < len(m) - 1  # projections pay, up to a point
    for cost in sparse:
        assert int(np.argmin(cost)) == 0  # too few candidates to pay for a second projection


def test_constants_round_trip_through_json(tmp_path):
    path = tmp_path / "costs.json"
    c = costmodel.CostConstants(1e-7, 2e-8, 3e-8, 4e-8, 5e-7)
    c.write(path)
    assert json.loads(path.read_text()) == c.__dict__
    assert costmodel.CostConstants.read(path) == c
    assert [p.name for p in tmp_path.iterdir()] == ["costs.json"]  # no temporary left behind


def test_constants_must_be_positive_seconds():
    with pytest.raises(ValueError, match="c_c"):
        costmodel.CostConstants(1e-7, 2e-8, 3e-8, 4e-8, -5e-7)
    with pytest.raises(ValueError, match="b_tracks"):
        costmodel.CostConstants(float("nan"), 2e-8, 3e-8, 4e-8, 5e-7)
