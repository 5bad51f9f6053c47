"""Figure 1's class map (roads, water, obstacles) vs a direct cell-by-cell construction."""

from __future__ import annotations

import numpy as np

from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import Grid
from pipeline.show.plots import road_water_obstacles


def test_road_water_obstacle_classes() -> None:
    rng = np.random.default_rng(5)
    grid = Grid.from_bounds((0, 0, 200, 160), 20.0, "EPSG:32634")
    stack = FeatureStack(grid)
    d = rng.choice([0.0, 20.0, 40.0], grid.shape, p=[0.2, 0.4, 0.4])
    water = (rng.random(grid.shape) < 0.2).astype(np.int16)
    obstacles = (rng.random(grid.shape) < 0.1).astype(np.int16)
    stack.add(Feature("road_distance", d, "continuous", units="m"))
    stack.add(Feature("water", water, "categorical"))
    stack.add(Feature("obstacles", obstacles, "categorical"))
    for widen in (False, True):
        got = road_water_obstacles(stack, widen=widen)
        for r in range(grid.height):
            for c in range(grid.width):
                near = d[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2] if widen else d[r:r + 1, c:c + 1]
                expected = 2 if water[r, c] or obstacles[r, c] else (1 if (near == 0).any() else 0)
                assert got[r, c] == expected, (widen, r, c)
