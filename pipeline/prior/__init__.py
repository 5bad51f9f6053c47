"""The prior the tracker reads: likelihood tables, the normalised density with its summed-area tables, its files and QGIS styles."""

from common.exports import lazy_exports

_EXPORTS = {
    "BinnedLikelihood": "likelihood",
    "CategoricalLikelihood": "likelihood",
    "Likelihood": "likelihood",
    "LikelihoodError": "likelihood",
    "LikelihoodModel": "likelihood",
    "RoadDistanceLikelihood": "likelihood",
    "likelihood_from_dict": "likelihood",
    "road_likelihood": "likelihood",
    "DENSITY_TOL": "terrain",
    "PriorError": "terrain",
    "TerrainPrior": "terrain",
    "density_table_rows": "terrain",
    "table_rows": "terrain",
    "sat_integral": "terrain",
    "sat_rect": "terrain",
    "PALETTE": "style",
    "QGIS_VERSION": "style",
    "VIRIDIS": "style",
    "paletted_qml": "style",
    "prior_qml": "style",
    "pseudocolor_qml": "style",
    "qml_document": "style",
    "style_path": "style",
    "STYLE_SAMPLE_EDGE": "write",
    "cog_writer": "write",
    "BUILD_TAG": "write",
    "TABLE_TAGS": "write",
    "build_tags": "write",
    "geotiff_profile": "write",
    "prior_tags": "write",
    "sat_paths": "write",
    "table_hash": "write",
    "write_prior": "write",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
