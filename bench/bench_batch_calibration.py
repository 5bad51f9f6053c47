"""Calibration of the batch sampler's co-association probabilities (issue #14) on the bundled region's
prior, TT, S = eq. 16 under Poisson(μ) with μ the expected number of the paper's 200 targets in the
central window; 30 burn-in sweeps + 150 samples with 2 split–merge proposals per sweep, 100 reports.

Two designs (:mod:`tracker.study.calibration`): "model" draws exactly from the model (N ~ Poisson(μ),
targets i.i.d. from r restricted to the window, the sampler's r); "paper" is the paper's simulation
associated with r over the whole grid. Goal: every bin [p, p+0.1) with pairs has a fraction truly from
one target in p + 0.05 ± 0.05. Reliability diagram: bench/figures/batch_reliability.png.
Full: 60 data sets per design; quick: 6.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.build.region import build_region_prior
from pipeline.config.region import load_config
from tracker.study.calibration import (
    DESIGNS,
    calibration_markdown,
    calibration_study,
    reliability_figure,
)

HERE = Path(__file__).resolve().parent
REGION = HERE.parent / "terrain_data" / "region.toml"


def run(quick: bool = False) -> dict:
    prior = build_region_prior(load_config(REGION), progress=False)
    n = 6 if quick else 60
    studies = [calibration_study(prior, n, design, burn_in=30, samples=150, split_merge=2) for design in DESIGNS]
    reliability_figure(studies, HERE / "figures" / "batch_reliability.png", "reliability, bundled region, TT")
    out: dict = {s["design"]: s for s in studies}
    out["table"] = [f"{s['design']} ({s['n_datasets']} data sets, {s['pairs']} pairs, mu = {s['mu']:.1f}): "
                    f"{s['bins_in_band']} of {s['bins_with_pairs']} bins in band" for s in studies]
    out["table"] += [calibration_markdown(s) for s in studies]
    return out
