"""The association-estimation tracker against an independent, ungated, one-report-at-a-time reference
written from paper 1's Fig. 3 (information-form Gaussian products, explicit F and Q matrices)."""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import Tracker, associate, perfect_estimate
from tracker.association.walk import widened_gate as _widened_gate
from tracker.gating.gate import gate_unchecked
from tracker.integrate import integrate
from tracker.models.motion import ConstantVelocity
from tracker.models.sfunc import ExpS, PoissonS, log_s
from tracker.types.reports import Reports

GOLDEN = Path(__file__).parent / "golden" / "association.json"


@functools.cache
def cos_prior(size_m: float = 14000.0, cell: float = 20.0) -> TerrainPrior:
    """A bumpy prior with a structural-zero lake, on a UTM grid."""
    g = Grid.from_bounds((0.0, 0.0, size_m, size_m), cell, "EPSG:32634")
    yy, xx = np.mgrid[0 : g.height, 0 : g.width]
    r = 1.0 + 0.9 * np.cos(xx / 9.0) * np.cos(yy / 13.0)
    r[50:130, 50:170] = 0.0  # a lake (x 1000-3400 m, y 11400-13000 m), outside the targets' window
    return TerrainPrior.from_array(r, g)


def uniform_prior(size_m: float = 14000.0) -> TerrainPrior:
    return TerrainPrior.uniform(Grid.from_bounds((0.0, 0.0, size_m, size_m), 20.0, "EPSG:32634"))


def scenario(seed: int, n_targets: int = 40, n_reports: int = 100, size_m: float = 14000.0, spread=(20.0, 150.0)):
    """Targets uniform in the central half of the region; reports with random elongated covariances."""
    rng = np.random.default_rng(seed)
    lo, hi = 0.25 * size_m, 0.75 * size_m
    targets = rng.uniform(lo, hi, size=(n_targets, 2))
    truth = rng.integers(0, n_targets, size=n_reports)
    angle = rng.uniform(0, np.pi, n_reports)
    sd = rng.uniform(*spread, size=(n_reports, 2))
    R = np.stack([np.stack([np.cos(angle), -np.sin(angle)], -1), np.stack([np.sin(angle), np.cos(angle)], -1)], 1)
    covs = R @ (sd[:, :, None] ** 2 * np.eye(2)) @ R.transpose(0, 2, 1)
    covs = 0.5 * (covs + covs.transpose(0, 2, 1))
    noise = np.einsum("kij,kj->ki", np.linalg.cholesky(covs), rng.standard_normal((n_reports, 2)))
    return Reports.create(targets[truth] + noise, covs, np.arange(n_reports) * 6.0, truth), targets


