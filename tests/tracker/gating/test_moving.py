"""Gating of constant-velocity tracks against reports with their own timestamps: every M_D,
both orientations and both gate forms against the dense brute force."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.gating.test_oracle import assert_same_pairs, brute_force, random_covs
from tracker.gating.gate import gate, gate_checked
from tracker.gating.scene import Scene


def _moving_scene(seed, nt, nr, dim, cond, vmax, scan, q):
    rng = np.random.default_rng(seed)
    side = 600.0
    pos = rng.uniform(0, side, (nt, dim))
    vel = rng.uniform(-vmax, vmax, (nt, dim))
    tm = np.hstack([pos, vel])
    tc = random_covs(rng, nt, 2 * dim, 1.0, 30.0, cond)
    track_times = rng.uniform(-1.0, 0.0, nt)
    report_times = rng.uniform(0.0, scan, nr)
    # put reports near where tracks will be, so pairs exist
    src = rng.integers(0, max(nt, 1), nr)
    rm = rng.uniform(0, side, (nr, dim))
    if nt:
        near = rng.random(nr) < 0.6
        dt = report_times - track_times[src]
        rm[near] = (pos[src] + dt[:, None] * vel[src] + rng.normal(0, 40, (nr, dim)))[near]
    rc = random_covs(rng, nr, dim, 3.0, 60.0, cond)
    return tm, tc, rm, rc, report_times, track_times, np.full(nt, q)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31), nt=st.integers(0, 25), nr=st.integers(0, 25),
       dim=st.sampled_from([2, 3]), cond=st.sampled_from([1.0, 1e3, 1e6]),
       vmax=st.sampled_from([0.0, 30.0, 300.0]), scan=st.sampled_from([0.0, 1.0, 10.0]),
       q=st.sampled_from([0.0, 1.0, 50.0]), m=st.sampled_from(["auto", 1, 2, 5, 40]),
       orientation=st.sampled_from(["auto", "reports", "tracks"]),
       form=st.sampled_from(["gamma", "score"]), buckets=st.sampled_from(["auto", 4]))
def test_moving_matches_brute_force(seed, nt, nr, dim, cond, vmax, scan, q, m, orientation,
                                    form, buckets):
    tm, tc, rm, rc, rt, tt, qq = _moving_scene(seed, nt, nr, dim, cond, vmax, scan, q)
    kw = dict(threshold=11.0) if form == "gamma" else dict(min_score=1e-9)
    t_idx, r_idx, d2 = gate(tm, tc, rm, rc, **kw, return_d2=True, report_times=rt,
                            track_times=tt, process_noise=qq, n_projections=m,
                            orientation=orientation, buckets=buckets)
    ref = dict(gamma=11.0) if form == "gamma" else dict(min_score=1e-9)
    want_d2, limit = brute_force(tm, tc, rm, rc, **ref, report_times=rt, track_times=tt, q=qq)
    assert_same_pairs(t_idx, r_idx, want_d2, limit)
    np.testing.assert_allclose(d2, want_d2[t_idx, r_idx], rtol=1e-6 * cond, atol=1e-9)


def test_static_tracks_ignore_report_times():
    rng = np.random.default_rng(5)
    tm, rm = rng.uniform(0, 100, (20, 2)), rng.uniform(0, 100, (30, 2))
    tc, rc = random_covs(rng, 20, 2, 3, 30), random_covs(rng, 30, 2, 3, 30)
    a = gate(tm, tc, rm, rc, threshold=9.0)
    b = gate(tm, tc, rm, rc, threshold=9.0, report_times=rng.uniform(0, 10, 30))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_moving_input_errors():
    tm = np.zeros((2, 4))
    tc = np.tile(np.eye(4), (2, 1, 1))
    rm, rc = np.zeros((3, 2)), np.tile(np.eye(2), (3, 1, 1))
    with pytest.raises(ValueError, match="report_times"):
        gate(tm, tc, rm, rc, threshold=1.0)
    with pytest.raises(ValueError, match="report_times"):
        gate(tm, tc, rm, rc, threshold=1.0, report_times=np.zeros(2))
    with pytest.raises(ValueError, match="report_times"):
        gate(tm, tc, rm, rc, threshold=1.0, report_times=np.array([0.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match=r"process_noise.*\[1\]"):
        gate(tm, tc, rm, rc, threshold=1.0, report_times=np.zeros(3),
             process_noise=np.array([0.0, -1.0]))
    with pytest.raises(ValueError, match="track_times"):
        gate(tm, tc, rm, rc, threshold=1.0, report_times=np.zeros(3),
             track_times=np.array([0.0, np.inf]))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), nt=st.integers(0, 25), nr=st.integers(0, 25),
       dim=st.sampled_from([2, 3]), moving=st.booleans())
def test_checked_path_gives_the_same_pairs(seed, nt, nr, dim, moving):
    """gate_checked on Scene.assume_valid (callers holding validated arrays) equals gate()."""
    tm, tc, rm, rc, rt, tt, q = _moving_scene(seed, nt, nr, dim, 1e3, 30.0, 5.0, 1.0)
    if not moving:
        tm, tc, rt, tt, q = tm[:, :dim], np.ascontiguousarray(tc[:, :dim, :dim]), None, 0.0, 0.0
    want = gate(tm, tc, rm, rc, threshold=9.0, return_d2=True, report_times=rt, track_times=tt,
                process_noise=q)
    for scene in (Scene.validate(tm, tc, rm, rc, rt, tt, q), Scene.assume_valid(tm, tc, rm, rc, rt, tt, q)):
        got = gate_checked(scene, threshold=9.0, return_d2=True)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
