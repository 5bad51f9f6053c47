"""Fitting the likelihoods on grids larger than memory: every statistic the fit needs, per tile.

:meth:`pipeline.learn.estimator.PriorEstimator.fit_stats` needs the cell statistics (area per combination of
term levels; :func:`pipeline.tiled.cells.tiled_cell_stats` adds them up over tiles) and each
point's levels and values. The latter come from the tiles that hold points only: each such tile's
features (:func:`pipeline.tiled.tiles.tile_features`) are sampled at the centres of its points' cells, so
a point reads the same cell it reads on the whole grid, and no process builds more than one tile.

Example::

    with get_client("tcp://10.0.0.5:8786") as client:
        cells, points = tiled_stats(config, est, xy_m, client, tile=1024)
    est.fit_stats(cells, points)
"""

from __future__ import annotations

import numpy as np
from distributed import Client, as_completed
from rasterio.windows import Window
from tqdm import tqdm

from common.dask import get_client
from pipeline.config.region import RegionConfig
from pipeline.learn.estimator import PriorEstimator
from pipeline.learn.sufficient import (
    NODATA_INDEX,
    CellStats,
    PointStats,
    Term,
    check_points,
    point_stats,
)
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.tiled.cells import learning_setup, tiled_cell_stats, tiled_terms
from pipeline.tiled.tiles import tile_features
from pipeline.tiled.windows import DEFAULT_TILE


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
    u, v = grid.to_pixel(pts[:, 0], pts[:, 1])
    inside = (u >= 0) & (u < grid.width) & (v >= 0) & (v < grid.height)
    row = np.floor(np.where(inside, v, 0)).astype(np.int64)
    col = np.floor(np.where(inside, u, 0)).astype(np.int64)
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
    own = client is None
    client = client or get_client(None)
    try:
        n = len(wins)
        futures = client.map(_tile_points, [config] * n, [specs] * n, [caps] * n, [terms] * n, wins, centres, pure=False)
        where = {f.key: sel for f, sel in zip(futures, groups, strict=True)}
        for fut in tqdm(as_completed(futures), total=n, desc="point statistics", unit="tile", disable=not progress):
            part = fut.result()
            index[where[fut.key]] = part.index
            value[where[fut.key]] = part.value
    finally:
        if own:
            client.close()
    return PointStats(terms, index, value, inside)


def learning_template(estimator: PriorEstimator) -> LikelihoodModel:
    """The template restricted to the estimator's ``features``: the tiled pass needs each fitted
    feature's form from a template (quantile bins of an untemplated feature need every value)."""
    template = estimator.template
    if template is None:
        raise ValueError("tiled learning needs a template ([likelihood.*] tables in the region config) giving each feature's form")
    names = list(estimator.features or template.terms)
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
    own = client is None
    client = client or get_client(None)
    try:
        terms = tiled_terms(config, learning_template(estimator), client, tile, estimator.flexible,
                            estimator.bin_width, progress)
        cells = tiled_cell_stats(config, terms, client, tile, progress)
        pstats = tiled_point_stats(config, terms, points, client, tile, progress)
    finally:
        if own:
            client.close()
    return cells, pstats