def reference(prior, reports, variant, s_model, motion=None):
    """Fig. 3 verbatim: every hypothesis scored for every report, no gate, plain loops."""
    xmin, ymin, xmax, ymax = prior.grid.bounds
    log_u = -math.log((xmax - xmin) * (ymax - ymin))
    terrain = variant == "TT"

    def log_int(m, c):
        """ln ∫G r for a stack of Gaussians (position part), one numba thread: tiny batches."""
        m, c = np.atleast_2d(m), c.reshape(-1, *c.shape[-2:])
        threads = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            with np.errstate(divide="ignore"):
                return np.log(integrate(prior, m[:, :2], c[:, :2, :2]))
        finally:
            numba.set_num_threads(threads)

    hyp = []  # [mean, cov, log_c, time]
    assign = []
    for j in range(len(reports)):
        z, V, t = reports.means[j], reports.covs[j], reports.times[j]
        n, k = len(hyp), j
        ratio = float(log_s(s_model, n + 1, k + 1) - log_s(s_model, n, k + 1))
        log_iz = float(log_int(z, V)[0]) if terrain else log_u
        cands = []
        for a, A, log_c, tq in hyp:
            if motion is not None:
                dt = t - tq
                F = np.eye(4)
                F[0, 2] = F[1, 3] = dt
                Q = motion.q * np.array(
                    [[dt**3 / 3, 0, dt**2 / 2, 0], [0, dt**3 / 3, 0, dt**2 / 2], [dt**2 / 2, 0, dt, 0], [0, dt**2 / 2, 0, dt]]
                )
                a, A = F @ a, F @ A @ F.T + Q
                if terrain:
                    log_c = float(log_int(a, A)[0])
            Hm = np.eye(a.size)[:2]
            S = Hm @ A @ Hm.T + V
            r = z - Hm @ a
            log_g = -0.5 * (r @ np.linalg.solve(S, r) + math.log(np.linalg.det(S)) + 2 * math.log(2 * math.pi))
            # Information form of the posterior (independent of the tracker's covariance form).
            Ai = np.linalg.inv(A)
            B = np.linalg.inv(Ai + Hm.T @ np.linalg.inv(V) @ Hm)
            b = B @ (Ai @ a + Hm.T @ np.linalg.solve(V, z))
            cands.append((log_g, log_c, b, B))
        best, arg, post = -np.inf, -1, None
        if cands:
            log_i = log_int(np.array([c[2] for c in cands]), np.array([c[3] for c in cands])) if terrain else None
            for q, (log_g, log_c, b, B) in enumerate(cands):
                score = log_g + (log_i[q] - log_c if terrain else 0.0)
                if score > best:
                    best, arg, post = score, q, (b, B, log_i[q] if terrain else log_u)
        if arg < 0 or log_iz + ratio > best:
            if motion is None:
                hyp.append((z.copy(), V.copy(), log_iz, t))
            else:
                a0 = np.zeros(4)
                a0[:2] = z
                A0 = np.zeros((4, 4))
                A0[:2, :2] = V
                A0[2:, 2:] = motion.velocity_std**2 * np.eye(2)
                hyp.append((a0, A0, log_iz, t))
            assign.append(len(hyp) - 1)
        else:
            hyp[arg] = (post[0], post[1], post[2], t)
            assign.append(arg)
    return np.array(assign), hyp


@pytest.fixture(scope="module")
def prior():
    return cos_prior()


@pytest.mark.parametrize("variant", ["UU", "TT"])
@pytest.mark.parametrize("tau", [-1.7, 1.0])
@pytest.mark.parametrize("gamma", [41.4, 3.0])
def test_gated_matches_ungated_reference(prior, variant, tau, gamma):
    # gamma = 3 is far too narrow: decisions must still match, through the widening fallback.
    reports, _ = scenario(seed=3, n_targets=30, n_reports=60)
    want, hyp = reference(prior, reports, variant, ExpS(tau))
    res = associate(prior, reports, variant, tau=tau, gamma=gamma, block=16)
    np.testing.assert_array_equal(res.assignments, want)
    assert res.n_detected == len(hyp)
    np.testing.assert_allclose(res.hypotheses.means, np.array([h[0] for h in hyp]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(res.hypotheses.log_c, np.array([h[2] for h in hyp]), rtol=1e-9)
    if gamma < 10:
        assert res.stats["widened"] > 0


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 10**6),
    variant=st.sampled_from(["UU", "TT"]),
    tau=st.floats(-3.0, 3.0),
    gamma=st.sampled_from([2.0, 9.0, 41.4]),
    block=st.integers(1, 40),
    crowd=st.sampled_from([5, 40]),
)
def test_decisions_match_reference_property(seed, variant, tau, gamma, block, crowd):
    prior = cos_prior()
    reports, _ = scenario(seed, n_targets=crowd, n_reports=30, spread=(10.0, 300.0))
    want, _ = reference(prior, reports, variant, ExpS(tau))
    got = associate(prior, reports, variant, tau=tau, gamma=gamma, block=block)
    np.testing.assert_array_equal(got.assignments, want)


def test_poisson_s_matches_reference(prior):
    reports, _ = scenario(seed=5, n_targets=20, n_reports=50)
    model = PoissonS(25.0)
    want, _ = reference(prior, reports, "TT", model)
    res = associate(prior, reports, "TT", s_model=model)
    np.testing.assert_array_equal(res.assignments, want)


