"""Helpers shared by the pipeline and the tracker: atomic output commits, the Dask client, lazy package exports,
the interactive map builder."""

from common.exports import lazy_exports

_EXPORTS = {
    "atomic_paths": "atomic",
    "get_client": "dask",
    "using_client": "dask",
    "lazy_exports": "exports",
    "LeafletMap": "maps",
    "covariance_popup": "maps",
    "density_map": "maps",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
