"""Plots of a fit: each feature's fitted likelihood (bars with 95% intervals, or the road curve)
against the empirical ratio (share of points / share of area). Both are scaled to an area-weighted
mean of 1 over the grid, so a bar above 1 means more targets there than under the uniform prior."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common.atomic import atomic_paths  # noqa: E402
from pipeline.learn.estimator import Z95, PriorEstimator  # noqa: E402
from pipeline.learn.forms import BASIS_FORMS  # noqa: E402
from pipeline.learn.sufficient import DISCRETE_FORMS  # noqa: E402
from pipeline.prior.likelihood import road_likelihood  # noqa: E402


def _coarse(emp: dict, n_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Merge fine distance bins into ``n_bins`` of equal area: centre (m), points, area, ratio."""
    area = np.asarray(emp["area_m2"])
    cnt = np.asarray(emp["count"])
    lo = np.asarray(emp["bin_centre"])
    cum = np.cumsum(area) / area.sum()
    group = np.minimum((cum * n_bins).astype(int), n_bins - 1)
    a = np.bincount(group, weights=area, minlength=n_bins)
    c = np.bincount(group, weights=cnt, minlength=n_bins)
    d = np.bincount(group, weights=area * lo, minlength=n_bins) / np.where(a > 0, a, 1)
    ok = a > 0
    ratio = (c[ok] / max(cnt.sum(), 1)) / (a[ok] / area.sum())
    return d[ok], c[ok], a[ok], ratio


def plot_fit(est: PriorEstimator, path: str | Path, n_distance_bins: int = 30) -> Path:
    """One panel per fitted terrain term; writes a PNG."""
    emp = est.empirical()
    terms = [t for t in est.terms_ if t.feature in emp]
    cols = min(3, len(terms))
    rows = int(np.ceil(len(terms) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows), squeeze=False)
    for ax, t in zip(axes.ravel(), terms, strict=False):
        e = emp[t.feature]
        area = np.asarray(e["area_m2"])
        if t.form in DISCRETE_FORMS:
            fitted = np.array([est.likelihoods_[t.feature][lv] for lv in t.levels])
            ci = np.array([est.ci_[t.feature][lv] for lv in t.levels])
            scale = (area @ fitted) / area.sum()
            ratio = np.asarray(e["ratio"])
            rscale = np.nansum(area * np.nan_to_num(ratio)) / area.sum()
            x = np.arange(len(t.levels))
            ax.bar(x, fitted / scale, color="#8fb3d9", label="fitted (ML)")
            err = np.abs(np.nan_to_num(ci / scale - (fitted / scale)[:, None])).T
            ax.errorbar(x, fitted / scale, yerr=err, fmt="none", ecolor="k", capsize=3, label="95% CI")
            ax.plot(x, ratio / rscale if rscale > 0 else ratio, "o", color="#d95f02", label="points / area")
            ax.set_xticks(x, [f"{lv}\n(n={int(c)})" for lv, c in zip(t.levels, e["count"], strict=True)], fontsize=8)
        elif t.form in BASIS_FORMS:
            d, _, a, ratio = _coarse(e, n_distance_bins)
            c = est.curves_[t.feature]
            v, lr, se = (np.asarray(c[k]) for k in ("value", "logr", "se"))
            fine = np.asarray(e["bin_centre"])
            # area mean 1, like the empirical ratio: the curve's area-weighted mean over the grid
            scale = (area @ np.exp(np.interp(fine, v, lr))) / area.sum()
            ax.plot(v, np.exp(lr) / scale, color="#1f78b4", label=f"fitted {t.form} in {t.scale}")
            ax.fill_between(v, np.exp(lr - Z95 * se) / scale, np.exp(lr + Z95 * se) / scale, color="#1f78b4", alpha=0.25,
                            label="95% CI (pointwise)")
            ax.plot(d, ratio, "o", ms=3, color="#d95f02", label="points / area (equal-area bins)")
            if t.scale == "log1p":
                ax.set_xscale("symlog", linthresh=1.0)
            ax.set_yscale("log")
            ax.set_xlabel(f"{t.feature} ({est.stack_[t.feature].units if est.stack_ is not None else ''})")
        else:
            d, _, a, ratio = _coarse(e, n_distance_bins)
            p = est.likelihoods_[t.feature]
            fine = np.asarray(e["bin_centre"])
            scale = (area @ road_likelihood(fine, p["rmd"], p["mv"])) / area.sum()
            # dense near the road, where the form peaks at rmd, sparse far out
            dd = np.unique(np.concatenate([np.linspace(0, min(fine.max(), 10 * p["rmd"]), 300), np.geomspace(1, fine.max(), 300)]))
            ax.plot(dd, road_likelihood(dd, p["rmd"], p["mv"]) / scale, color="#1f78b4",
                    label=f"fitted rmd={p['rmd']:.0f} m, mv={p['mv']:.2f}")
            ax.plot(d, ratio, "o", ms=3, color="#d95f02", label="points / area (equal-area bins)")
            ax.set_xscale("symlog", linthresh=max(e["bin_width"] * 20, 1.0))
            ax.set_xlabel("distance (m)")
        ax.set_title(t.feature)
        ax.set_ylabel("relative likelihood (area mean 1)")
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(terms):]:
        ax.axis("off")
    fig.suptitle(f"fitted likelihoods ({est.method}, n = {est.n_used_} points)")
    fig.tight_layout()
    with atomic_paths(path) as (tmp,):
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(path)