def test_constant_velocity_matches_reference(prior):
    rng = np.random.default_rng(8)
    n, k = 6, 48
    start = rng.uniform(5000, 9000, (n, 2))
    vel = rng.uniform(-8, 8, (n, 2))
    truth = rng.integers(0, n, k)
    times = np.sort(rng.uniform(0, 300, k))
    covs = np.tile(np.diag([60.0**2, 30.0**2]), (k, 1, 1))
    pos = start[truth] + vel[truth] * times[:, None] + rng.normal(0, 1, (k, 2)) * [60.0, 30.0]
    reports = Reports.create(pos, covs, times, truth)
    motion = ConstantVelocity(q=0.05, velocity_std=10.0)
    for variant in ("UU", "TT"):
        want, hyp = reference(prior, reports, variant, ExpS(0.0), motion)
        res = associate(prior, reports, variant, tau=0.0, motion=motion, block=8)
        np.testing.assert_array_equal(res.assignments, want)
        np.testing.assert_allclose(res.hypotheses.means, np.array([h[0] for h in hyp]), atol=1e-6)


def test_uniform_prior_tt_equals_uu():
    prior = uniform_prior()
    for seed in range(3):
        reports, _ = scenario(seed, n_targets=40, n_reports=120)
        tt = associate(prior, reports, "TT", tau=-1.0)
        uu = associate(prior, reports, "UU", tau=-1.0)
        np.testing.assert_array_equal(tt.assignments, uu.assignments)
        # The terrain normalisers of a constant prior are the constant itself.
        # (to the terrace rule's accuracy goal of 0.1 %).
        np.testing.assert_allclose(tt.hypotheses.log_c, uu.estimate.log_c, atol=1e-3)


def test_well_separated_target_forms_one_hypothesis(prior):
    rng = np.random.default_rng(2)
    target = np.array([3000.0, 11000.0])
    covs = np.tile(np.array([[900.0, 300.0], [300.0, 400.0]]), (25, 1, 1))
    z = target + np.einsum("kij,kj->ki", np.linalg.cholesky(covs), rng.standard_normal((25, 2)))
    reports = Reports.create(z, covs)
    for variant in ("UU", "UT", "TT"):
        res = associate(prior, reports, variant, tau=-1.7)
        assert res.n_detected == 1
        assert np.all(res.assignments == 0)
        assert res.hypotheses.counts[0] == 25


def test_static_fusion_is_order_independent(prior):
    rng = np.random.default_rng(4)
    target = np.array([7000.0, 7000.0])
    covs = np.tile(np.diag([50.0**2, 50.0**2]), (12, 1, 1))
    z = target + rng.normal(0, 50.0, (12, 2))
    reports = Reports.create(z, covs, truth=np.zeros(12, int))
    oracle = perfect_estimate(prior, reports)  # information form: Σ V⁻¹ and Σ V⁻¹ z
    for perm_seed in range(4):
        perm = np.random.default_rng(perm_seed).permutation(12)
        res = associate(prior, reports.subset(perm), "TT", tau=10.0)  # large tau: always fuse
        assert res.n_detected == 1
        np.testing.assert_allclose(res.hypotheses.means[0], oracle.means[0], atol=1e-8)
        np.testing.assert_allclose(res.hypotheses.covs[0], oracle.covs[0], rtol=1e-9)
        np.testing.assert_allclose(res.hypotheses.log_c[0], oracle.log_c[0], rtol=1e-12)


def test_streaming_equals_batch(prior):
    reports, _ = scenario(seed=11, n_targets=25, n_reports=80)
    batch = associate(prior, reports, "TT", tau=-1.7)
    for block, chunk in ((1, 1), (5, 7), (64, 33)):
        tr = Tracker(prior, "TT", tau=-1.7, block=block)
        got = np.concatenate([tr.update(reports.subset(slice(s, s + chunk))) for s in range(0, len(reports), chunk)])
        np.testing.assert_array_equal(got, batch.assignments)
        assert tr.n_detected_ == batch.n_detected


