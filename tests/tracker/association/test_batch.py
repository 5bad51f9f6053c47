"""Batch association against enumeration of every partition (small K), dense numerical integration,
and the greedy tracker's own decisions."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from pipeline.prior import TerrainPrior
from tests.tracker.association.test_greedy import cos_prior, scenario, uniform_prior
from tracker.association.batch import (
    BatchAssociator,
    ReportStats,
    batch_estimate,
    cluster_log_lik,
    gate_bound,
    log_posterior,
)
from tracker.association.batch_kernels import choose, move_log_weights
from tracker.integrate import integrate
from tracker.models.sfunc import ExpS, PoissonS, log_s
from tracker.study.simulate import simulate
from tracker.types.reports import Reports


@functools.cache
def bundled_prior() -> TerrainPrior:
    from pipeline.build.region import build_region_prior
    from pipeline.config.region import load_config
    from tests.pipeline.gis_helpers import REGION_TOML

    return build_region_prior(load_config(REGION_TOML), progress=False)


def partitions(K: int) -> np.ndarray:
    """Every partition of K items as restricted growth strings (Bell(K), K)."""
    out = [[0]]
    for _ in range(1, K):
        out = [p + [c] for p in out for c in range(max(p) + 2)]
    return np.array(out, np.int64)


def enumerate_lp(ba: BatchAssociator, reports: Reports) -> tuple[np.ndarray, np.ndarray]:
    """(partitions, ln p(Λ|Z) normalised over all of them), from the 2^K table."""
    table = ba._table(ReportStats.of(reports))
    parts = partitions(len(reports))
    bit = 1 << np.arange(len(reports))
    lp = np.zeros(parts.shape[0])
    n = parts.max(1) + 1
    for c in range(len(reports)):
        masks = ((parts == c) * bit).sum(1)
        lp += np.where(masks > 0, table[masks], 0.0)
    lp += log_s(ba.s_model, n, len(reports))
    return parts, lp - np.logaddexp.reduce(lp)


def canon(labels: np.ndarray) -> tuple:
    """Restricted growth string of a labelling (first appearance order)."""
    seen: dict[int, int] = {}
    return tuple(seen.setdefault(int(x), len(seen)) for x in labels)


def small_scene(seed: int, K: int, prior: TerrainPrior, n_targets: int = 3, spread=(60.0, 300.0)) -> Reports:
    rep, _ = scenario(seed, n_targets=n_targets, n_reports=K, spread=spread)
    if prior.grid.bounds[0] != 0.0:  # move the scene into the prior's window
        xmin, ymin, xmax, ymax = prior.grid.bounds
        shift = np.array([xmin + 0.5 * (xmax - xmin) - 7000.0, ymin + 0.5 * (ymax - ymin) - 7000.0])
        rep = Reports.create(rep.means + shift, rep.covs, rep.times, rep.truth)
    return rep


PRIORS = {"cos": cos_prior, "uniform": uniform_prior}


def test_cluster_log_lik_matches_dense_integration() -> None:
    """ln L_C of 1-4 reports against Σ over the prior's cells of r(y) Π G(z_k; y, V_k) · cell area."""
    prior = cos_prior()
    g = prior.grid
    rep = small_scene(4, 4, prior, n_targets=1, spread=(150.0, 400.0))
    rs = ReportStats.of(rep)
    rows, cols = np.mgrid[0 : g.height, 0 : g.width]
    x = g.transform.c + (cols + 0.5) * g.dx
    y = g.transform.f - (rows + 0.5) * g.dy
    for members in ([0], [0, 1], [1, 2, 3], [0, 1, 2, 3]):
        m = np.array(members)
        log_dense = np.log(prior.density) + math.log(g.dx * g.dy)
        for k in m:
            d = np.stack([x - rep.means[k, 0], y - rep.means[k, 1]], -1)
            vi = np.linalg.inv(rep.covs[k])
            log_dense = log_dense - 0.5 * np.einsum("...i,ij,...j->...", d, vi, d) - math.log(2 * math.pi) - 0.5 * math.log(np.linalg.det(rep.covs[k]))
        dense = np.logaddexp.reduce(log_dense[np.isfinite(log_dense)])
        ll = cluster_log_lik(prior, "TT", np.array([m.size]), rs.vinv[m].sum(0)[None], rs.hv[m].sum(0)[None],
                             rs.qv[m].sum(keepdims=True), rs.ldv[m].sum(keepdims=True), rs.origin)[0]
        assert abs(ll - dense) < 2e-3, (members, ll, dense)


