"""Where a tiled build's tiles are: row-major tile windows of the region grid, and the halo each
feature needs around a tile (one cell for slope, the distance cap in cells for distances) so the
cropped tile equals the same cells of the whole-grid build.
"""

from __future__ import annotations

import math

from rasterio.windows import Window

from pipeline.config.region import FeatureSpec, RegionConfig
from pipeline.gis.grid import Grid
from pipeline.prior.likelihood import BinnedLikelihood, LikelihoodModel, RoadDistanceLikelihood

DEFAULT_TILE = 1024
"""Tile edge in cells: a multiple of the GeoTIFF block (256), small enough for a few per worker."""
ROAD_TAIL = 1e-12
"""Derived distance caps put the road term within this relative distance of its floor mv."""


class TiledBuildError(ValueError):
    """A region config or model that the tiled build cannot handle; the message names the feature."""


def tile_windows(grid: Grid, tile: int = DEFAULT_TILE) -> list[Window]:
    """Row-major windows of at most ``tile`` x ``tile`` cells covering the grid."""
    if tile < 1:
        raise ValueError(f"tile must be >= 1 cell, got {tile}")
    return [
        Window(c, r, min(tile, grid.width - c), min(tile, grid.height - r))
        for r in range(0, grid.height, tile)
        for c in range(0, grid.width, tile)
    ]


def halo_window(core: Window, rows: int, cols: int, grid: Grid) -> Window:
    """``core`` grown by ``rows`` / ``cols`` cells on each side, clipped to the grid."""
    r0, c0 = max(0, core.row_off - rows), max(0, core.col_off - cols)
    r1 = min(grid.height, core.row_off + core.height + rows)
    c1 = min(grid.width, core.col_off + core.width + cols)
    return Window(c0, r0, c1 - c0, r1 - r0)


def needed_features(config: RegionConfig, names) -> dict[str, FeatureSpec]:
    """The feature specs behind ``names`` plus the sources of classes features among them."""
    out: dict[str, FeatureSpec] = {}
    for name in names:
        if name not in config.features:
            raise TiledBuildError(f"{config.path}: no [features.{name}] for the likelihood term {name!r}")
        spec = config.features[name]
        if spec.type == "classes":
            out[spec.source] = config.features[spec.source]
        out[name] = spec
    for spec in out.values():
        for layer in spec.layers:
            if config.layers[layer].kind == "pointcloud":
                raise TiledBuildError(
                    f"{config.path}: [features.{spec.name}] uses the point cloud [layers.{layer}]; "
                    "the tiled build needs a DEM raster (point clouds are gridded whole)"
                )
    return out


def _road_cap(term: RoadDistanceLikelihood) -> float:
    """Distance (m) beyond which the road term is within ROAD_TAIL (relative) of its floor mv."""
    ratio = (1.0 - term.mv) / (ROAD_TAIL * term.mv)
    return term.rmd * (1.0 + (math.sqrt(2.0 * math.log(ratio)) if ratio > 1.0 else 0.0))


def distance_caps(config: RegionConfig, model: LikelihoodModel | None, specs: dict[str, FeatureSpec]) -> dict[str, float]:
    """Cap (m) of each distance feature in ``specs``: its ``max_distance_m``, else the largest distance
    its uses can tell apart (road term: ROAD_TAIL; binned table or classes: their last edge)."""
    caps = {}
    terms = model.terms if model else {}
    for spec in specs.values():
        if spec.type != "distance":
            continue
        if spec.max_distance_m is not None:
            caps[spec.name] = spec.max_distance_m
            continue
        uses = []
        term = terms.get(spec.name)
        if isinstance(term, RoadDistanceLikelihood):
            uses.append(_road_cap(term))
        elif isinstance(term, BinnedLikelihood):
            uses.append(float(term.edges[-1]))
        uses += [s.breaks[-1] for s in specs.values() if s.type == "classes" and s.source == spec.name]
        if not uses:
            raise TiledBuildError(
                f"{config.path}: [features.{spec.name}]: the tiled build needs max_distance_m (metres) "
                "for a distance that no road/binned likelihood or classes breaks bound"
            )
        caps[spec.name] = max(uses)
    return caps


def feature_halos(specs: dict[str, FeatureSpec], caps: dict[str, float], grid: Grid) -> dict[str, tuple[int, int]]:
    """Halo (rows, cols) each feature needs: 1 cell for slope, the cap in cells for distances, else 0."""
    halos = {}
    for spec in specs.values():
        if spec.type == "slope":
            halos[spec.name] = (1, 1)
        elif spec.type == "distance":
            cap = caps[spec.name]
            halos[spec.name] = (math.ceil(cap / grid.dy), math.ceil(cap / grid.dx))
        else:
            halos[spec.name] = (0, 0)
    for spec in specs.values():
        if spec.type == "classes":
            halos[spec.name] = halos[spec.source]
    return halos
