"""Batch association at scale: greedy plus one full Gibbs sweep on the tracker bench's scene
(full: 100,000 static targets / 1,000,000 reports on 100 km x 100 km; quick: 10,000 / 100,000).
Goal: greedy + chain set-up + one sweep <= 30 s on 2 cores, peak memory <= 4 GiB.

Each stage is timed in wall and CPU seconds (process time, both threads). Baseline in the same run: a
second sweep from the same state and random stream whose rounds gate against ALL live clusters with
the project's gater (``gater=gate_unchecked``, the path the cluster index replaces); it must walk
the same chain. A third sweep, from the same state again, runs under cProfile for the per-phase
breakdown of a sweep (its own time is not the measured one)."""

from __future__ import annotations

import cProfile
import os
import pstats
import time

import numpy as np

from bench.bench_tracker import scenario, synthetic_prior
from bench.timing import peak_gib, reset_peak
from tracker.association.batch import BatchAssociator
from tracker.association.greedy import Tracker
from tracker.gating.gate import gate_unchecked

GOAL_TOTAL_S = 30.0
GOAL_PEAK_GIB = 4.0

# cProfile entries whose cumulative time makes up each phase of a sweep's rounds
_PHASES = {
    "gate (index, exact test)": ("cluster_index.py", "gated"),
    "own cluster without the report": ("batch_kernels.py", "own_without"),
    "round dependencies": ("batch_kernels.py", "earlier_dependency"),
    "selection and options": [("batch_kernels.py", "select_round"), ("batch_kernels.py", "round_options")],
    "integrals (ln L of the options)": ("batch.py", "cluster_log_lik"),
    "apply moves": ("batch_kernels.py", "apply_moves"),
    "index update": [("batch.py", "_gaussians"), ("cluster_index.py", "update"), ("cluster_index.py", "remove")],
}


class _Clock:
    """Wall and CPU (process) seconds since construction."""

    def __init__(self) -> None:
        self.w, self.c = time.perf_counter(), time.process_time()

    def read(self) -> tuple[float, float]:
        return time.perf_counter() - self.w, time.process_time() - self.c


def _phases(prof: cProfile.Profile, total: float) -> dict[str, float]:
    """Shares of the profiled sweep's time per phase; the rest is the rounds' numpy bookkeeping."""
    st = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    out = {}
    for phase, keys in _PHASES.items():
        keys = keys if isinstance(keys, list) else [keys]
        out[phase] = sum(v[3] for (f, _, name), v in st.items() if any(f.endswith(k[0]) and name == k[1] for k in keys))
    out["numpy bookkeeping (rest)"] = total - sum(out.values())
    return {k: v / total for k, v in out.items()}