def test_log_posterior_matches_enumeration_table() -> None:
    prior = cos_prior()
    rep = small_scene(2, 6, prior)
    for variant, s in (("TT", PoissonS(5.0)), ("UU", ExpS(-1.0))):
        ba = BatchAssociator(prior, variant, s_model=s)
        parts, lp = enumerate_lp(ba, rep)
        raw = [log_posterior(prior, rep, parts[i], s, variant) for i in (0, 7, 100, parts.shape[0] - 1)]
        diffs = np.array(raw) - lp[[0, 7, 100, parts.shape[0] - 1]]
        assert np.ptp(diffs) < 1e-9  # one common constant: the normaliser


def test_greedy_decisions_are_the_stepwise_argmax() -> None:
    """With S = e^{-nτ} each greedy step is the argmax of this model's conditional over the reports so far."""
    prior = cos_prior()
    rep, _ = scenario(7, n_targets=8, n_reports=30, spread=(20.0, 150.0))
    for variant in ("UU", "TT"):
        ba = BatchAssociator(prior, variant, tau=-1.7)
        g = ba.greedy(rep)
        rs = ReportStats.of(rep)
        for k in range(1, len(rep)):
            prev = g[:k]
            opts = {}
            for c in np.unique(prev):
                m = np.append(np.flatnonzero(prev == c), k)
                both = [m, m[:-1]]
                ll = cluster_log_lik(prior, variant, np.array([x.size for x in both]), np.array([rs.vinv[x].sum(0) for x in both]),
                                     np.array([rs.hv[x].sum(0) for x in both]), np.array([rs.qv[x].sum() for x in both]),
                                     np.array([rs.ldv[x].sum() for x in both]), rs.origin)
                opts[c] = ll[0] - ll[1]
            single = cluster_log_lik(prior, variant, np.array([1]), rs.vinv[[k]], rs.hv[[k]], rs.qv[[k]], rs.ldv[[k]], rs.origin)[0]
            best = max(opts, key=opts.get)
            choice = "new" if single + 1.7 > opts[best] else best
            want = "new" if g[k] not in prev else g[k]
            top = max(opts[best], single + 1.7)
            close = abs(opts[best] - (single + 1.7)) < 1e-6 * max(1.0, abs(top))
            assert choice == want or close, (variant, k)


@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_integrate_path_gives_the_table_chain(variant: str) -> None:
    """The production path (chunked rounds, gate, integrate) and the one-report-at-a-time table path
    walk the same chain for the same random stream."""
    prior = cos_prior()
    rep = small_scene(11, 7, prior)
    chains = []
    for table, chunk, cache in ((True, 1, None), (False, 64, True), (False, 3, False)):
        ba = BatchAssociator(prior, variant, s_model=PoissonS(4.0), table=table, chunk=chunk, cache=cache)
        ch = ba.chain(rep, np.zeros(len(rep), np.int64))
        rng = np.random.default_rng(5)
        seq = []
        for _ in range(25):
            ch.sweep(1.0, rng)
            seq.append(canon(ch.labels))
        assert ch.lp == pytest.approx(log_posterior(prior, rep, ch.labels, PoissonS(4.0), variant), abs=1e-8)
        chains.append(seq)
    assert chains[0] == chains[1] == chains[2]
    assert len(set(chains[0])) > 1  # the chain moved


