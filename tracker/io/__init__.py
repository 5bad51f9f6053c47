"""File formats of the tracker: reports and true targets in (:mod:`tracker.io.reports`), tracks (with
their QGIS styles) and assignments out (:mod:`tracker.io.tracks`), and the covariance columns they share (:mod:`tracker.io.columns`)."""

from tracker.io.columns import COV_COLUMNS, cov_columns, covs_from_columns
from tracker.io.reports import (
    REPORT_COLUMNS,
    read_reports,
    read_targets,
    write_reports,
    write_targets,
)
from tracker.io.tracks import (
    ELLIPSE_VERTICES,
    TRACK_COLOUR,
    ellipse_polygons,
    read_tracks,
    track_styles,
    write_assignments,
    write_layer_styles,
    write_tracks,
)

__all__ = [
    "COV_COLUMNS",
    "ELLIPSE_VERTICES",
    "REPORT_COLUMNS",
    "TRACK_COLOUR",
    "cov_columns",
    "covs_from_columns",
    "ellipse_polygons",
    "read_reports",
    "read_targets",
    "read_tracks",
    "track_styles",
    "write_assignments",
    "write_layer_styles",
    "write_reports",
    "write_targets",
    "write_tracks",
]
