"""Maps like paper 1's Figures 1 (road, water, obstacle features) and 2 (the prior density), as PNG."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from scipy.ndimage import binary_dilation  # noqa: E402

from common.atomic import atomic_paths  # noqa: E402
from pipeline.features.stack import FeatureStack  # noqa: E402
from pipeline.gis.grid import Grid  # noqa: E402
from pipeline.prior.terrain import TerrainPrior  # noqa: E402


def _extent_km(grid: Grid) -> tuple[float, float, float, float]:
    xmin, ymin, xmax, ymax = grid.bounds
    return (0.0, (xmax - xmin) / 1000.0, 0.0, (ymax - ymin) / 1000.0)


def _save(fig, path: str | Path) -> Path:
    with atomic_paths(path) as (tmp,):
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)


def plot_prior(prior: TerrainPrior, path: str | Path) -> Path:
    """Figure 2: the density, lighter = more probable, a nonlinear (square-root) scale so zeros stand out black."""
    fig, ax = plt.subplots(figsize=(7, 6.2))
    d = np.asarray(prior.density)
    im = ax.imshow(np.sqrt(d / d.max()), cmap="gray", extent=_extent_km(prior.grid), interpolation="nearest")
    ax.set(xlabel="east (km)", ylabel="north (km)", title=f"Prior density ({prior.grid.crs.to_string()}, {prior.grid.dx:g} m cells)")
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label("sqrt(density / max density)")
    return _save(fig, path)


def road_water_obstacles(stack: FeatureStack, road: str = "road_distance", water: str = "water",
                         obstacles: str = "obstacles", widen: bool = False) -> np.ndarray:
    """Figure 1's classes per cell: 0 open ground, 1 road, 2 water or obstacle (missing features skipped);
    ``widen`` draws roads one cell wider on each side."""
    classes = np.zeros(stack.grid.shape, dtype=np.int8)
    if road in stack:
        classes[stack[road].values <= 0] = 1
        if widen:  # a 1-cell road vanishes when 700 cells are drawn on ~450 pixels
            classes[binary_dilation(classes == 1, structure=np.ones((3, 3), dtype=bool))] = 1
    for name in (water, obstacles):
        if name in stack:
            classes[stack[name].values == 1] = 2
    return classes


def plot_features(stack: FeatureStack, path: str | Path) -> Path:
    """Figure 1 (roads white, water and obstacles black on grey) plus one panel per feature."""
    features = list(stack)
    n = len(features) + 1
    cols = min(4, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.9 * rows), squeeze=False)
    extent = _extent_km(stack.grid)
    ax = axes.flat[0]
    ax.imshow(road_water_obstacles(stack, widen=max(stack.grid.shape) > 400), cmap=ListedColormap(["0.55", "white", "black"]), vmin=0, vmax=2,
              extent=extent, interpolation="nearest")
    ax.set_title("roads (white), water and obstacles (black)", fontsize=10)
    for ax, f in zip(axes.flat[1:], features, strict=False):
        if f.kind == "categorical":
            codes = f.codes()
            shown = np.ma.masked_less(f.values, 0)
            im = ax.imshow(shown, cmap=plt.get_cmap("tab10", max(len(codes), 1)), extent=extent,
                           interpolation="nearest", vmin=codes.min() - 0.5 if codes.size else 0,
                           vmax=codes.max() + 0.5 if codes.size else 1)
            cb = fig.colorbar(im, ax=ax, shrink=0.8, ticks=codes)
            cb.ax.set_yticklabels([f.label(c) for c in codes])
        else:
            im = ax.imshow(np.ma.masked_invalid(f.values), cmap="viridis", extent=extent, interpolation="nearest")
            fig.colorbar(im, ax=ax, shrink=0.8).set_label(f.units)
        ax.set_title(f.name)
    for ax in axes.flat:
        ax.set_xlabel("east (km)")
        ax.set_ylabel("north (km)")
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    fig.tight_layout()
    return _save(fig, path)
