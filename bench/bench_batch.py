"""Batch association at scale: greedy plus one full Gibbs sweep on the tracker bench's scene
(full: 100,000 static targets / 1,000,000 reports on 100 km x 100 km; quick: 10,000 / 100,000).
Goal: greedy + one sweep <= 30 s on 2 cores, peak memory <= 4 GiB.

Baseline in the same run: a second sweep from the same state and random stream whose rounds gate
against ALL live clusters (the path before the persistent cluster index); it must walk the same chain."""

from __future__ import annotations

import os
import resource
import time

import numpy as np

from bench.bench_tracker import scenario, synthetic_prior
from tracker.association.batch import BatchAssociator
from tracker.association.greedy import Tracker


def run(quick: bool = False) -> dict:
    size_m, n_targets, n_reports = (32_000.0, 10_000, 100_000) if quick else (100_000.0, 100_000, 1_000_000)
    prior = synthetic_prior(size_m)
    reports = scenario(prior, n_targets, n_reports)
    warm = reports.subset(slice(0, 3000))
    ba = BatchAssociator(prior, "TT", tau=-1.7)
    ba.chain(warm, Tracker(prior, "TT", tau=-1.7, off_prior="skip").update(warm)).sweep(1.0, np.random.default_rng(0))
    t0 = time.perf_counter()
    tr = Tracker(prior, "TT", tau=-1.7, off_prior="skip")
    g = np.concatenate([tr.update(reports.subset(slice(s, s + 50_000))) for s in range(0, n_reports, 50_000)])
    t_greedy = time.perf_counter() - t0
    keep = np.flatnonzero(g >= 0)  # the chain takes the reports on the prior
    rep = reports.subset(keep)
    t1 = time.perf_counter()
    ch = ba.chain(rep, g[keep])
    t_chain = time.perf_counter() - t1
    lp0 = ch.lp
    t2 = time.perf_counter()
    moved = ch.sweep(1.0, np.random.default_rng(1))
    t_sweep = time.perf_counter() - t2
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    rounds, integrals = ba.stats_["rounds"], ba.stats_["integrals"]
    base = ba.chain(rep, g[keep])
    base.index.candidates = lambda zc, lam_v: np.flatnonzero(base.cnt > 0)
    t3 = time.perf_counter()
    base.sweep(1.0, np.random.default_rng(1))
    t_base = time.perf_counter() - t3
    same = bool(np.array_equal(base.labels, ch.labels))
    return {"n_reports": n_reports, "n_targets": n_targets, "greedy_s": t_greedy, "chain_setup_s": t_chain,
            "sweep_s": t_sweep, "total_s": t_greedy + t_chain + t_sweep, "moved": moved, "rounds": rounds,
            "integrals": integrals, "lp_greedy": lp0, "lp_after_sweep": ch.lp,
            "n_greedy": int(np.unique(g[keep]).size), "n_after": int(ch.istate[0]), "peak_rss_gib": rss,
            "sweep_gating_all_clusters_s": t_base, "sweep_speedup_vs_all_clusters": t_base / t_sweep,
            "same_chain_as_all_clusters": same, "load_average_1min": os.getloadavg()[0],
            "meets_goal": bool(t_greedy + t_chain + t_sweep <= 30.0 and rss <= 4.0) if not quick else None}
