"""Small synthetic feature stacks and the true model for the learn tests (points: ``TerrainPrior.sample``)."""

from __future__ import annotations

import numpy as np
from affine import Affine
from scipy import ndimage

from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import Grid
from pipeline.prior.likelihood import CategoricalLikelihood, LikelihoodModel, RoadDistanceLikelihood


def small_stack(h: int = 60, w: int = 80, cell: float = 20.0, seed: int = 0) -> FeatureStack:
    """Correlated features: ``land`` (3 classes in blobs), ``water`` (a lake, a structural zero),
    ``road_distance`` (metres to a diagonal road: the lake and some land classes sit near it)."""
    rng = np.random.default_rng(seed)
    grid = Grid("EPSG:32734", Affine(cell, 0.0, 300_000.0, 0.0, -cell, 6_200_000.0), h, w)
    rows, cols = np.mgrid[0:h, 0:w]
    road = np.abs(rows - 0.6 * cols - 5) < 0.8
    d = ndimage.distance_transform_edt(~road) * cell
    noise = ndimage.gaussian_filter(rng.normal(size=(h, w)), 4)
    land = np.digitize(noise + 0.002 * d / cell, np.quantile(noise, [0.4, 0.75])).astype(np.int16)
    water = (((rows - h * 0.3) ** 2 + (cols - w * 0.7) ** 2) < (min(h, w) * 0.15) ** 2).astype(np.int16)
    stack = FeatureStack(grid)
    stack.add(Feature("land", land, "categorical", labels={0: "grass", 1: "bush", 2: "rock"}))
    stack.add(Feature("water", water, "categorical", labels={0: "dry", 1: "water"}))
    stack.add(Feature("road_distance", d, "continuous", "m"))
    return stack


TRUE_MODEL = LikelihoodModel(
    {
        "land": CategoricalLikelihood({"grass": 1.0, "bush": 0.5, "rock": 0.2}),
        "water": CategoricalLikelihood({"dry": 1.0, "water": 0.0}),
        "road_distance": RoadDistanceLikelihood(rmd=80.0, mv=0.15),
    }
)
