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

Full: 500 data sets for "model" and "paper", 60 for "paper-grid", seeds from 10,000 (the exploratory
run of session 5 used seeds 0–59; the counts were fixed before any bin was seen). Convergence check,
fixed in advance: for each of "model" and "paper" with a bin out of band, its first 40 data sets are
rerun with 4× the burn-in and samples, beside the same 40 at 1×. Speed: the sampler on 12 data sets
with and without the ln L cache, same run (CPU s, one process). Quick: 4 data sets each.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.build.region import build_region_prior
from pipeline.config.region import load_config
from tracker.association.batch import BatchAssociator
from tracker.models.sfunc import PoissonS
from tracker.study.calibration import (
    DESIGNS,
    calibration_markdown,
    calibration_study,
    reliability_figure,
    simulate_model,
)
from tracker.study.experiment import expected_in_window, window_prior
from tracker.study.simulate import central_windows, simulate

HERE = Path(__file__).resolve().parent
REGION = HERE.parent / "terrain_data" / "region.toml"
FULL = {"model": 500, "paper": 500, "paper-grid": 60}
SEED = 10_000
CHECK_SETS = 40
SWEEPS = {"burn_in": 20, "samples": 100, "split_merge": 2}


def _speed(prior, n_sets: int) -> dict:
    """CPU seconds of the sampler (calibration settings) on the same data sets, without and with the
    ln L cache, and whether the samples agree exactly."""
    _, keep = central_windows(prior, 14000.0, 0.5)
    mu = expected_in_window(prior, 200)
    mp = window_prior(prior, keep)
    half = n_sets // 2
    reps = [simulate_model(mp, mu, 100, SEED + s).reports for s in range(half)]
    reps += [simulate(prior, SEED + s, 200, 100).reports for s in range(n_sets - half)]

    def run(cache: bool) -> tuple[float, list, int]:
        t = time.process_time()
        out = [BatchAssociator(mp, "TT", s_model=PoissonS(mu), mode="sample", seed=i, cache=cache, **SWEEPS).fit(r)
               for i, r in enumerate(reps)]
        return time.process_time() - t, [r.pair_prob for r in out], sum(r.stats["integrals"] for r in out)

    run(True)  # compile and warm
    t0, p0, i0 = run(False)
    t1, p1, i1 = run(True)
    return {"data sets": n_sets, "uncached CPU s": round(t0, 2), "cached CPU s": round(t1, 2), "speed-up": round(t0 / t1, 2),
            "integrals uncached": i0, "integrals cached": i1,
            "identical samples": all(np.array_equal(a, b) for a, b in zip(p0, p1, strict=True))}


def _row(s: dict, label: str = "") -> dict:
    filled = [b for b in s["bins"] if b["n"]]
    return {
        "design": s["design"] + label, "data sets": s["n_datasets"], "sweeps": f"{s['burn_in']}+{s['samples']}",
        "pairs": s["pairs"], "mu": round(s["mu"], 1),
        "value: bins in band": s["bins_in_band"], "goal": f"{len(filled)} of {len(filled)}",
        "meets_goal": s["bins_in_band"] == len(filled),
        "middle bins: fraction - mean prob": round(s["middle_fraction_minus_prob"], 4),
        "its SE over data sets": round(s["middle_std_error_sets"], 4),
        "max SE over data sets, bins 0.1-0.8": round(max((b["std_error_sets"] for b in s["bins"][1:9] if b["std_error_sets"] is not None), default=float("nan")), 4),
        "baseline: same data, r over the grid": "paper-grid row" if s["design"] == "paper" else "",
    }


def run(quick: bool = False) -> dict:
    prior = build_region_prior(load_config(REGION), progress=False)
    t0 = time.perf_counter()
    speed = _speed(prior, 2 if quick else 12)
    studies = [calibration_study(prior, 4 if quick else FULL[design], design, seed=SEED, progress=True, workers=2, **SWEEPS)
               for design in DESIGNS]
    reliability_figure(studies, HERE / "figures" / "batch_reliability.png", "reliability, bundled region, TT")
    out: dict = {s["design"]: s for s in studies}
    out["speed"] = speed
    out["table"] = [_row(s) for s in studies]
    n_check = 2 if quick else CHECK_SETS
    for s in studies[:2]:
        if s["bins_in_band"] == s["bins_with_pairs"]:
            continue
        pair = [calibration_study(prior, n_check, s["design"], seed=SEED, workers=2, progress=True,
                                  burn_in=f * SWEEPS["burn_in"], samples=f * SWEEPS["samples"], split_merge=SWEEPS["split_merge"])
                for f in (1, 4)]
        out[f"{s['design']} convergence"] = pair
        out["table"] += [_row(pair[0], f", first {n_check}, 1x"), _row(pair[1], f", first {n_check}, 4x")]
        out["table"].append(f"{s['design']}, first {n_check} data sets, 4x sweeps:\n\n" + calibration_markdown(pair[1]))
    out["table"].append({"speed: sampler on the same data sets, one process": "", **speed})
    out["table"] += [f"{s['design']}:\n\n" + calibration_markdown(s) for s in studies]
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out
