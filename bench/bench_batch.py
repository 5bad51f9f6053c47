"""Batch association at scale: greedy plus one full Gibbs sweep on the tracker bench's scene
(full: 100,000 static targets / 1,000,000 reports on 100 km x 100 km; quick: 10,000 / 100,000).
Goal: greedy + one sweep <= 30 s on 2 cores, peak memory <= 4 GiB."""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import numpy as np

from bench.bench_tracker import scenario, synthetic_prior
from tracker.association.batch import BatchAssociator
from tracker.association.greedy import Tracker

REGION = Path(__file__).resolve().parents[1] / "terrain_data" / "region.toml"


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
    return {"n_reports": n_reports, "n_targets": n_targets, "greedy_s": t_greedy, "chain_setup_s": t_chain,
            "sweep_s": t_sweep, "total_s": t_greedy + t_chain + t_sweep, "moved": moved, "rounds": ba.stats_["rounds"],
            "integrals": ba.stats_["integrals"], "lp_greedy": lp0, "lp_after_sweep": ch.lp,
            "n_greedy": int(np.unique(g[keep]).size), "n_after": int(ch.istate[0]), "peak_rss_gib": rss}



def calibration(n_datasets: int = 10, samples: int = 200, variant: str = "TT") -> dict:
    """Reliability of the posterior co-association probabilities on the paper's simulated data sets
    (bundled region prior, 100 reports each, S = eq. 16 with μ the expected number of targets in the
    central window): per bin [p, p+0.1), the fraction of gated pairs truly from one target."""
    from pipeline.build.region import build_region_prior
    from pipeline.config.region import load_config
    from tracker.models.sfunc import PoissonS
    from tracker.study.simulate import simulate

    prior = build_region_prior(load_config(REGION), progress=False)
    g = prior.grid
    rows, cols = np.mgrid[0 : g.height, 0 : g.width]
    x = g.transform.c + (cols + 0.5) * g.dx
    y = g.transform.f - (rows + 0.5) * g.dy

    def mass(b: tuple) -> float:
        return float(prior.density[(x >= b[0]) & (x < b[2]) & (y >= b[1]) & (y < b[3])].sum())

    probs, same = [], []
    for seed in range(n_datasets):
        sc = simulate(prior, seed)
        mu = 200.0 * mass(sc.keep) / mass(sc.region)  # expected targets in the keep window
        res = BatchAssociator(prior, variant, s_model=PoissonS(mu), mode="sample", burn_in=30, samples=samples,
                              split_merge=2, seed=seed).fit(sc.reports)
        t = sc.reports.truth
        probs.append(res.pair_prob)
        same.append(t[res.pairs[:, 0]] == t[res.pairs[:, 1]])
    p, s = np.concatenate(probs), np.concatenate(same)
    bins = np.minimum((p * 10).astype(int), 9)
    return {"pairs": int(p.size), "bins": [
        {"p": b / 10, "n": int((bins == b).sum()), "fraction_same": float(s[bins == b].mean()) if (bins == b).any() else None}
        for b in range(10)]}


if __name__ == "__main__":
    import json

    print(json.dumps(calibration() if "--calibration" in sys.argv else run(quick="--quick" in sys.argv), indent=1))
