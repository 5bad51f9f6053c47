"""The one constant-velocity formula: every prediction path (ConstantVelocity.predict, gating's
project / project_states / projected_cov_entry, the association kernels' helpers) gives the explicit
F P Fᵀ + Q(dt) with the signed cross term, for dt < 0, dt = 0 and dt > 0."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from tracker.association import walk
from tracker.gating.reach import project, project_states, projected_cov_entry
from tracker.models.motion import MOTION_CV, ConstantVelocity, cv_cov_entry, cv_mean_entry


def explicit(x: np.ndarray, P: np.ndarray, dt: float, q: float, d: int) -> tuple[np.ndarray, np.ndarray]:
    """F x and F P Fᵀ + Q as dense numpy matrices (the model's definition)."""
    eye = np.eye(d)
    F = np.block([[eye, dt * eye], [np.zeros((d, d)), eye]])
    a = abs(dt)
    Q = q * np.block([[a**3 / 3 * eye, dt * a / 2 * eye], [dt * a / 2 * eye, a * eye]])
    return F @ x, F @ P @ F.T + Q


def scene(seed: int, n: int, d: int, sign: int):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(n, 2 * d, 2 * d))
    P = L @ L.transpose(0, 2, 1) + np.eye(2 * d)
    P = 0.5 * (P + P.transpose(0, 2, 1))
    x = rng.normal(0.0, 100.0, (n, 2 * d))
    dt = sign * rng.uniform(0.01, 20.0, n)
    return x, P, dt


@njit
def _entries(x, P, dt, q, d):
    n, sd = x.shape
    m = np.empty((n, sd))
    c = np.empty((n, sd, sd))
    pc = np.empty((n, d, d))
    for i in range(n):
        for r in range(sd):
            m[i, r] = cv_mean_entry(x, i, r, dt[i], d)
            for s in range(sd):
                c[i, r, s] = cv_cov_entry(P, i, r, s, dt[i], q, d)
        for r in range(d):
            for s in range(d):
                pc[i, r, s] = projected_cov_entry(P, i, r, s, dt[i], q, d, True)
    return m, c, pc


@njit
def _walk_positions(Hm, Hc, Ht, t, q):
    out = np.empty((Hm.shape[0], 5))
    for h in range(Hm.shape[0]):
        out[h, 0], out[h, 1], out[h, 2], out[h, 3], out[h, 4] = walk._pos_at(Hm, Hc, Ht, h, t, MOTION_CV, q)
    return out


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), d=st.sampled_from([2, 3]), sign=st.sampled_from([-1, 0, 1]),
       q=st.floats(0.0, 10.0))
def test_every_path_is_the_explicit_formula(seed, d, sign, q):
    n = 6
    x, P, dt = scene(seed, n, d, sign)
    want = [explicit(x[i], P[i], dt[i], q, d) for i in range(n)]
    wm = np.array([w[0] for w in want])
    wc = np.array([w[1] for w in want])
    tol = dict(rtol=1e-10, atol=1e-8)

    em, ec, epc = _entries(x, P, dt, q, d)  # the element functions themselves
    np.testing.assert_allclose(em, wm, **tol)
    np.testing.assert_allclose(ec, wc, **tol)
    np.testing.assert_allclose(epc, wc[:, :d, :d], **tol)
    pos, pcov = project(x, P, dt, q, d)
    np.testing.assert_allclose(pos, wm[:, :d], **tol)
    np.testing.assert_allclose(pcov, wc[:, :d, :d], **tol)
    sm, sc = project_states(x, P, dt, q, d)
    np.testing.assert_allclose(sm, wm, **tol)
    np.testing.assert_allclose(sc, wc, **tol)
    if d == 2:
        pm, pc = ConstantVelocity(q=q, velocity_std=1.0).predict(x, P, dt)
        np.testing.assert_allclose(pm, wm, **tol)
        np.testing.assert_allclose(pc, wc, **tol)
        # the association kernels: one report time t, hypotheses last seen at t - dt
        t = 50.0
        got = _walk_positions(x, P, t - dt, t, q)
        np.testing.assert_allclose(got[:, :2], wm[:, :2], **tol)
        np.testing.assert_allclose(got[:, 2:], wc[:, [0, 0, 1], [0, 1, 1]], **tol)


