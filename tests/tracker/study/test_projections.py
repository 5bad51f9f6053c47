"""tracker.study.projections: the brute force against an explicit per-pair loop with F P Fᵀ + Q
matrices and against gate(); measured sweeps find the brute-force pair set at every M_D; the
cost model's pick is the argmin of its own curve and needs more projections for faster tracks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tracker.gating.gate import gate
from tracker.study.projections import brute_force_pairs, measure_projections, predicted_choice


def _spd(rng: np.random.Generator, n: int, d: int, lo: float, hi: float) -> np.ndarray:
    a = rng.normal(size=(n, d, d))
    q, _ = np.linalg.qr(a)
    ev = rng.uniform(lo, hi, (n, d)) ** 2
    return np.einsum("nij,nj,nkj->nik", q, ev, q)


def _scene(seed: int, n_t: int, n_r: int, d: int, moving: bool, side: float = 2000.0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, side, (n_t, d))
    if moving:
        means = np.hstack([pos, rng.uniform(-80, 80, (n_t, d))])
        covs = np.zeros((n_t, 2 * d, 2 * d))
        covs[:, :d, :d] = _spd(rng, n_t, d, 10, 200)
        covs[:, d:, d:] = _spd(rng, n_t, d, 1, 10)
        # position/velocity correlation; P stays positive definite (1.5² < σ_p,min² σ_v,min = 100)
        covs[:, :d, d:] = 1.5 * np.eye(d)
        covs[:, d:, :d] = covs[:, :d, d:].transpose(0, 2, 1)
    else:
        means, covs = pos, _spd(rng, n_t, d, 10, 200)
    return means, covs, rng.uniform(0, side, (n_r, d)), _spd(rng, n_r, d, 10, 200), rng.uniform(0, 10, n_r)


def _loop_oracle(tm, tc, rm, rc, rt, gamma, q, moving):
    """Per pair: x(t) = F x, P(t) = F P Fᵀ + Q(dt) with explicit matrices, d² by np.linalg.solve."""
    d = rm.shape[1]
    pairs = []
    for i in range(len(tm)):
        for j in range(len(rm)):
            if moving:
                dt = rt[j]
                f = np.eye(2 * d)
                f[:d, d:] = dt * np.eye(d)
                big_q = np.zeros((2 * d, 2 * d))
                big_q[:d, :d] = q * abs(dt) ** 3 / 3 * np.eye(d)
                x = f @ tm[i]
                p = f @ tc[i] @ f.T + big_q
                mean, cov = x[:d], p[:d, :d]
            else:
                mean, cov = tm[i], tc[i]
            dx = rm[j] - mean
            if dx @ np.linalg.solve(cov + rc[j], dx) <= gamma:
                pairs.append((i, j))
    return pairs


@given(seed=st.integers(0, 10_000), d=st.sampled_from([2, 3]), moving=st.booleans(),
       n_t=st.integers(0, 12), n_r=st.integers(0, 12))
@settings(max_examples=40, deadline=None)
def test_brute_force_matches_explicit_loop_and_gate(seed, d, moving, n_t, n_r) -> None:
    tm, tc, rm, rc, rt = _scene(seed, n_t, n_r, d, moving)
    gamma, q = 11.3, 2.0
    t_idx, r_idx = brute_force_pairs(tm, tc, rm, rc, rt, threshold=gamma, process_noise=q)
    assert list(zip(t_idx.tolist(), r_idx.tolist(), strict=True)) == _loop_oracle(tm, tc, rm, rc, rt, gamma, q, moving)
    g_t, g_r = gate(tm, tc, rm, rc, threshold=gamma, report_times=rt if moving else None, process_noise=q)
    np.testing.assert_array_equal(t_idx, g_t)
    np.testing.assert_array_equal(r_idx, g_r)


def test_brute_force_needs_report_times_for_moving_tracks() -> None:
    tm, tc, rm, rc, _ = _scene(0, 3, 3, 2, True)
    with pytest.raises(ValueError, match="report_times"):
        brute_force_pairs(tm, tc, rm, rc, threshold=9.0)


def test_measured_sweep_finds_the_brute_force_pairs_at_every_md() -> None:
    tm, tc, rm, rc, rt = _scene(7, 150, 150, 2, True, side=3000.0)
    expected = brute_force_pairs(tm, tc, rm, rc, rt, threshold=9.21, process_noise=1.0)[0].size
    table = measure_projections(tm, tc, rm, rc, rt, threshold=9.21, ms=[1, 3, 8], process_noise=1.0, repeats=1)
    assert len(table) == 6 and set(table["orientation"]) == {"reports", "tracks"}
    assert (table["pairs"] == expected).all() and expected > 0
    assert (table["seconds"] > 0).all()


def _fast_scene(speed_scale: float, n: int = 3000):
    rng = np.random.default_rng(3)
    side = 1000.0 * np.sqrt(n / 50.0)
    heading = rng.uniform(0, 2 * np.pi, n)
    vel = speed_scale * rng.uniform(0, 300, n)[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)
    tm = np.hstack([rng.uniform(0, side, (n, 2)), vel])
    tc = np.zeros((n, 4, 4))
    tc[:, :2, :2] = 30.0**2 * np.eye(2)
    tc[:, 2:, 2:] = 2.0**2 * np.eye(2)
    return tm, tc, rng.uniform(0, side, (n, 2)), np.tile(30.0**2 * np.eye(2), (n, 1, 1)), rng.uniform(0, 10, n)


def test_predicted_choice_is_the_argmin_and_grows_with_speed() -> None:
    picks = []
    for scale in (0.01, 1.0, 10.0):
        choice = predicted_choice(*_fast_scene(scale), threshold=9.21)
        curve = choice.cost_reports if choice.on_reports else choice.cost_tracks
        assert choice.m == int(np.argmin(curve)) + 1
        assert curve[choice.m - 1] <= min(choice.cost_reports.min(), choice.cost_tracks.min())
        picks.append(max(int(np.argmin(choice.cost_tracks)), int(np.argmin(choice.cost_reports))))
    assert picks[0] <= picks[1] <= picks[2] and picks[2] > picks[0], picks


def test_predicted_choice_rejects_static_tracks() -> None:
    tm, tc, rm, rc, rt = _scene(1, 5, 5, 2, False)
    with pytest.raises(ValueError, match="static"):
        predicted_choice(tm, tc, rm, rc, rt, threshold=9.21)
