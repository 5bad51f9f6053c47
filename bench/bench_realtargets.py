"""Learn here, track there on Swellendam building centroids: one full setting, i.e. the learning pass
(features, one terrain fit per fold with held-out blocks, the priors cut around the held-out blocks)
and 28 data sets × 100 reports × UU/UT/TT × 25 τ on 2 workers (goal: under 2 minutes on 2 cores).

Quick: 6 data sets × 13 τ values. Needs ../shared/real_data/swellendam (raises FileNotFoundError without).
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from tracker.study.experiment import parse_taus
from tracker.study.heldout import HeldoutConfig, Prepared, prepare, run_heldout

ROOT = Path(__file__).resolve().parents[1]
REGION = ROOT / "terrain_data" / "swellendam.toml"
TARGETS = ROOT.parent / "shared" / "real_data" / "swellendam" / "training_data.gpkg"
GOAL_S = 120.0


def _config(quick: bool) -> HeldoutConfig:
    return HeldoutConfig(
        str(REGION), str(TARGETS), "buildings", n_datasets=6 if quick else 28, n_reports=100,
        taus=parse_taus("-9:3:1" if quick else "-9:3:0.25"), alphas=(1.0,), hybrid=False, handset=False,
        other_region=False, exact_s=False,
    )


def _learn(config: HeldoutConfig, out: str) -> tuple[Prepared, float, float]:
    """The learning pass in a child (numba's threads stay out of the parent, which then forks its workers
    like the CLI); wall and CPU seconds measured there."""
    t0, c0 = time.perf_counter(), time.process_time()
    prepared = prepare(config, out, progress=False)
    return prepared, time.perf_counter() - t0, time.process_time() - c0


def run(quick: bool = False) -> dict:
    if not TARGETS.exists():
        raise FileNotFoundError(f"{TARGETS}: the Swellendam data this benchmark runs on is missing")
    config = _config(quick)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            prepared, t_learn, cpu_learn = pool.submit(_learn, config, tmp).result()
        t_learn_wall = time.perf_counter() - t0  # includes the child's start-up and imports
        t1 = time.perf_counter()
        results = run_heldout(config, prepared, workers=2, progress=False)
        t_track = time.perf_counter() - t1
    total = t_learn_wall + t_track
    return {
        "n_datasets": config.n_datasets,
        "n_reports": config.n_reports,
        "n_taus": len(config.taus),
        "variants": ["UU", "UT", "TT"],
        "held_out_blocks": len(prepared.blocks),
        "folds_learned": len(prepared.models),
        "learning_seconds": t_learn,
        "learning_cpu_seconds": cpu_learn,
        "learning_seconds_with_start_up": t_learn_wall,
        "tracking_seconds_2_workers": t_track,
        "total_seconds": total,
        "goal_seconds": GOAL_S,
        "meets_goal": bool(total < GOAL_S) if not quick else None,
        "load_average_1min": os.getloadavg()[0],
        "note": "one setting of terrain-track heldout without the extra priors (hybrid, hand-set, r^alpha, other "
                "fold); timed on a shared machine, load average beside it",
        "rows": int(len(results)),
        "table": [
            {"part": "learning pass: features + 5 fold fits + cut priors (with the child's start-up)", "seconds": t_learn_wall},
            {"part": f"tracking: {config.n_datasets} data sets x {config.n_reports} reports x UU/UT/TT x {len(config.taus)} tau, 2 workers",
             "seconds": t_track},
            {"part": "one full setting", "seconds": total, "goal_seconds": GOAL_S,
             "meets_goal": bool(total < GOAL_S) if not quick else None},
        ],
    }