def test_ut_associates_as_uu_and_estimates_with_terrain(prior):
    reports, _ = scenario(seed=6)
    uu = associate(prior, reports, "UU", tau=0.5)
    ut = associate(prior, reports, "UT", tau=0.5)
    np.testing.assert_array_equal(ut.assignments, uu.assignments)
    assert not uu.estimate.terrain and ut.estimate.terrain
    want = np.log(integrate(prior, uu.hypotheses.means, uu.hypotheses.covs))
    np.testing.assert_allclose(ut.estimate.log_c, want, rtol=1e-12)


def test_perfect_estimate_groups_by_truth(prior):
    reports, targets = scenario(seed=9, n_targets=10, n_reports=60, spread=(10.0, 30.0))
    est = perfect_estimate(prior, reports)
    np.testing.assert_array_equal(est.labels, np.unique(reports.truth))
    for lab, mean, cov in zip(est.labels, est.means, est.covs, strict=True):
        sel = reports.truth == lab
        info = np.linalg.inv(reports.covs[sel]).sum(axis=0)
        np.testing.assert_allclose(cov, np.linalg.inv(info), rtol=1e-9)
        assert np.linalg.norm(mean - targets[lab]) < 6 * math.sqrt(np.linalg.eigvalsh(cov)[-1])


# ---- bad input: clear errors, nothing already fused is lost


def _state(tr: Tracker):
    h = tr.hypotheses_
    return (h.means.copy(), h.covs.copy(), h.log_c.copy(), tr.n_reports_)


def _assert_same(a, b):
    for x, y in zip(a[:3], b[:3], strict=True):
        np.testing.assert_array_equal(x, y)
    assert a[3] == b[3]


def test_bad_reports_raise_and_leave_state(prior):
    reports, _ = scenario(seed=1, n_reports=30)
    tr = Tracker(prior, "TT", tau=-1.7)
    tr.update(reports)
    before = _state(tr)
    z = reports.means[:3].copy()
    z[1, 0] = np.nan
    with pytest.raises(ValueError, match=r"indices \[1\]"):
        tr.update(Reports(z, reports.covs[:3], reports.times[:3], reports.truth[:3]))
    bad = reports.covs[:3].copy()
    bad[2] = [[1.0, 2.0], [2.0, 1.0]]
    with pytest.raises(ValueError, match=r"positive definite at indices \[2\]"):
        tr.update(Reports(reports.means[:3], bad, reports.times[:3], reports.truth[:3]))
    _assert_same(before, _state(tr))


def test_reports_off_the_prior(prior):
    reports, _ = scenario(seed=1, n_reports=10)
    z = reports.means.copy()
    z[4] = [-50000.0, 7000.0]  # far off the grid
    z[7] = [2200.0, 12200.0]  # in the middle of the lake
    covs = reports.covs.copy()
    covs[7] = np.diag([25.0, 25.0])
    off = Reports.create(z, covs, reports.times)
    tr = Tracker(prior, "TT", tau=-1.7)
    with pytest.raises(ValueError, match=r"indices \[4, 7\]"):
        tr.update(off)
    assert tr.n_detected_ == 0 and tr.n_reports_ == 0
    skip = Tracker(prior, "TT", tau=-1.7, off_prior="skip")
    got = skip.update(off)
    assert got[4] == -1 and got[7] == -1 and np.all(np.delete(got, [4, 7]) >= 0)
    assert skip.n_reports_ == 8
    # UU takes the uniform density over all space: off-grid reports are fine there.
    assert np.all(associate(prior, off, "UU", tau=-1.7).assignments >= 0)


def test_times_backwards_with_motion(prior):
    reports, _ = scenario(seed=1, n_reports=10)
    tr = Tracker(prior, "UU", tau=0.0, motion=ConstantVelocity())
    tr.update(reports.subset(slice(0, 5)))
    before = _state(tr)
    with pytest.raises(ValueError, match=r"backwards at indices \[0\]"):
        tr.update(reports.subset(slice(2, 4)))
    _assert_same(before, _state(tr))
    rev = reports.subset(np.array([5, 7, 6]))
    with pytest.raises(ValueError, match=r"backwards at indices \[2\]"):
        tr.update(rev)


