"""The paper's experiment end to end: 28 data sets × 100 reports × UU/UT/TT × 25 τ values on the
bundled region's prior (goal: under 10 s on 2 cores), with two baselines measured in the same run
on a few data sets: the same pipeline serially (per data set), and a naive one (every τ run
integrates afresh and every score builds its own Gram matrix).

Quick: 6 data sets × 9 τ values.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from pipeline.build import build_region_prior
from pipeline.config import load_config
from pipeline.prior import TerrainPrior
from tracker.association import associate, perfect_estimate
from tracker.experiment import ExperimentConfig, parse_taus, run_dataset, run_experiment
from tracker.metrics import score
from tracker.simulate import simulate

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


def run(quick: bool = False) -> dict:
    taus = parse_taus("-3:3:0.75" if quick else "-3:3:0.25")
    config = ExperimentConfig(n_datasets=6 if quick else 28, n_reports=100, taus=taus)
    with tempfile.TemporaryDirectory() as tmp:
        prior_path = str(Path(tmp) / "prior.tif")
        build_region_prior(load_config(REGION), progress=False).write(prior_path)
        # Fill numba's on-disk cache outside the timings, in workers, so this process stays fork-safe.
        warm = ExperimentConfig(n_datasets=2, n_reports=20, taus=(0.0,), base_seed=10_000)
        run_experiment(prior_path, warm, workers=2, progress=False)

        t0 = time.perf_counter()
        results = run_experiment(prior_path, config, workers=2, progress=False)
        t_full = time.perf_counter() - t0

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
        "goal_seconds": 10.0,
        "meets_goal": bool(t_full < 10.0) if not quick else None,
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
            {"what": "same, serial (extrapolated)", "seconds": round(serial_total, 2),
             "setting": f"from {n_base} data sets"},
            {"what": "naive: no cache, Gram per score (extrapolated)", "seconds": round(naive_total, 2),
             "setting": "from 1 data set"},
        ],
    }