@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_cached_sampler_walks_the_uncached_chain(variant: str) -> None:
    """The ln L cache (keyed by member set) changes no draw: the same samples, split-merge included,
    and every cached value is the cluster's ln L integrated afresh."""
    prior = cos_prior()
    rep = simulate(prior, 3, n_targets=15, n_reports=40).reports
    runs = [BatchAssociator(prior, variant, s_model=PoissonS(15.0), mode="sample", burn_in=3, samples=30, split_merge=3,
                            seed=4, cache=cache).fit(rep) for cache in (False, True)]
    np.testing.assert_array_equal(runs[0].pair_prob, runs[1].pair_prob)
    np.testing.assert_array_equal(runs[0].nd_prob, runs[1].nd_prob)
    assert runs[1].stats["integrals"] < runs[0].stats["integrals"] or variant == "UU"
    ba = BatchAssociator(prior, variant, s_model=PoissonS(15.0), seed=4)
    ch = ba.chain(rep, ba.greedy(rep))
    rng = np.random.default_rng(0)
    for _ in range(5):
        ch.sweep(1.0, rng)
        ch.split_merge(1.0, rng, ba._pairs(ch.rs), 3, 3)
    assert len(ch.cache) > 0
    rs = ch.rs
    live = np.flatnonzero(ch.cnt > 0)
    for c in live:
        members = np.flatnonzero(ch.labels == c)
        assert int(np.bitwise_xor.reduce(rs.key[members])) == int(ch.zh[c])
        direct = log_posterior(prior, Reports.create(rep.means[members], rep.covs[members], rep.times[members]), np.zeros(members.size, np.int64), PoissonS(15.0), variant) \
            - float(log_s(PoissonS(15.0), 1, members.size))
        if members.size > 1:
            assert ch.cache[int(ch.zh[c])] == pytest.approx(direct, abs=1e-8)
    assert ch.lp == pytest.approx(log_posterior(prior, rep, ch.labels, PoissonS(15.0), variant), abs=1e-8)


@pytest.mark.parametrize("prior_name", ["cos", "uniform", "bundled"])
@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_map_equals_enumerated_map(prior_name: str, variant: str) -> None:
    prior = bundled_prior() if prior_name == "bundled" else PRIORS[prior_name]()
    seeds = range(3) if prior_name == "bundled" else range(4)
    for seed in seeds:
        K = 5 + seed % 4
        rep = small_scene(100 + seed, K, prior)
        for s in (ExpS(-1.7), PoissonS(3.0)):
            ba = BatchAssociator(prior, variant, s_model=s, table=True, anneal=8, restarts=1, split_merge=2, seed=seed)
            res = ba.fit(rep)
            parts, lp = enumerate_lp(ba, rep)
            best = parts[np.argmax(lp)]
            assert canon(res.labels) == canon(best), (seed, s)
            assert res.log_posterior >= res.greedy_log_posterior - 1e-9


def _sample_tv(variant: str, sweeps: int, seed: int) -> float:
    prior = cos_prior()
    # three targets within 1.5 km, 150-400 m noise: 5-7 partitions above 1 %, entropy 1.7-1.8 nats
    rep, _ = scenario(22, n_targets=3, n_reports=6, size_m=3000.0, spread=(150.0, 400.0))
    ba = BatchAssociator(prior, variant, s_model=PoissonS(3.0), table=True)
    parts, lp = enumerate_lp(ba, rep)
    ch = ba.chain(rep, ba.greedy(rep))
    rng = np.random.default_rng(seed)
    pairs = ba._pairs(ch.rs)
    counts: dict[tuple, int] = {}
    for s in range(50 + sweeps):
        ch.sweep(1.0, rng)
        ch.split_merge(1.0, rng, pairs, 1, 3)
        if s >= 50:
            key = canon(ch.labels)
            counts[key] = counts.get(key, 0) + 1
    exact = {canon(p): math.exp(v) for p, v in zip(parts, lp, strict=True)}
    return 0.5 * sum(abs(counts.get(k, 0) / sweeps - p) for k, p in exact.items())


@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_sampler_matches_enumerated_posterior_quick(variant: str) -> None:
    assert _sample_tv(variant, 1500, 1) < 0.06


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_sampler_matches_enumerated_posterior(variant: str) -> None:
    """Total variation below 0.02 at 20,000 sweeps (each: one Gibbs scan and one split-merge proposal)."""
    assert _sample_tv(variant, 20000, 2) < 0.02


