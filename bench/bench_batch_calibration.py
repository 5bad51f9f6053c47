"""Calibration of the batch sampler's co-association probabilities (issue #14) on the bundled region's
prior, TT, S = eq. 16 under Poisson(μ) with μ the expected number of the paper's 200 targets in the
central window; 20 burn-in sweeps + 100 samples with 2 split–merge proposals per sweep, 100 reports,
data sets on 2 worker processes.

Three designs (:mod:`tracker.study.calibration`): "model" draws exactly from the model (N ~ Poisson(μ),
targets i.i.d. from r restricted to the window, the sampler's r); "paper" is the paper's simulation
associated under r restricted to the window (the experiment's batch model); "paper-grid" is the paper's
simulation associated with r over the whole grid (the mismatch). Goal: every bin [p, p+0.1) with pairs
has a fraction truly from one target (point estimate) in p + 0.05 ± 0.05; standard errors binomial and
over data sets. Reliability diagram: bench/figures/batch_reliability.png.
Full: 60 data sets for "model" and "paper", 20 for "paper-grid" (last measured in the previous session);
quick: 4 each.
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
FULL = {"model": 60, "paper": 60, "paper-grid": 20}


def run(quick: bool = False) -> dict:
    prior = build_region_prior(load_config(REGION), progress=False)
    studies = [calibration_study(prior, 4 if quick else FULL[design], design, burn_in=20, samples=100, split_merge=2,
                                 progress=True, workers=2) for design in DESIGNS]
    reliability_figure(studies, HERE / "figures" / "batch_reliability.png", "reliability, bundled region, TT")
    out: dict = {s["design"]: s for s in studies}
    out["table"] = []
    for s in studies:
        filled = [b for b in s["bins"] if b["n"]]
        out["table"].append({
            "design": s["design"], "data sets": s["n_datasets"], "pairs": s["pairs"], "mu": round(s["mu"], 1),
            "value: bins in band": s["bins_in_band"], "goal": f"{len(filled)} of {len(filled)}",
            "meets_goal": s["bins_in_band"] == len(filled),
            "middle bins: fraction - mean prob": round(s["middle_fraction_minus_prob"], 4),
            "its SE over data sets": round(s["middle_std_error_sets"], 4),
            "baseline: same data, r over the grid": "paper-grid row" if s["design"] == "paper" else "",
        })
    out["table"] += [f"{s['design']}:\n\n" + calibration_markdown(s) for s in studies]
    return out
