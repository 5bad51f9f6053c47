"""Learning the likelihood tables from past targets: the estimator, its statistics, its evaluation.

Public names only; ``pipeline.learn.plots`` (matplotlib) and ``pipeline.learn.run`` (the CLI use
case) are imported from their modules.
"""

from pipeline.gis.targets import read_targets
from pipeline.learn.estimator import (
    SPATIAL,
    PriorEstimator,
    cross_fitted,
    make_terms,
    template_start,
    with_features,
)
from pipeline.learn.evaluate import (
    MODELS,
    CVResult,
    FoldModels,
    block_cv,
    default_bandwidths,
    with_mixture,
    with_model,
    with_selection,
)
from pipeline.learn.kde import block_folds, block_ids, fit_kde_cv, grid_kde, log_kde_feature
from pipeline.learn.mixture import MixturePrior, simplex_weights
from pipeline.learn.select import BackwardSelection
from pipeline.learn.sufficient import (
    CellStats,
    PointStats,
    Term,
    cached_cell_stats,
    cell_stats,
    check_points,
    point_stats,
    with_range,
)
from pipeline.learn.window import BlockWindow

__all__ = [
    "MODELS", "SPATIAL", "BackwardSelection", "BlockWindow", "CVResult", "CellStats", "FoldModels", "MixturePrior", "PointStats", "PriorEstimator", "Term",
    "block_cv", "block_folds", "cross_fitted", "block_ids", "cached_cell_stats", "cell_stats", "check_points",
    "default_bandwidths", "fit_kde_cv", "grid_kde", "log_kde_feature", "make_terms", "point_stats", "read_targets", "simplex_weights",
    "template_start", "with_features", "with_mixture", "with_model", "with_range", "with_selection",
]
