"""Figures like paper 1's Figures 11–15 (mean score and mean |N̂_D − N_D| versus τ) and Table 1 as text.

Inputs are the experiment's long-format results table (one row per data set, algorithm and τ; the
``algorithm`` column is the variant for greedy, "TT batch" for batch, "TT posterior" for its Bayes estimates).
Scores are drawn scaled by 10^4.5 per metre, as in the paper.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from common.atomic import atomic_paths  # noqa: E402

SCORE_SCALE = 10**4.5
PAPER_TABLE = {"TT": {"UT": 0.63, "UU": 0.99}, "UT": {"TT": 0.37, "UU": 0.99}, "UU": {"TT": 0.005, "UT": 0.0}}


def save_figure(fig: plt.Figure, path: Path) -> Path:
    with atomic_paths(path) as (tmp,):
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def _errorbar_panel(ax: plt.Axes, results: pd.DataFrame, variants: Sequence[str], column: str, scale: float) -> None:
    for variant in variants:
        g = results[results["algorithm"] == variant].groupby("tau")[column]
        mean, std = g.mean() * scale, g.std(ddof=1).fillna(0.0) * scale
        ax.errorbar(mean.index, mean.values, yerr=std.values, capsize=2, marker="o", ms=3, lw=1, label=variant)
    ax.set_xlabel("τ")
    ax.grid(alpha=0.3)
    if len(variants) > 1:
        ax.legend()


def _split(results: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(rows with S = e^{-nτ}, rows with the exact eq. 16 S, which have no τ)."""
    exact = results["s_model"] == "poisson"
    return results[~exact], results[exact]


def score_figure(results: pd.DataFrame, variant: str, path: Path, title: str = "") -> Path:
    """Mean Score (×10^4.5 per m) versus τ with ±1 standard deviation bars (Figures 11–13); a dashed
    line for the exact-S (Poisson) runs when present."""
    results, exact = _split(results)
    fig, ax = plt.subplots(figsize=(5, 3.4))
    _errorbar_panel(ax, results, [variant], "score", SCORE_SCALE)
    mean_exact = exact.loc[exact["algorithm"] == variant, "score"].mean() * SCORE_SCALE
    if exact["algorithm"].eq(variant).any():
        ax.axhline(mean_exact, ls="--", color="0.3", lw=1, label="exact S, Poisson(μ)")
        ax.legend()
    ax.set_ylabel("Score × 10^4.5 (1/m)")
    ax.set_title(title or f"Average scores, {variant}")
    fig.tight_layout()
    return save_figure(fig, path)


def nd_error_figure(results: pd.DataFrame, variants: Sequence[str], path: Path, title: str = "") -> Path:
    """Mean |N̂_D − N_D| after all reports versus τ, ±1 standard deviation (Figures 14–15)."""
    results, _ = _split(results)
    fig, ax = plt.subplots(figsize=(5, 3.4))
    _errorbar_panel(ax, results, variants, "nd_abs_error", 1.0)
    ax.set_ylabel("|N̂_D − N_D|")
    ax.set_title(title or f"Average absolute error of N̂_D, {' and '.join(variants)}")
    fig.tight_layout()
    return save_figure(fig, path)


