"""Maps of priors and feature stacks: PNG (matplotlib loads on first use) and interactive HTML (folium)."""

from common.exports import lazy_exports

_EXPORTS = {
    "add_region_layers": "html",
    "prior_map": "html",
    "write_prior_html": "html",
    "plot_features": "plots",
    "plot_prior": "plots",
    "road_water_obstacles": "plots",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
