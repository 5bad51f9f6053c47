"""The learning pass at scale: every statistic the Poisson-process fit needs, per tile on Dask workers.

:meth:`pipeline.learn.estimator.PriorEstimator.fit_stats` needs two things, and neither needs the grid whole:

- **cell statistics** (:class:`pipeline.learn.sufficient.CellStats`: area per combination of term
  levels, and the mean continuous value in each). They add up over any partition of the grid, so
  each tile's features (:func:`pipeline.tiled.tiles.tile_features`) go through
  :func:`pipeline.learn.sufficient.cell_stats` on a worker and the client merges the small tables
  (:func:`tiled_cell_stats`, :func:`merge_cell_stats`). Equality with
  ``cell_stats(build_features(config), terms)``: the same combinations in the same order, areas
  exact (cell counts times the cell area), continuous means within float rounding (a mean of tile
  means weighted by area instead of one running sum).
- **point statistics**: each point's levels and values, from the tiles that hold points only
  (:func:`tiled_point_stats`): each such tile's features are sampled at the centres of its
  points' cells, so a point reads the same cell it reads on the whole grid.

Terms need two grid-wide facts first — the category codes present and the range of each continuous
feature — gathered in one cheap tile pass (:func:`feature_summaries`); :func:`tiled_terms` then runs
:func:`pipeline.learn.estimator.make_terms` on a tiny stack holding exactly those values, which gives the
terms of the whole grid (quantile bins, which need every value, are refused: give edges instead).

Example::

    with get_client("tcp://10.0.0.5:8786") as client:
        cells, points = tiled_stats(config, est, xy_m, client, tile=1024)
    est.fit_stats(cells, points)
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from distributed import Client, as_completed
from rasterio.windows import Window
from sklearn.base import clone
from tqdm import tqdm

from common.dask import get_client, using_client
from pipeline.config.region import RegionConfig
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE, Grid
from pipeline.learn.estimator import PriorEstimator, make_terms
from pipeline.learn.run import LearnReport, prepare_learning, report_paths, write_report
from pipeline.learn.sufficient import (
    CONTINUOUS_FORMS,
    NODATA_INDEX,
    CellStats,
    PointStats,
    Term,
    cell_stats,
    check_points,
    point_stats,
)
from pipeline.prior.likelihood import BinnedLikelihood, LikelihoodModel
from pipeline.tiled.tiles import tile_features
from pipeline.tiled.windows import (
    DEFAULT_TILE,
    TiledBuildError,
    distance_caps,
    needed_features,
    tile_windows,
)

log = logging.getLogger(__name__)


def learning_setup(config: RegionConfig, names) -> tuple[dict, dict]:
    """Feature specs behind ``names`` and their distance caps. A distance fitted directly (road form
    or bins) needs ``max_distance_m`` in the config: its fitted shape may reach any distance."""
    specs = needed_features(config, names)
    for name in names:
        spec = specs[name]
        if spec.type == "distance" and spec.max_distance_m is None:
            raise TiledBuildError(
                f"{config.path}: [features.{name}]: the tiled learning pass needs max_distance_m (metres) "
                "on a distance it fits, so every tile's distances are exact"
            )
    return specs, distance_caps(config, None, specs)


# --------------------------------------------------------------------------- grid-wide facts
def _summarise(stack: FeatureStack) -> dict[str, dict]:
    out = {}
    for f in stack:
        meta = {"kind": f.kind, "units": f.units, "labels": dict(f.labels)}
        if f.kind == "categorical":
            meta["codes"] = set(f.codes().tolist())
        else:
            finite = f.values[np.isfinite(f.values)]
            meta["range"] = (float(finite.min()), float(finite.max())) if finite.size else None
        out[f.name] = meta
    return out


def _merge_summaries(a: dict, b: dict) -> dict:
    out = {}
    for name, m in a.items():
        n = dict(m)
        if m["kind"] == "categorical":
            n["codes"] = m["codes"] | b[name]["codes"]
        else:
            ranges = [r for r in (m["range"], b[name]["range"]) if r is not None]
            n["range"] = (min(r[0] for r in ranges), max(r[1] for r in ranges)) if ranges else None
        out[name] = n
    return out


def _tile_summary(config: RegionConfig, specs: dict, caps: dict, win: Window) -> dict:
    return _summarise(tile_features(config, specs, caps, win))


def feature_summaries(config: RegionConfig, specs: dict, caps: dict, client: Client, tile: int = DEFAULT_TILE,
                      progress: bool = True) -> dict[str, dict]:
    """Per feature over the whole grid: kind, units, labels, and the codes present (categorical) or
    the finite (min, max) (continuous; None when it has no data)."""
    wins = tile_windows(config.grid, tile)
    futures = client.map(_tile_summary, [config] * len(wins), [specs] * len(wins), [caps] * len(wins), wins, pure=False)
    total = None
    for fut in tqdm(as_completed(futures), total=len(futures), desc="feature summaries", unit="tile", disable=not progress):
        part = fut.result()
        total = part if total is None else _merge_summaries(total, part)
    return total


def summary_stack(grid: Grid, summaries: dict[str, dict]) -> FeatureStack:
    """A one-row stack whose cells are each feature's distinct codes, or its min and max: every
    grid-wide fact :func:`pipeline.learn.estimator.make_terms` uses apart from quantiles."""
    width = max(2, *(len(m.get("codes", ())) for m in summaries.values()))
    row = Grid(grid.crs, grid.transform, 1, width)
    stack = FeatureStack(row)
    for name, m in summaries.items():
        if m["kind"] == "categorical":
            codes = sorted(m["codes"]) or [NODATA_CODE]
            values = np.resize(np.asarray(codes, dtype=np.int32), width)
        else:
            lo, hi = m["range"] if m["range"] is not None else (np.nan, np.nan)
            values = np.full(width, hi)
            values[0] = lo
        stack.add(Feature(name, values[None, :], m["kind"], m["units"], m["labels"]))
    return stack


def tiled_terms(
    config: RegionConfig,
    template: LikelihoodModel,
    client: Client | None = None,
    tile: int = DEFAULT_TILE,
    flexible: dict[str, list[float]] | None = None,
    bin_width: float | None = None,
    progress: bool = True,
) -> list[Term]:
    """The terms :func:`pipeline.learn.estimator.make_terms` makes for ``template``'s features on the whole grid."""
    names = list(template.terms)
    specs, caps = learning_setup(config, names)
    flexible = flexible or {}
    with using_client(client) as c:
        summaries = feature_summaries(config, specs, caps, c, tile, progress)
    for name in names:
        m = summaries[name]
        quantiles = (m["kind"] == "continuous" and name not in flexible and m["units"] != "m"
                     and not isinstance(template.terms[name], BinnedLikelihood))
        if quantiles:
            raise TiledBuildError(f"feature {name!r}: quantile bins need every value; give bin edges (flexible) or a binned template")
    terms, _ = make_terms(summary_stack(config.grid, summaries), template, tuple(names), flexible, bin_width, 8)
    return terms


