"""Calibration of the batch sampler's posterior co-association probabilities (issue #14).

Pairs of gated reports whose posterior P(i and j from one target) falls in [p, p + 0.1) should be
truly from one target a fraction p + 0.05 of the time. That holds when the data come from the model
the sampler assumes, so three designs are simulated, all with S = eq. 16 under Poisson(μ), μ the
paper's expected number of targets in the central window (``n_targets`` × the window's share of the
sampling region's prior mass):

* ``"model"``: exactly paper 1's model. N ~ Poisson(μ) targets i.i.d. from r, each report of a target
  picked uniformly, noise N(0, V) with V from the airborne sensor; r is the prior restricted to the
  paper's central window (whole cells, :func:`~tracker.study.experiment.window_prior`).
* ``"paper"``: the paper's experiment (:func:`tracker.study.simulate.simulate`: ``n_targets`` from r
  over the region, keep the window), associated under that design's model: r restricted to the
  window, as the experiment's batch does. Only the count prior differs from the truth (Poisson(μ)
  against the design's Binomial(n_targets, share)).
* ``"paper-grid"``: the paper's experiment associated with r over the whole grid. The model then puts
  targets where there are none: every cluster's ∫G r is too small by the window's share of the
  mass, a per-cluster factor that favours fewer clusters, i.e. overconfident co-association.

``calibration_study`` runs the sampler on many data sets and returns the reliability table;
``reliability_figure`` draws the reliability diagram (matplotlib).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from pipeline.prior import TerrainPrior
from tracker.association.batch import BatchAssociator
from tracker.models.sfunc import PoissonS
from tracker.study.experiment import expected_in_window, map_local, window_prior
from tracker.study.simulate import AirborneSensor, Scenario, central_windows, simulate
from tracker.types.reports import Reports

DESIGNS = ("model", "paper", "paper-grid")
N_BINS = 10


def simulate_model(prior: TerrainPrior, mu: float, n_reports: int, seed: int,
                   sensor: AirborneSensor | None = None) -> Scenario:
    """One data set drawn exactly from the model: N ~ Poisson(μ) (at least 1) targets i.i.d. from
    ``prior``'s r, ``n_reports`` reports of uniformly picked targets, V from ``sensor`` flying past
    the grid's centre."""
    sensor = sensor or AirborneSensor()
    rng = np.random.default_rng(seed)
    n = 0
    while n == 0:  # a data set with reports needs a target: condition on N >= 1
        n = int(rng.poisson(mu))
    targets = prior.sample(n, rng)
    truth = rng.integers(0, n, size=n_reports)
    times = np.arange(n_reports) * sensor.report_interval_s
    b = prior.grid.bounds
    centre = np.array([0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3])])
    platform = sensor.platform_track(times, centre, rng.uniform(0.0, 2 * np.pi))
    covs = sensor.covariances(platform, targets[truth])
    means = targets[truth] + np.einsum("kij,kj->ki", np.linalg.cholesky(covs), rng.standard_normal((n_reports, 2)))
    return Scenario(targets, Reports.create(means, covs, times, truth), platform, b, b, int(seed))


def reliability(prob: np.ndarray, same: np.ndarray, n_bins: int = N_BINS, groups: np.ndarray | None = None) -> list[dict]:
    """Per bin [p, p + 1/n_bins) of posterior co-association ``prob``: the number of pairs ``n``, the
    fraction truly from one target ``fraction_same`` (None when empty), its binomial standard error,
    with ``groups`` (the data set of each pair) also ``std_error_sets``, the standard error of that
    ratio over data sets (pairs of one data set are correlated), and whether the point estimate lies in
    the goal band p + w/2 ± w/2 (w the bin width)."""
    prob, same = np.asarray(prob, float), np.asarray(same, bool)
    w = 1.0 / n_bins
    bins = np.minimum((prob * n_bins).astype(np.int64), n_bins - 1)
    rows = []
    for k in range(n_bins):
        sel = bins == k
        s = same[sel]
        frac = float(s.mean()) if s.size else None
        row = {
            "p": k * w, "n": int(s.size), "fraction_same": frac,
            "mean_prob": float(prob[sel].mean()) if s.size else None,
            "std_error": float(np.sqrt(frac * (1 - frac) / s.size)) if s.size else None,
            "in_band": bool(frac is not None and k * w - 1e-12 <= frac <= (k + 1) * w + 1e-12),
        }
        if groups is not None:
            row["std_error_sets"] = _ratio_std_error(s, np.asarray(groups)[sel]) if s.size else None
        rows.append(row)
    return rows


def _ratio_std_error(same: np.ndarray, groups: np.ndarray) -> float | None:
    """Standard error of Σ same / Σ n over data sets (delta method for a ratio of per-set totals)."""
    _, g = np.unique(groups, return_inverse=True)
    n, t = np.bincount(g), np.bincount(g, weights=same)
    d = n.size
    if d < 2:
        return None
    frac = t.sum() / n.sum()
    return float(np.sqrt(d / (d - 1) * ((t - frac * n) ** 2).sum()) / n.sum())


