"""Region config -> features -> prior, in memory, and the feature GeoTIFFs."""

from common.exports import lazy_exports

_EXPORTS = {
    "BuildMemoryError": "region",
    "UnusedFeatureWarning": "region",
    "available_memory_bytes": "region",
    "build_memory_bytes": "region",
    "check_memory": "region",
    "unused_features": "region",
    "build_features": "region",
    "build_prior": "region",
    "build_region_prior": "region",
    "region_model": "region",
    "region_provenance": "region",
    "write_features": "region",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
