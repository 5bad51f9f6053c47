"""Helpers shared by the pipeline and the tracker: atomic output commits, the Dask client, lazy package exports."""

from common.exports import lazy_exports

_EXPORTS = {
    "atomic_paths": "atomic",
    "remove_stale_temps": "atomic",
    "scratch_dir": "atomic",
    "get_client": "dask",
    "using_client": "dask",
    "lazy_exports": "exports",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
