"""The features of one tile: each built on the tile grown by its halo, from windowed inputs, and cropped."""

from __future__ import annotations

import dataclasses
import tempfile
import warnings
from pathlib import Path

import numpy as np
from rasterio.windows import Window

from pipeline.build.region import build_features
from pipeline.config.region import FeatureSpec, RegionConfig
from pipeline.features.stack import FeatureStack
from pipeline.gis.layers import LayerWarning
from pipeline.tiled.vrt import filtered_vector_layer, windowed_raster_layer
from pipeline.tiled.windows import feature_halos, halo_window


def tile_features(config: RegionConfig, specs: dict[str, FeatureSpec], caps: dict[str, float], core: Window) -> FeatureStack:
    """The features ``specs`` on the window ``core`` of the region grid, each built on its halo
    window by :func:`pipeline.build.region.build_features` (distances capped at ``caps``) and cropped."""
    grid = config.grid
    halos = feature_halos(specs, caps, grid)
    stack = FeatureStack(grid.window_grid(core.row_off, core.col_off, core.height, core.width))
    for halo in sorted(set(halos.values())):
        group = {
            n: (dataclasses.replace(s, max_distance_m=caps[n]) if s.type == "distance" else s)
            for n, s in specs.items() if halos[n] == halo
        }
        win = halo_window(core, *halo, grid)
        sub_grid = grid.window_grid(win.row_off, win.col_off, win.height, win.width)
        # Vector features reach a tile's cells from at most margin_m + buffer_m (+ a cell for
        # all_touched) outside it; categories read whole layers (their classes and checks are global).
        reach = max((s.margin_m + s.buffer_m for s in group.values() if s.type in ("mask", "distance")), default=0.0)
        reach += 2 * max(grid.dx, grid.dy)
        x0, y0, x1, y1 = sub_grid.bounds
        box = (x0 - reach, y0 - reach, x1 + reach, y1 + reach)
        whole = {s.layer for s in specs.values() if s.type == "categories"}
        with tempfile.TemporaryDirectory(prefix="tile-vrt-") as tmp:
            layers = dict(config.layers)
            for name in {ly for s in group.values() for ly in s.layers}:
                if layers[name].kind == "raster":
                    layers[name] = windowed_raster_layer(layers[name], sub_grid, Path(tmp))
                elif layers[name].kind == "vector" and name not in whole:
                    layers[name] = filtered_vector_layer(layers[name], box, grid.crs, Path(tmp))
            sub = dataclasses.replace(config, grid=sub_grid, layers=layers, features=group)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LayerWarning)  # "no geometry touches the grid" is normal for a tile
                built = build_features(sub, progress=False)
        r0, c0 = core.row_off - win.row_off, core.col_off - win.col_off
        for f in built:
            values = np.ascontiguousarray(f.values[r0 : r0 + core.height, c0 : c0 + core.width])
            stack.add(dataclasses.replace(f, values=values))
    return stack
