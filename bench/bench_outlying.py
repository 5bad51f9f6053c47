"""Swellendam's outlying fold: what a model fitted on the towns can know about the countryside.

Run: ``PYTHONPATH=$PWD .venv/bin/python -m bench.run outlying`` (~5 min; needs ../shared/real_data/swellendam;
``--quick``: the outlying fold alone, without the in-sample fit).

bench_maxent's folds (5 folds of 2 km blocks, :func:`pipeline.learn.evaluate.block_cv`'s) are four folds of one
town block each and a fifth fold of the 18 other blocks (villages and farms, 429 buildings). The fifth fold's
training points lie in four town blocks, its observation window. Per outer fold this bench fits the config's
8-feature model in its window with ε and τ cross-fitted (as bench_maxent's row "terrain (forms, tracks, track
ends, towns)"), then scores its held-out points under every (τ, ε) of a grid: p ∝ (1 − ε)·r^τ/Σr^τ + ε·u with
the fitted tables r (:func:`pipeline.build.region.calibrate`, what ``build --model`` applies). The best
point of the grid is an **oracle**, chosen on the held-out points, not a method: it says how far calibration
alone could move a fold, and whether the cross-fit could have found it. The row "in-sample" is the same
model fitted on all points and scored on each fold's own points: what a fit that has seen the fold reaches
there. Gains are nats per point over the uniform density on the grid, as in bench_maxent.
"""

from __future__ import annotations

import warnings

import numpy as np

from bench.bench_maxent import (
    BLOCK_M,
    DATA,
    FOLDS,
    fitted_forms,
    in_sample,
    log_grid_area,
    swellendam,
)

TAUS = tuple(float(round(t, 1)) for t in np.arange(0.3, 1.21, 0.1))
EPSILONS = (0.0, 0.01, 0.1)


def held_out_gain(r: np.ndarray, grid, pts: np.ndarray, tau: float, eps: float) -> float:
    """Mean log density (nats per point, over the uniform density on ``grid``) at ``pts`` (N, 2, metres)
    of the fitted tables ``r`` (H, W, unnormalised) tempered by ``tau`` and mixed with ε of the uniform
    density over their support: the density ``build --model`` writes."""
    from pipeline.build.region import calibrate
    from pipeline.prior import TerrainPrior

    prior = TerrainPrior.from_array(calibrate(np.array(r, dtype=np.float64), tau, eps), grid)
    with np.errstate(divide="ignore"):
        ld = np.log(prior.density_at(pts[:, 0], pts[:, 1]))
    return float(ld.mean() + log_grid_area(grid))


def run(quick: bool = False) -> dict:
    from pipeline.learn import BlockWindow
    from pipeline.learn.estimator import PriorEstimator
    from pipeline.learn.evaluate import block_cv

    if not DATA.exists():
        return {"skipped": f"{DATA} missing", "table": [f"outlying: skipped ({DATA} missing)"]}
    cfg, learn, stack, pts = swellendam()
    grid = stack.grid
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cv = block_cv(pts, PriorEstimator(features=stack, template=cfg.model), FOLDS, BLOCK_M, None,
                      ("uniform", "terrain"), progress=False)
    index, blocks = cv.extra["test_index"], cv.extra["test_blocks"]
    everything = np.concatenate(index)
    folds = []
    # quick: only the fold with the most blocks, the outlying one, and no in-sample fit
    chosen_folds = [int(np.argmax([len(b) for b in blocks]))] if quick else range(len(index))
    for j in chosen_folds:
        test = index[j]
        train = np.setdiff1d(everything, test)
        est = fitted_forms(cfg, learn, stack, learn.features, window=BlockWindow(BLOCK_M, frozenset(blocks[j].tolist())))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(pts[train])
        r = est.model_.evaluate(stack)
        at_cv = held_out_gain(r, grid, pts[test], est.temper_, est.defensive_)
        own = float(est.score_samples(pts[test]).mean() + log_grid_area(grid))
        assert abs(at_cv - own) < 1e-9, (at_cv, own)  # the sweep scores the estimator's own density
        sweep = {(t, e): held_out_gain(r, grid, pts[test], t, e) for t in TAUS for e in EPSILONS}
        best = max(sweep, key=sweep.get)
        folds.append({"fold": j + 1, "held-out blocks": len(blocks[j]),
                      "training blocks": int(len(np.unique(np.concatenate(blocks))) - len(blocks[j])),
                      "points": len(test), "cross-fitted tau": round(est.temper_, 3),
                      "cross-fitted eps": float(f"{est.defensive_:.3g}"), "held-out gain": round(at_cv, 3),
                      "oracle tau": best[0], "oracle eps": best[1], "oracle gain": round(sweep[best], 3),
                      "sweep": {f"tau {t}, eps {e}": round(v, 3) for (t, e), v in sweep.items()}})
        print(folds[-1]["fold"], {k: v for k, v in folds[-1].items() if k != "sweep"}, flush=True)
    if not quick:
        for f, g in zip(folds, in_sample(cfg, learn, stack, pts, index), strict=True):
            f["in-sample gain"] = round(float(g), 3)
    table = [{k: v for k, v in f.items() if k != "sweep"} for f in folds]
    out = folds[int(np.argmax([f["held-out blocks"] for f in folds]))]
    verdict = (f"fold {out['fold']} ({out['held-out blocks']} blocks held out, {out['training blocks']} town blocks "
               f"to learn from): held-out {out['held-out gain']:+.3f} with the cross-fitted tau {out['cross-fitted tau']}, "
               f"eps {out['cross-fitted eps']}; the oracle tau {out['oracle tau']}, eps {out['oracle eps']} "
               f"(chosen on the held-out points) {out['oracle gain']:+.3f}"
               + (f"; fitted on all points and scored in-sample {out['in-sample gain']:+.3f}" if not quick else ""))
    n = np.array([f["points"] for f in folds], dtype=float)
    # one (τ, ε) for every fold: read off the held-out folds, so a reference, never a result
    fixed = {k: {"per_fold": [f["sweep"][k] for f in folds],
                 "pooled": round(float(n @ [f["sweep"][k] for f in folds] / n.sum()), 3)} for k in folds[0]["sweep"]}
    return {"folds": folds, "taus": list(TAUS), "epsilons": list(EPSILONS), "fixed_for_every_fold": fixed,
            "verdict": verdict, "table": [*table, verdict]}


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1, default=float))
