"""Batch against greedy on the paper's experiment design (28 data sets × 100 reports, 200 targets over
the central 14 km, the central 7 km kept; UU, UT, TT; τ from −3 to 3 by 0.5 and the exact S of eq. 16)
on the bundled region's prior and on Swellendam's (real data; skipped with the reason when absent,
an error when CI=true).

The exact S is eq. 16 under N_T ~ Poisson(μ) with μ the expected number of the 200 targets that fall
in the central window: μ = 200 × mass(window) / mass(14 km region) of the prior
(:func:`tracker.study.calibration.expected_in_window`).

Figures and summary.json per prior in bench/figures/batch_experiment_<name>/. Quick: 6 data sets and
τ from −3 to 3 by 1.5, bundled region only.
"""

from __future__ import annotations

import multiprocessing
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from pipeline.build.region import build_region_prior
from pipeline.config.region import load_config
from pipeline.prior.terrain import TerrainPrior
from tracker.study.calibration import expected_in_window
from tracker.study.experiment import (
    ExperimentConfig,
    parse_taus,
    run_experiment,
    summarise,
    write_outputs,
)

HERE = Path(__file__).resolve().parent
CONFIGS = {"region": HERE.parent / "terrain_data" / "region.toml",
           "swellendam": HERE.parent / "terrain_data" / "swellendam.toml"}
REAL_DATA = HERE.parent.parent / "shared" / "real_data" / "swellendam"


def _build_prior(config: str, path: str) -> None:
    build_region_prior(load_config(Path(config)), progress=False).write(path)


def _row(name: str, summary: dict) -> list[dict]:
    rows = []
    for v, d in summary["batch_vs_greedy"].items():
        rows.append({
            "prior": name, "variant": v,
            "score x1e4.5 batch/greedy (best tau)": "/".join(f"{x:.2f}" for x in d["mean_score_x10^4.5"]),
            "P(batch better score)": round(d["prob_better_score_best_tau"], 3),
            "|ND^-ND| batch/greedy (best tau)": "/".join(f"{x:.2f}" for x in d["mean_nd_abs_error_best"]),
            "P(batch better |ND^-ND|)": round(d["prob_better_nd_error_best_tau"], 3),
            "score exact S batch/greedy": "/".join(f"{x:.2f}" for x in d.get("mean_score_exact_s_x10^4.5", [])),
            "P(batch better score, exact S)": round(d.get("prob_better_score_exact_s", float("nan")), 3),
            "|ND^-ND| exact S batch/greedy": "/".join(f"{x:.2f}" for x in d.get("mean_nd_abs_error_exact_s", [])),
            "P(batch better |ND^-ND|, exact S)": round(d.get("prob_better_nd_error_exact_s", float("nan")), 3),
            "min ln p gain": round(min(d["min_log_posterior_gain"], d.get("min_log_posterior_gain_exact_s", 0.0)), 6),
            "UU->TT gap closed": round(d["share_of_uu_tt_gap_closed"], 3) if "share_of_uu_tt_gap_closed" in d else "",
        })
    return rows


def run(quick: bool = False) -> dict:
    names = ["region"] if quick else ["region", "swellendam"]
    out: dict = {"table": []}
    for name in names:
        if name == "swellendam" and not REAL_DATA.is_dir():
            if os.environ.get("CI") == "true":
                raise FileNotFoundError(f"{REAL_DATA} missing (CI=true: the Swellendam run must happen)")
            out["table"].append(f"swellendam skipped: {REAL_DATA} not found")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            path = str(Path(tmp) / "prior.tif")
            # built in a spawned child: numba's threads in this process would make forking workers unsafe
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
                pool.submit(_build_prior, str(CONFIGS[name]), path).result()
            mu = expected_in_window(TerrainPrior.read(path), 200)
            config = ExperimentConfig(n_datasets=6 if quick else 28, n_reports=100,
                                      taus=parse_taus("-3:3:1.5" if quick else "-3:3:0.5"), poisson_mu=mu,
                                      methods=("greedy", "batch"))
            results = run_experiment(path, config, workers=2, progress=False)
        summary = summarise(results, config)
        write_outputs(results, summary, HERE / "figures" / f"batch_experiment_{name}", title=f"{name}, greedy and batch")
        out[name] = {"mu": mu, "n_datasets": config.n_datasets, "batch_vs_greedy": summary["batch_vs_greedy"],
                     "table_normal": summary["table_normal"]}
        out["table"].extend(_row(name, summary))
    return out