def _one_dataset(s: int, prior: TerrainPrior, model_prior: TerrainPrior, design: str, mu: float, variant: str,
                 n_targets: int, n_reports: int, burn_in: int, samples: int, split_merge: int) -> tuple[np.ndarray, np.ndarray]:
    """Posterior co-association of data set ``s``'s gated pairs, and whether each pair is truly one target."""
    if design == "model":
        rep = simulate_model(model_prior, mu, n_reports, s).reports
    else:
        rep = simulate(prior, s, n_targets, n_reports).reports
    res = BatchAssociator(model_prior, variant, s_model=PoissonS(mu), mode="sample", burn_in=burn_in, samples=samples,
                          split_merge=split_merge, seed=s).fit(rep)
    return res.pair_prob, rep.truth[res.pairs[:, 0]] == rep.truth[res.pairs[:, 1]]


def calibration_study(prior: TerrainPrior, n_datasets: int = 100, design: str = "model", variant: str = "TT",
                      n_targets: int = 200, n_reports: int = 100, burn_in: int = 30, samples: int = 150,
                      split_merge: int = 2, seed: int = 0, progress: bool = False, workers: int | None = 1) -> dict:
    """Sample ``n_datasets`` simulated data sets of ``design`` (:data:`DESIGNS`) with S = eq. 16 under
    Poisson(μ), μ = :func:`~tracker.study.experiment.expected_in_window`, on ``workers`` processes
    (None: all cores); returns the reliability table (``bins``), the number of gated pairs, μ, the
    mean posterior minus the fraction truly from one target over the middle bins 0.1–0.8, and the settings."""
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {DESIGNS}, got {design!r}")
    _, keep = central_windows(prior, 14000.0, 0.5)
    mu = expected_in_window(prior, n_targets)
    model_prior = prior if design == "paper-grid" else window_prior(prior, keep)
    fn = partial(_one_dataset, prior=prior, model_prior=model_prior, design=design, mu=mu, variant=variant,
                 n_targets=n_targets, n_reports=n_reports, burn_in=burn_in, samples=samples, split_merge=split_merge)
    seeds = list(range(seed, seed + n_datasets))
    probs, same = zip(*tqdm(map_local(fn, seeds, workers), total=n_datasets, desc=f"calibration ({design})",
                            unit="set", disable=not progress), strict=True)
    groups = np.concatenate([np.full(len(p), s) for p, s in zip(probs, seeds, strict=True)])
    p, t = np.concatenate(probs), np.concatenate(same)
    table = reliability(p, t, groups=groups)
    middle = (p >= 0.1) & (p < 0.9)
    return {"design": design, "variant": variant, "n_datasets": n_datasets, "mu": mu, "pairs": int(p.size),
            "burn_in": burn_in, "samples": samples, "split_merge": split_merge, "bins": table,
            "bins_in_band": int(sum(r["in_band"] for r in table if r["n"])),
            "bins_with_pairs": int(sum(1 for r in table if r["n"])),
            "middle_pairs": int(middle.sum()),
            "middle_fraction_minus_prob": float(t[middle].mean() - p[middle].mean()) if middle.any() else None,
            "middle_std_error_sets": _ratio_std_error(t[middle] - p[middle], groups[middle]) if middle.any() else None}


def calibration_markdown(study: dict) -> str:
    """The reliability table as Markdown (bins as columns)."""
    rows = study["bins"]
    head = "| bin | " + " | ".join(f"{r['p']:.1f}" for r in rows) + " |"
    fmt = [f"{r['fraction_same']:.3f}" if r["fraction_same"] is not None else "–" for r in rows]
    return "\n".join([head, "|---" * (len(rows) + 1) + "|",
                      "| pairs | " + " | ".join(str(r["n"]) for r in rows) + " |",
                      "| same target | " + " | ".join(fmt) + " |",
                      "| mean posterior | " + " | ".join(_fmt(r["mean_prob"]) for r in rows) + " |",
                      "| binomial SE | " + " | ".join(_fmt(r["std_error"]) for r in rows) + " |",
                      "| SE over data sets | " + " | ".join(_fmt(r.get("std_error_sets")) for r in rows) + " |",
                      "| in p+0.05±0.05 | " + " | ".join("yes" if r["in_band"] else ("–" if not r["n"] else "no") for r in rows) + " |"])


def _fmt(x: float | None) -> str:
    return "–" if x is None else f"{x:.3f}"


def reliability_figure(studies: list[dict], path: str | Path, title: str = "") -> Path:
    """Reliability diagram: fraction of pairs truly from one target against the bin's mean posterior
    co-association, ±1 standard error (over data sets when known, else binomial), with the goal band
    p + 0.05 ± 0.05 shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tracker.study.plots import save_figure

    fig, ax = plt.subplots(figsize=(4.6, 4.2))
    edges = np.linspace(0, 1, N_BINS + 1)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        ax.fill_between([lo, hi], [lo, lo], [hi, hi], color="0.85", lw=0)
    ax.plot([0, 1], [0, 1], color="0.4", lw=0.8, ls="--")
    for st in studies:
        r = [b for b in st["bins"] if b["n"]]
        ax.errorbar([b["mean_prob"] for b in r], [b["fraction_same"] for b in r], yerr=[b.get("std_error_sets") or b["std_error"] for b in r],
                    marker="o", ms=4, capsize=2, lw=1, label=f"{st['design']} ({st['n_datasets']} sets, {st['pairs']} pairs)")
    ax.set_xlabel("posterior P(same target)")
    ax.set_ylabel("fraction truly from one target")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title or "reliability of co-association")
    fig.tight_layout()
    return save_figure(fig, Path(path))