def test_bad_arguments(prior):
    with pytest.raises(ValueError, match="variant"):
        Tracker(prior, "XT", tau=1.0)
    with pytest.raises(ValueError, match="exactly one of tau"):
        Tracker(prior, "TT")
    with pytest.raises(ValueError, match="gamma"):
        Tracker(prior, "TT", tau=1.0, gamma=-1.0)


# ---- regression goldens: any change in decisions fails (regenerate deliberately: python -m tests.tracker.association.test_greedy)

GOLDEN_CASES = [(seed, variant, tau) for seed in (21, 22) for variant in ("UU", "TT") for tau in (-1.7, 0.5)]


def _golden_run(seed, variant, tau):
    res = associate(cos_prior(), scenario(seed, n_targets=60, n_reports=100)[0], variant, tau=tau)
    return {"assignments": res.assignments.tolist(), "n_detected": res.n_detected}


def test_regression_goldens():
    stored = json.loads(GOLDEN.read_text())
    for seed, variant, tau in GOLDEN_CASES:
        key = f"{seed}/{variant}/{tau}"
        assert _golden_run(seed, variant, tau) == stored[key], key


if __name__ == "__main__":
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps({f"{s}/{v}/{t}": _golden_run(s, v, t) for s, v, t in GOLDEN_CASES}) + "\n")
    print(f"wrote {GOLDEN}")


def test_empty_update_changes_nothing(prior):
    tr = Tracker(prior, "TT", tau=0.0)
    empty = Reports.create(np.zeros((0, 2)), np.zeros((0, 2, 2)))
    assert tr.update(empty).shape == (0,)
    assert tr.n_detected_ == 0 and tr.n_reports_ == 0
    assert associate(prior, empty, "UT", tau=0.0).estimate.means.shape == (0, 2)