def overview_figure(results: pd.DataFrame, variants: Sequence[str], path: Path, title: str = "") -> Path:
    """Mean Score, |N̂_D − N_D|, GOSPA and purity versus τ for all variants on one page."""
    panels = [("score", SCORE_SCALE, "Score × 10^4.5 (1/m)"), ("nd_abs_error", 1.0, "|N̂_D − N_D|"),
              ("gospa_m", 1.0, "GOSPA (m)"), ("purity", 1.0, "association purity")]
    results, _ = _split(results)
    fig, axes = plt.subplots(2, 2, figsize=(9, 6.5))
    for ax, (column, scale, label) in zip(axes.ravel(), panels, strict=True):
        for variant in variants:
            mean = results[results["algorithm"] == variant].groupby("tau")[column].mean() * scale
            ax.plot(mean.index, mean.values, marker="o", ms=3, lw=1, label=variant)
        ax.set_xlabel("τ")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0, 0].legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def table_markdown(table: Mapping[str, Mapping[str, float | None]], paper: bool = True) -> str:
    """Table 1 as Markdown: P(row better than column), with the paper's value in brackets."""
    names = list(table)
    lines = ["| row better than column | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for a in names:
        cells = []
        for b in names:
            v = table[a][b]
            if v is None:
                cells.append("=")
            else:
                ref = PAPER_TABLE.get(a, {}).get(b)
                cells.append(f"{v:.3f}" + (f" ({ref:g})" if paper and ref is not None else ""))
        lines.append(f"| **{a}** | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _titled(title: str, what: str) -> str:
    return f"{title}: {what}" if title else what


def write_figures(results: pd.DataFrame, out_dir: Path, prefix: str = "", title: str = "") -> list[Path]:
    """All figures for one experiment into ``out_dir`` (PNG); returns their paths. Curves are per
    ``algorithm`` ("TT" greedy, "TT batch", "TT posterior"); batch and posterior share greedy's
    |N̂_D − N_D| panels."""
    out_dir = Path(out_dir)
    names = [f"{v}{m}" for m in ("", " batch", " posterior") for v in ("UU", "UT", "TT")]
    variants = [v for v in names if v in set(results["algorithm"])]
    paths = [score_figure(results, v, out_dir / f"{prefix}score_{v.replace(' ', '_')}.png", _titled(title, f"average scores, {v}"))
             for v in variants]
    groups = [g for g in ([f"{v}{m}" for m in ("", " batch", " posterior") for v in ("UU", "UT")],
                          ["TT", "TT batch", "TT posterior"]) if set(g) & set(variants)]
    for g in groups:
        present = [v for v in g if v in variants]
        paths.append(nd_error_figure(results, present, out_dir / f"{prefix}nd_error_{'_'.join(present).replace(' ', '_')}.png",
                                     _titled(title, f"|N̂_D − N_D|, {' and '.join(present)}")))
    paths.append(overview_figure(results, variants, out_dir / f"{prefix}overview.png", title))
    return paths


def tracks_figure(
    prior,
    report_means,
    report_covs,
    track_means,
    track_covs,
    path: Path,
    targets=None,
    ellipse_prob: float = 0.95,
    title: str = "",
) -> Path:
    """Map of the prior (square-root grey scale) with the reports' and the estimated targets'
    ``ellipse_prob`` covariance ellipses (metres, the prior's CRS) and, for simulations, the true targets."""
    from matplotlib.collections import PolyCollection

    from tracker.io.tracks import ellipse_polygons

    fig, ax = plt.subplots(figsize=(8, 7))
    left, bottom, right, top = prior.grid.bounds
    ax.imshow(prior.density**0.5, extent=(left, right, bottom, top), cmap="gray", origin="upper")
    for means, covs, colour, label in (
        (report_means, report_covs, "tab:orange", f"reports ({len(report_means)})"),
        (track_means, track_covs, "tab:cyan", f"estimated targets ({len(track_means)})"),
    ):
        if len(means):
            rings = [np.asarray(p.exterior.coords) for p in ellipse_polygons(means, covs, ellipse_prob)]
            ax.add_collection(PolyCollection(rings, facecolors="none", edgecolors=colour, linewidths=0.8, label=label))
    if targets is not None and len(targets):
        ax.plot(targets[:, 0], targets[:, 1], "+", color="tab:red", ms=6, label=f"true targets ({len(targets)})")
    pts = np.concatenate([np.reshape(report_means, (-1, 2)), np.reshape(track_means, (-1, 2))])
    if len(pts):
        pad = 300.0
        ax.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
        ax.set_ylim(pts[:, 1].min() - pad, pts[:, 1].max() + pad)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"reports and estimated targets ({ellipse_prob:.0%} ellipses)")
    ax.legend(loc="upper right", fontsize=8)
    return save_figure(fig, Path(path))
