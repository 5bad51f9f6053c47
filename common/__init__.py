"""Helpers shared by the pipeline and the tracker: atomic output commits and the Dask client."""