# --------------------------------------------------------------------------------- reduction
def merge_cell_stats(parts: list[CellStats]) -> CellStats:
    """Sum of cell statistics over disjoint parts of one grid (same terms): areas added per
    combination, continuous means weighted by area; rows in :func:`cell_stats`' order (the mixed-radix
    key with the first term least significant)."""
    if not parts:
        raise ValueError("merge_cell_stats: no parts")
    index = np.concatenate([p.index for p in parts])
    value = np.concatenate([p.value for p in parts])
    area = np.concatenate([p.area for p in parts])
    keys, inv = np.unique(index, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.lexsort(keys.T)  # last term most significant, as in the combination key
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    inv = rank[inv]
    keys = keys[order]
    total = np.bincount(inv, weights=area, minlength=keys.shape[0])
    merged = np.full(keys.shape, np.nan)
    for k, t in enumerate(parts[0].terms):
        if t.form in CONTINUOUS_FORMS:
            ok = ~np.isnan(value[:, k])
            s = np.bincount(inv[ok], weights=(area * value[:, k])[ok], minlength=keys.shape[0])
            merged[:, k] = np.where(keys[:, k] >= 0, s / total, np.nan)
    return CellStats(parts[0].terms, keys, merged, total, parts[0].cell_area, sum(p.n_cells for p in parts))


def _tile_stats(config: RegionConfig, specs: dict, caps: dict, terms: tuple[Term, ...], win: Window) -> CellStats:
    return cell_stats(tile_features(config, specs, caps, win), terms)


def tiled_cell_stats(
    config: RegionConfig, terms, client: Client | None = None, tile: int = DEFAULT_TILE, progress: bool = True
) -> CellStats:
    """:func:`pipeline.learn.sufficient.cell_stats` of the region's features, computed per tile on ``client``
    (default: an in-process cluster) and merged; no process holds more than a few tiles."""
    terms = tuple(terms)
    specs, caps = learning_setup(config, [t.feature for t in terms])
    wins = tile_windows(config.grid, tile)
    with using_client(client) as c:
        futures = c.map(_tile_stats, [config] * len(wins), [specs] * len(wins), [caps] * len(wins),
                        [terms] * len(wins), wins, pure=False)
        parts = [f.result() for f in tqdm(as_completed(futures), total=len(futures), desc="cell statistics",
                                          unit="tile", disable=not progress)]
    return merge_cell_stats(parts)


# ------------------------------------------------------------------------------ point statistics
def _tile_points(config: RegionConfig, specs: dict, caps: dict, terms: tuple[Term, ...], win: Window,
                 centres: np.ndarray) -> PointStats:
    return point_stats(tile_features(config, specs, caps, win), terms, centres)


def tiled_point_stats(
    config: RegionConfig, terms, points: np.ndarray, client: Client | None = None, tile: int = DEFAULT_TILE,
    progress: bool = True,
) -> PointStats:
    """:func:`pipeline.learn.sufficient.point_stats` of points (N, 2) (metres, the grid's CRS) on the region's
    features, built only on the tiles (``tile`` cells a side, as in :func:`pipeline.tiled.windows.tile_windows`)
    that hold points, on ``client`` (default: an in-process cluster). Off-grid points get no data."""
    terms = tuple(terms)
    pts = check_points(points)
    if tile < 1:
        raise ValueError(f"tile must be >= 1 cell, got {tile}")
    grid = config.grid
    row, col, inside = grid.cell_index(pts[:, 0], pts[:, 1])
    index = np.full((len(pts), len(terms)), NODATA_INDEX, dtype=np.int64)
    value = np.full(index.shape, np.nan)
    tile_id = (row // tile) * ((grid.width + tile - 1) // tile) + col // tile
    groups = [np.flatnonzero(inside & (tile_id == t)) for t in np.unique(tile_id[inside])]
    if not groups:
        return PointStats(terms, index, value, inside)
    specs, caps = learning_setup(config, [t.feature for t in terms])
    wins, centres = [], []
    for sel in groups:
        r0, c0 = int(row[sel[0]] // tile * tile), int(col[sel[0]] // tile * tile)
        win = Window(c0, r0, min(tile, grid.width - c0), min(tile, grid.height - r0))
        # Cell centres of the tile's own grid: a point on a tile edge reads the cell it reads on the whole grid.
        sub = grid.window_grid(r0, c0, win.height, win.width)
        xy = np.column_stack([sub.transform.c + (col[sel] - c0 + 0.5) * sub.dx, sub.transform.f - (row[sel] - r0 + 0.5) * sub.dy])
        wins.append(win)
        centres.append(xy)
    with using_client(client) as c:
        n = len(wins)
        futures = c.map(_tile_points, [config] * n, [specs] * n, [caps] * n, [terms] * n, wins, centres, pure=False)
        where = {f.key: sel for f, sel in zip(futures, groups, strict=True)}
        for fut in tqdm(as_completed(futures), total=n, desc="point statistics", unit="tile", disable=not progress):
            part = fut.result()
            index[where[fut.key]] = part.index
            value[where[fut.key]] = part.value
    return PointStats(terms, index, value, inside)


def learning_template(estimator: PriorEstimator) -> LikelihoodModel:
    """The template restricted to the estimator's ``features``: the tiled pass needs each fitted
    feature's form from a template (quantile bins of an untemplated feature need every value)."""
    template = estimator.template
    if template is None:
        raise ValueError("tiled learning needs a template ([likelihood.*] tables in the region config) giving each feature's form")
    names = list(estimator.feature_names or template.terms)
    missing = [n for n in names if n not in template.terms]
    if missing:
        raise ValueError(f"tiled learning: features {missing} have no [likelihood.*] template table; add one per fitted feature")
    return LikelihoodModel({n: template.terms[n] for n in names}, template.meta)


def tiled_stats(
    config: RegionConfig, estimator: PriorEstimator, points: np.ndarray, client: Client | None = None,
    tile: int = DEFAULT_TILE, progress: bool = True,
) -> tuple[CellStats, PointStats]:
    """The cell and point statistics :meth:`PriorEstimator.fit_stats` takes, for ``estimator``'s
    template, features, ``flexible`` bins and ``bin_width``, computed tile by tile on ``client``."""
    with using_client(client) as c:
        terms = tiled_terms(config, learning_template(estimator), c, tile, estimator.flexible,
                            estimator.bin_width, progress)
        cells = tiled_cell_stats(config, terms, c, tile, progress)
        pstats = tiled_point_stats(config, terms, points, c, tile, progress)
    return cells, pstats


def learn_region_tiled(
    region: str | Path, targets: str | Path, out: str | Path, layer: str | None = None, x: str = "x", y: str = "y",
    targets_crs: str | None = None, scheduler: str | None = None, tile: int = DEFAULT_TILE, progress: bool = True,
) -> LearnReport:
    """:func:`pipeline.learn.run.learn_region` on a grid larger than memory: the statistics per tile
    (``tile`` cells a side) on Dask (``scheduler`` address, or a local in-process cluster), then the same ML
    and naive fits. The spatial block cross-validation and the hybrid need the whole grid and are skipped."""
    config, lc, pts, est = prepare_learning(region, targets, layer, x, y, targets_crs)
    if lc.forms or lc.weights:
        raise ValueError(f"{config.path}: tiled learning fits the [likelihood.*] tables' forms, unweighted; [learn] forms/weights need the in-memory learn")
    est.set_params(defensive=None if lc.defensive == "cv" else lc.defensive, temper=None if lc.temper == "cv" else lc.temper)
    skipped = ["the spatial block cross-validation"] + (["the hybrid fit"] if lc.hybrid else []) + (
        ["the defensive mixture's cross-fitted epsilon"] if lc.defensive == "cv" else [])
    log.info("tiled learning: skipping %s (they need the whole grid)", " and ".join(skipped))
    with get_client(scheduler) as client:
        cells, points = tiled_stats(config, est, pts, client, tile, progress)
    est.fit_stats(cells, points)
    naive = clone(est).set_params(method="naive").fit_stats(cells, points)
    est.model_.meta["learned"]["tiled"] = {"tile_cells": tile, "scheduler": scheduler or "local"}
    return write_report(LearnReport(est, naive, None, None, report_paths(out), lc), targets)