@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_gate_bound_holds(variant: str) -> None:
    """Brute force: the conditional mass of the clusters outside the gate is below gate_bound."""
    prior = cos_prior()
    gamma = 3.0
    log_rmax = math.log(prior.density.max()) + math.log(2.0)
    for seed in range(3):
        rep = small_scene(40 + seed, 7, prior, n_targets=4)
        s = PoissonS(4.0)
        ba = BatchAssociator(prior, variant, s_model=s, table=True)
        rs = ReportStats.of(rep)
        table = ba._table(rs)
        rng = np.random.default_rng(seed)
        labels = rng.integers(0, 3, len(rep))
        K = len(rep)
        for i in range(K):
            rest = labels.copy()
            rest[i] = -1
            clusters = [np.flatnonzero(rest == c) for c in np.unique(rest[rest >= 0])]
            n_minus = len(clusters)
            masks = [int(sum(1 << int(k) for k in m)) for m in clusters]
            bi = 1 << i
            w = [table[mk | bi] - table[mk] + float(log_s(s, n_minus, K)) for mk in masks]
            w_new = table[bi] + float(log_s(s, n_minus + 1, K))
            total = np.logaddexp.reduce(np.array(w + [w_new]))
            out, log_i = [], []
            for m, wc in zip(clusters, w, strict=True):
                P = rs.vinv[m].sum(0)
                B = np.linalg.inv(P)
                b = B @ rs.hv[m].sum(0)
                r = (rep.means[i] - rs.origin) - b
                if r @ np.linalg.solve(B + rep.covs[i], r) > gamma:
                    out.append(wc)
                    log_i.append(math.log(integrate(prior, (b + rs.origin)[None], B[None])[0]) if variant == "TT"
                                 else -math.log(14000.0**2))
            if not out:
                continue
            neglected = math.exp(np.logaddexp.reduce(np.array(out)) - total)
            lrmax = log_rmax if variant == "TT" else -math.log(14000.0**2)
            bound = gate_bound(float(log_s(s, n_minus, K) - log_s(s, n_minus + 1, K)), gamma, lrmax,
                               float(np.linalg.slogdet(rep.covs[i])[1]), float(table[bi]), np.array(log_i))
            assert neglected <= bound, (seed, i, neglected, bound)


@pytest.mark.parametrize("variant", ["UU", "TT"])
def test_batch_beats_greedy_on_simulated_data(variant: str) -> None:
    prior = cos_prior()
    for seed in range(2):
        rep = simulate(prior, seed, n_targets=60, n_reports=60).reports
        res = BatchAssociator(prior, variant, tau=-1.7, anneal=4, restarts=0, icm_max=10, seed=seed).fit(rep)
        assert res.log_posterior >= res.greedy_log_posterior - 1e-9
        assert res.log_posterior == pytest.approx(log_posterior(prior, rep, res.labels, ExpS(-1.7), variant), abs=1e-6)
        est = batch_estimate(prior, rep, res.labels, variant)
        assert est.counts.sum() == len(rep) and est.means.shape == (res.n_detected, 2)


def test_sample_mode_outputs() -> None:
    prior = cos_prior()
    rep = small_scene(5, 8, prior)
    res = BatchAssociator(prior, "TT", s_model=PoissonS(3.0), mode="sample", burn_in=5, samples=40, split_merge=1, seed=3).fit(rep)
    assert res.pairs.shape[1] == 2 and (res.pairs[:, 0] < res.pairs[:, 1]).all()
    assert ((res.pair_prob >= 0) & (res.pair_prob <= 1)).all()
    assert res.nd_prob.sum() == pytest.approx(1.0) and res.nd_values.min() >= 1
    assert ((res.membership >= 0) & (res.membership <= 1)).all()


def test_move_kernel_matches_the_formula() -> None:
    """move_log_weights / choose against the written-out conditional p(o) ∝ exp(beta · w_o)."""
    delta = np.array([-3.0, 0.5, -1.0])
    w = move_log_weights(delta, -2.0, -4.0, -5.5)
    np.testing.assert_allclose(w, [-7.0, -3.5, -5.0, -7.5])
    p = np.exp(0.7 * (w - w.max()))
    p /= p.sum()
    u = (np.arange(4000) + 0.5) / 4000
    freq = np.bincount([choose(w, 0.7, x) for x in u], minlength=4) / u.size
    np.testing.assert_allclose(freq, p, atol=1e-3)
    assert choose(w, math.inf, 0.9) == 1
