"""Feature grids on a Grid: the stack, rasterised masks and categories, distances, slope."""

from common.exports import lazy_exports

_EXPORTS = {
    "Feature": "stack",
    "FeatureStack": "stack",
    "distance_m": "distance",
    "line_ends": "rasterize",
    "slope_classes": "slope",
    "slope_deg": "slope",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
