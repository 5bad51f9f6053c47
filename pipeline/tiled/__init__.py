"""The tiled (Dask) prior build and learning passes (dask loads on first use)."""

from common.exports import lazy_exports

_EXPORTS = {
    "build_prior_tiled": "build",
    "DEFAULT_TILE": "windows",
    "TiledBuildError": "windows",
    "distance_caps": "windows",
    "feature_halos": "windows",
    "halo_window": "windows",
    "needed_features": "windows",
    "tile_windows": "windows",
    "tile_features": "tiles",
    "NpyRows": "store",
    "filtered_vector_layer": "vrt",
    "windowed_raster_layer": "vrt",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
