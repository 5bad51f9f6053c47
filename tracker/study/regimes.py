"""Where the terrain prior pays off: paper 1's experiment repeated over a grid of sensor noise
scale × number of targets, each cell summarised by the variants' scores at their own best τ.

The sensor's range and azimuth standard deviations are multiplied by a common ``scale``, so the
report ellipses keep their shape and grow linearly (metres); the number of targets is the number
drawn over the simulation region (``ExperimentConfig.n_targets``), of which those in the central
window are kept (``mean_targets_in_window``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from pipeline.prior import TerrainPrior
from tracker.study.compare import best_tau_index, prob_better
from tracker.study.experiment import VARIANTS, ExperimentConfig, run_experiment, score_matrix
from tracker.study.simulate import AirborneSensor, simulate


def scaled_sensor(sensor: AirborneSensor, scale: float) -> AirborneSensor:
    """``sensor`` with its range (m) and azimuth (rad) standard deviations multiplied by ``scale``."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be positive and finite, got {scale}")
    return replace(sensor, range_std_m=sensor.range_std_m * scale, azimuth_std_rad=sensor.azimuth_std_rad * scale)


def report_spread_m(prior: TerrainPrior, config: ExperimentConfig) -> float:
    """Median over the config's data sets and reports of the major-axis standard deviation
    √λmax(V) (metres) of the report ellipses (the cross-range error for the default sensor)."""
    sds = []
    for seed in config.seeds:
        sc = simulate(prior, seed, config.n_targets, config.n_reports, config.region_m, config.keep_fraction, config.sensor)
        sds.append(np.sqrt(np.linalg.eigvalsh(sc.reports.covs)[:, -1]))
    return float(np.median(np.concatenate(sds)))


def best_tau_summary(results: pd.DataFrame, variants: Sequence[str] = VARIANTS) -> dict[str, float]:
    """Each variant at its own best τ (lowest mean score): mean score (per m) and the τ; then the
    relative gains ``gain_TT_over_UU`` = 1 − mean TT / mean UU (and UT over UU, TT over UT; NaN when
    the denominator is 0) and the
    appendix-B probabilities ``p_TT_better_UU`` etc. (normal form, paired by data set)."""
    taus = np.sort(results["tau"].unique())
    at_best: dict[str, np.ndarray] = {}
    out: dict[str, float] = {}
    for v in variants:
        s = score_matrix(results, v)
        b = best_tau_index(s)
        at_best[v] = s[:, b]
        out[f"score_{v}"] = float(s[:, b].mean())
        out[f"best_tau_{v}"] = float(taus[b])
    for a, b in (("TT", "UU"), ("UT", "UU"), ("TT", "UT")):
        if a in at_best and b in at_best:
            # undefined when b scored a perfect association (0): nothing left to gain
            den = out[f"score_{b}"]
            out[f"gain_{a}_over_{b}"] = 1.0 - out[f"score_{a}"] / den if den > 0 else float("nan")
            out[f"p_{a}_better_{b}"] = prob_better(at_best[a] - at_best[b])
    return out


def regime_grid(
    prior_path: str | os.PathLike,
    noise_scales: Sequence[float],
    target_counts: Sequence[int],
    base: ExperimentConfig,
    workers: int | None = 1,
    progress: bool = True,
) -> pd.DataFrame:
    """One row per (noise scale, target count): ``base`` with the sensor scaled and ``n_targets``
    set, run on the same seeds, summarised by :func:`best_tau_summary`, plus ``spread_m`` (median
    report major-axis σ, metres), ``mean_targets_in_window`` and ``mean_nd`` (detected targets)."""
    if not noise_scales or not target_counts:
        raise ValueError("noise_scales and target_counts must not be empty")
    prior = TerrainPrior.read(prior_path)
    rows = []
    cells = [(s, n) for s in noise_scales for n in target_counts]
    for scale, n_targets in tqdm(cells, desc="regime cells", unit="cell", disable=not progress):
        config = replace(base, sensor=scaled_sensor(base.sensor, scale), n_targets=int(n_targets))
        results = run_experiment(prior_path, config, workers=workers, progress=False)
        per_seed = results.groupby("seed")
        rows.append({
            "noise_scale": float(scale),
            "n_targets": int(n_targets),
            "spread_m": report_spread_m(prior, config),
            "mean_targets_in_window": float(per_seed["n_targets"].first().mean()),
            "mean_nd": float(per_seed["nd"].first().mean()),
            **best_tau_summary(results, config.variants),
        })
    return pd.DataFrame(rows)