def test_stale_report_fused_keeps_its_normaliser(prior):
    # Two targets 300 m apart (inside each other's wide gate, far in score): the second block's report of A
    # sees B just changed, rescores it inside numba, and must fuse into A with A's new normaliser.
    a, b = np.array([7000.0, 7000.0]), np.array([7300.0, 7000.0])
    z = np.array([a, b, b + [5.0, -3.0], a + [-4.0, 6.0]])
    covs = np.tile(np.diag([900.0, 900.0]), (4, 1, 1))
    reports = Reports.create(z, covs)
    want, hyp = reference(prior, reports, "TT", ExpS(-1.0))
    tr = Tracker(prior, "TT", tau=-1.0, gamma=80.0)
    got = np.concatenate([tr.update(reports.subset(slice(0, 2))), tr.update(reports.subset(slice(2, 4)))])
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(tr.hypotheses_.log_c, np.array([h[2] for h in hyp]), rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_blocks_equal_one_at_a_time_at_scale(variant):
    # Thousands of reports in crowded blocks: every refresh, in-kernel rescoring and low-c check runs.
    prior = cos_prior()
    reports, _ = scenario(17, n_targets=800, n_reports=4000, size_m=14000.0, spread=(10.0, 120.0))
    one = Tracker(prior, variant, tau=-1.0, block=1)
    want = np.concatenate([one.update(reports.subset(slice(i, i + 1))) for i in range(len(reports))])
    got = associate(prior, reports, variant, tau=-1.0, block=1024)
    np.testing.assert_array_equal(got.assignments, want)
    np.testing.assert_allclose(got.hypotheses.log_c, one.hypotheses_.log_c, rtol=1e-12)


@pytest.mark.parametrize("variant", ["UU", "UT"])
@pytest.mark.parametrize("gamma", [41.4, 3.0])
def test_crowded_gate_matches_reference(prior, variant, gamma):
    # 200 reports at one spot with S favouring new targets: gates of 100+ hypotheses (the sequential loop's
    # candidate buffers grow), and gamma = 3 widens through the hypotheses' grid.
    rng = np.random.default_rng(5)
    n = 200
    sd = rng.uniform(10.0, 60.0, (n, 2))
    covs = np.stack([np.diag(s**2) for s in sd])
    reports = Reports.create(7000.0 + rng.normal(0.0, 30.0, (n, 2)), covs)
    want, hyp = reference(prior, reports, "UU", ExpS(-10.0))
    res = associate(prior, reports, variant, tau=-10.0, gamma=gamma)
    np.testing.assert_array_equal(res.assignments, want)
    assert res.n_detected == len(hyp) > 64 and res.hypotheses.counts.max() > 1
    assert gamma > 40 or res.stats["widened"] > 0
    np.testing.assert_allclose(res.hypotheses.means, np.array([h[0] for h in hyp]), rtol=0, atol=1e-6)


@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_timings_split_the_total(prior, variant):
    # The profile's steps are disjoint parts of the update's time (Python overhead is what is left).
    from tracker.association.greedy import TIMINGS

    tr = Tracker(prior, variant, tau=-1.0, block=16)
    tr.update(scenario(3, n_targets=40, n_reports=100)[0])
    tm = tr.timings_
    assert tuple(tm) == TIMINGS and all(v >= 0.0 for v in tm.values())
    parts = sum(v for k, v in tm.items() if k != "total")
    assert 0.0 < parts <= tm["total"]
    assert tm["walk"] > 0.0
    if variant == "TT":
        assert tm["integrals"] > 0.0 and tm["gate"] > 0.0
    else:  # the sequential loop: gating and products happen inside the walk
        assert tm["gate"] == tm["geometry"] == tm["refresh"] == 0.0


@pytest.mark.parametrize(("tau", "gamma"), [(-1.7, 9.21), (1.0, 9.21), (-1.7, 3.0)])
def test_gates_widened_inside_the_walk_decide_as_the_block_gate_path(tau, gamma, monkeypatch):
    # Targets in a small part of a large prior (r low everywhere): new targets' reports fail the gate
    # bound often. The walk settles those whose widened gate needs no integral itself (walk._widen_here),
    # the others come back to Tracker._block; the gater path (no hypotheses' grid) widens them all in
    # Python by brute force. Decisions and hypotheses must be the same.
    import tracker.association.greedy as greedy

    calls = []
    monkeypatch.setattr(greedy, "widened_gate", lambda *a: calls.append(1) or _widened_gate(*a))
    prior = cos_prior(size_m=40000.0, cell=40.0)
    reports, _ = scenario(seed=11, n_targets=300, n_reports=3000, size_m=40000.0, spread=(5.0, 60.0))
    fast = Tracker(prior, "TT", tau=tau, gamma=gamma, block=256)
    got = fast.update(reports)
    slow = Tracker(prior, "TT", tau=tau, gamma=gamma, block=256, gater=gate_unchecked)
    want = slow.update(reports)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(fast.hypotheses_.log_c, slow.hypotheses_.log_c)
    np.testing.assert_array_equal(fast.hypotheses_.means, slow.hypotheses_.means)
    assert fast.stats_["widened"] == slow.stats_["widened"] > len(calls) > 0


def test_walk_compiles_once_for_static_and_moving_targets():
    """The walk gets the same argument types with and without the static hypotheses' grid
    (``walk.no_grid``), so numba compiles it once: a second signature costs minutes on a cold cache."""
    from tracker.association import walk as walk_module

    prior = cos_prior()
    reports, _ = scenario(5, n_targets=20, n_reports=40)
    static = associate(prior, reports, "TT", tau=2.0, block=8)
    moving = associate(prior, reports, "TT", tau=2.0, motion=ConstantVelocity(q=0.05, velocity_std=10.0), block=8)
    assert static.assignments.size == moving.assignments.size == 40
    assert len(walk_module.walk.signatures) == 1, walk_module.walk.signatures
