"""Maps of priors and feature stacks (matplotlib loads on first use)."""

from common.exports import lazy_exports

_EXPORTS = {
    "plot_features": "plots",
    "plot_prior": "plots",
    "road_water_obstacles": "plots",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