@pytest.mark.parametrize("sign", [-1, 0, 1])
def test_walk_pair_geometry_is_the_kalman_step_of_the_formula(sign):
    """pair_geometry (the association's scoring kernel): prediction by the formula, then the
    position update, against numpy."""
    n, q = 5, 0.7
    x, P, dt = scene(3, n, 2, sign)
    rng = np.random.default_rng(4)
    z = x[:, :2] + rng.normal(0, 30.0, (n, 2))
    V = np.tile(np.diag([40.0, 90.0]), (n, 1, 1))
    t = rng.uniform(0.0, 5.0, n)
    Ht = t - dt
    blk = (z, V, t)
    hyp = (x, P, np.zeros(n), np.ones(n, np.int64), Ht)
    cfg = (41.4, False, 0.0, 0, 0.0, MOTION_CV, q, 10.0)
    idx = np.arange(n)
    log_g, post_m, post_c, pred_m, pred_c = walk.pair_geometry(idx, idx, blk, hyp, cfg)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    for i in range(n):
        a, A = explicit(x[i], P[i], dt[i], q, 2)
        S = H @ A @ H.T + V[i]
        K = A @ H.T @ np.linalg.inv(S)
        r = z[i] - a[:2]
        np.testing.assert_allclose(pred_m[i], a[:2], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(pred_c[i], A[:2, :2], rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(post_m[i], a + K @ r, rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(post_c[i], A - K @ H @ A, rtol=1e-9, atol=1e-8)
        want = -0.5 * (r @ np.linalg.solve(S, r) + np.linalg.slogdet(S)[1]) - np.log(2 * np.pi)
        assert log_g[i] == pytest.approx(want, rel=1e-10, abs=1e-10)


def test_retrodiction_cross_term_is_negative():
    """Backwards in time position and velocity errors are anti-correlated: Q_pv = q dt|dt|/2 < 0."""
    x, P = np.zeros((1, 4)), np.zeros((1, 4, 4))
    _, back = project_states(x, P, -2.0, 1.0, 2)
    _, fwd = project_states(x, P, 2.0, 1.0, 2)
    assert back[0, 0, 2] == pytest.approx(-2.0) and fwd[0, 0, 2] == pytest.approx(2.0)
    assert back[0, 0, 0] == fwd[0, 0, 0] == pytest.approx(8.0 / 3.0)


def test_constant_velocity_prediction_matches_matrices():
    rng = np.random.default_rng(0)
    motion = ConstantVelocity(q=0.3, velocity_std=4.0)
    L = rng.normal(size=(5, 4, 4))
    P = L @ L.transpose(0, 2, 1) + np.eye(4)
    x = rng.normal(size=(5, 4))
    dt = np.array([0.0, 1.0, 2.5, 10.0, 0.1])
    m, C = motion.predict(x, P, dt)
    for i, d in enumerate(dt):
        F = np.block([[np.eye(2), d * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
        Q = 0.3 * np.block([[d**3 / 3 * np.eye(2), d**2 / 2 * np.eye(2)], [d**2 / 2 * np.eye(2), d * np.eye(2)]])
        np.testing.assert_allclose(m[i], F @ x[i], rtol=1e-12)
        np.testing.assert_allclose(C[i], F @ P[i] @ F.T + Q, rtol=1e-12)


def test_bad_motion_parameters():
    with pytest.raises(ValueError, match="q"):
        ConstantVelocity(q=-1.0)
    with pytest.raises(ValueError, match="velocity_std"):
        ConstantVelocity(velocity_std=0.0)
