"""The paper's experiment end to end: 28 data sets × 100 reports × UU/UT/TT × 25 τ values on the
bundled region's prior (goal: under 10 s on 2 cores), with two baselines measured in the same run
on a few data sets: the same pipeline serially (per data set), and a naive one (every τ run
integrates afresh and every score builds its own Gram matrix).

Quick: 6 data sets × 9 τ values.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

from pipeline.build.region import build_region_prior
from pipeline.config.region import load_config
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import associate, perfect_estimate
from tracker.study.experiment import (
    ExperimentConfig,
    map_local,
    parse_taus,
    run_dataset,
    run_experiment,
)
from tracker.study.metrics import score
from tracker.study.simulate import simulate

REGION = Path(__file__).resolve().parents[1] / "terrain_data" / "region.toml"


def _naive_dataset(prior_path: str, seed: int, config: ExperimentConfig) -> None:
    """Baseline: no integral cache, no shared Gram — what a direct transcription of the paper does."""
    prior = TerrainPrior.read(prior_path)
    sc = simulate(prior, seed, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
    ref = perfect_estimate(prior, sc.reports)
    for variant in config.variants:
        for tau in config.taus:
            res = associate(prior, sc.reports, "UU" if variant == "UT" else variant, tau=tau, off_prior="skip")
            est = res.estimate
            score(prior, est.means, est.covs, variant != "UU", ref.means, ref.covs, True)


def _build_prior(path: str) -> None:
    build_region_prior(load_config(REGION), progress=False).write(path)


def _timed_dataset(prior_path: str, seed: int, config: ExperimentConfig) -> tuple[int, float]:
    """run_dataset in a worker, returning (records, CPU seconds it took there)."""
    c0 = time.process_time()
    records = run_dataset(prior_path, seed, config)
    return len(records), time.process_time() - c0


def run(quick: bool = False) -> dict:
    taus = parse_taus("-3:3:0.75" if quick else "-3:3:0.25")
    config = ExperimentConfig(n_datasets=6 if quick else 28, n_reports=100, taus=taus)
    with tempfile.TemporaryDirectory() as tmp:
        prior_path = str(Path(tmp) / "prior.tif")
        # Build in a child process: building starts numba's OpenMP threads, after which this process
        # could no longer fork workers (it would fall back to the slower fork server), unlike the CLI.
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            pool.submit(_build_prior, prior_path).result()
        # Fill numba's on-disk cache outside the timings, in workers, so this process stays fork-safe.
        warm = ExperimentConfig(n_datasets=2, n_reports=20, taus=(0.0,), base_seed=10_000)
        run_experiment(prior_path, warm, workers=2, progress=False)

        t0 = time.perf_counter()
        results = run_experiment(prior_path, config, workers=2, progress=False)
        t_full = time.perf_counter() - t0
        # The same work with each data set's CPU time measured in its worker (load-independent).
        timed = list(map_local(partial(_timed_dataset, prior_path, config=config), config.seeds, 2))
        cpu_full = sum(cpu for _, cpu in timed)

        n_base = 2
        t0 = time.perf_counter()
        for seed in range(n_base):
            run_dataset(prior_path, seed, config)
        t_serial = (time.perf_counter() - t0) / n_base
        t0 = time.perf_counter()
        _naive_dataset(prior_path, 0, config)
        t_naive = time.perf_counter() - t0

    n_runs = config.n_datasets * len(config.variants) * len(taus)
    serial_total = t_serial * config.n_datasets
    naive_total = t_naive * config.n_datasets
    return {
        "n_datasets": config.n_datasets,
        "n_reports": config.n_reports,
        "n_taus": len(taus),
        "variant_runs": n_runs,
        "seconds_2_workers": t_full,
        "cpu_seconds": cpu_full,
        "cpu_seconds_over_2_cores": cpu_full / 2,
        "note": "cpu_seconds: data-set work measured in the workers (excludes pool start-up)",
        "load_average_1min": os.getloadavg()[0],
        "goal_seconds": 10.0,
        "meets_goal_wall": bool(t_full < 10.0) if not quick else None,
        "meets_goal_cpu_over_2_cores": bool(cpu_full / 2 < 10.0) if not quick else None,
        "reports_x_variant_x_tau_per_s": n_runs * config.n_reports / t_full,
        "serial_seconds_per_dataset": t_serial,
        "naive_seconds_per_dataset": t_naive,
        "speedup_vs_serial_extrapolated": serial_total / t_full,
        "speedup_vs_naive_extrapolated": naive_total / t_full,
        "cache_and_gram_speedup_per_dataset": t_naive / t_serial,
        "rows": int(len(results)),
        "table": [
            {"what": "experiment, 2 workers", "seconds": round(t_full, 2),
             "setting": f"{config.n_datasets} sets x {config.n_reports} reports x 3 variants x {len(taus)} tau"},
            {"what": "same, CPU seconds / 2 (wall time on 2 idle cores)", "seconds": round(cpu_full / 2, 2),
             "setting": f"load average {os.getloadavg()[0]:.1f} during the run"},
            {"what": "same, serial (extrapolated)", "seconds": round(serial_total, 2),
             "setting": f"from {n_base} data sets"},
            {"what": "naive: no cache, Gram per score (extrapolated)", "seconds": round(naive_total, 2),
             "setting": "from 1 data set"},
        ],
    }