def run(quick: bool = False) -> dict:
    reset_peak()  # bench.run's process may have run larger benches before this one
    size_m, n_targets, n_reports = (32_000.0, 10_000, 100_000) if quick else (100_000.0, 100_000, 1_000_000)
    prior = synthetic_prior(size_m)
    reports = scenario(prior, n_targets, n_reports)
    warm = reports.subset(slice(0, 3000))
    for gater in (None, gate_unchecked):  # compile the kernels of both paths
        ba = BatchAssociator(prior, "TT", tau=-1.7, gater=gater)
        ba.chain(warm, Tracker(prior, "TT", tau=-1.7, off_prior="skip").update(warm)).sweep(1.0, np.random.default_rng(0))
    ba = BatchAssociator(prior, "TT", tau=-1.7)
    clock = _Clock()
    tr = Tracker(prior, "TT", tau=-1.7, off_prior="skip")
    g = np.concatenate([tr.update(reports.subset(slice(s, s + 50_000))) for s in range(0, n_reports, 50_000)])
    greedy_s, greedy_cpu = clock.read()
    keep = np.flatnonzero(g >= 0)  # the chain takes the reports on the prior
    rep = reports.subset(keep)
    clock = _Clock()
    ch = ba.chain(rep, g[keep])
    setup_s, setup_cpu = clock.read()
    lp0 = ch.lp
    setup_integrals = ba.stats_["integrals"]
    clock = _Clock()
    moved = ch.sweep(1.0, np.random.default_rng(1))
    sweep_s, sweep_cpu = clock.read()
    rss = peak_gib()
    rounds, integrals = ba.stats_["rounds"], ba.stats_["integrals"] - setup_integrals
    total_s, total_cpu = greedy_s + setup_s + sweep_s, greedy_cpu + setup_cpu + sweep_cpu
    base = BatchAssociator(prior, "TT", tau=-1.7, gater=gate_unchecked).chain(rep, g[keep])
    clock = _Clock()
    base.sweep(1.0, np.random.default_rng(1))
    base_s, base_cpu = clock.read()
    same = bool(np.array_equal(base.labels, ch.labels) and base.lp == ch.lp)
    del base
    prof_chain = ba.chain(rep, g[keep])
    prof = cProfile.Profile()
    clock = _Clock()
    prof.enable()
    prof_chain.sweep(1.0, np.random.default_rng(1))
    prof.disable()
    shares = _phases(prof, clock.read()[0])
    meets = bool(total_s <= GOAL_TOTAL_S and rss <= GOAL_PEAK_GIB)
    load = os.getloadavg()[0]
    return {"n_reports": n_reports, "n_targets": n_targets, "greedy_s": greedy_s, "greedy_cpu_s": greedy_cpu,
            "chain_setup_s": setup_s, "chain_setup_cpu_s": setup_cpu, "sweep_s": sweep_s, "sweep_cpu_s": sweep_cpu,
            "total_s": total_s, "total_cpu_s": total_cpu, "moved": moved, "rounds": rounds, "integrals": integrals,
            "setup_integrals": setup_integrals, "lp_greedy": lp0, "lp_after_sweep": ch.lp, "n_greedy": int(np.unique(g[keep]).size),
            "n_after": int(ch.istate[0]), "peak_rss_gib": rss,
            "sweep_gating_all_clusters_s": base_s, "sweep_gating_all_clusters_cpu_s": base_cpu,
            "sweep_speedup_vs_all_clusters": base_s / sweep_s, "sweep_cpu_ratio_vs_all_clusters": base_cpu / sweep_cpu,
            "same_chain_as_all_clusters": same, "sweep_phase_shares": shares, "load_average_1min": load,
            "goal_total_s": GOAL_TOTAL_S, "goal_peak_gib": GOAL_PEAK_GIB, "meets_goal": meets if not quick else None,
            "table": [
                {"stage": "greedy TT", "wall s": round(greedy_s, 2), "CPU s": round(greedy_cpu, 2)},
                {"stage": "chain set-up", "wall s": round(setup_s, 2), "CPU s": round(setup_cpu, 2),
                 "integrals": setup_integrals},
                {"stage": "one Gibbs sweep", "wall s": round(sweep_s, 2), "CPU s": round(sweep_cpu, 2),
                 "rounds": rounds, "integrals": integrals, "moved": moved},
                {"stage": "total (goal <= 30 s)", "wall s": round(total_s, 2), "CPU s": round(total_cpu, 2),
                 "goal": GOAL_TOTAL_S, "meets_goal": None if quick else total_s <= GOAL_TOTAL_S},
                {"stage": "peak RSS (GiB, goal <= 4)", "GiB": round(rss, 2), "goal": GOAL_PEAK_GIB,
                 "meets_goal": None if quick else rss <= GOAL_PEAK_GIB},
                {"stage": "baseline sweep: gater on all live clusters", "wall s": round(base_s, 2),
                 "CPU s": round(base_cpu, 2), "same chain": same},
            ] + [f"sweep phase {k}: {100 * v:.0f} % (cProfile, third sweep)" for k, v in shares.items()] + [
                f"{n_reports:,} reports / {n_targets:,} targets: greedy + set-up + sweep {total_s:.1f} s wall "
                f"({'quick scene: no goal' if quick else ('meets' if meets else 'misses') + ' the 30 s / 4 GiB goal'}), peak {rss:.2f} GiB, "
                f"sweep x{base_s / sweep_s:.2f} over gating all live clusters in the same run, load {load:.1f}",
            ]}
