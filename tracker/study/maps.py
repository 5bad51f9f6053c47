"""Reports, estimated targets and true targets over the prior as an interactive, self-contained HTML map
(Leaflet via folium, the map builder of :mod:`common.maps` that the pipeline's prior map uses too)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from common.maps import LeafletMap, VectorSource, covariance_popup, density_map
from pipeline.prior import TerrainPrior
from tracker.io.tracks import ellipse_polygons

COLOURS = {"reports": "#ff7f0e", "tracks": "#d62ad6", "truth": "#d62728"}


def tracks_map(
    prior: TerrainPrior,
    report_means: np.ndarray,
    report_covs: np.ndarray,
    track_means: np.ndarray,
    track_covs: np.ndarray,
    track_counts: np.ndarray,
    targets: np.ndarray | None = None,
    assoc_probs: np.ndarray | None = None,
    ellipse_prob: float = 0.95,
    basemap: str | None = None,
    vectors: Sequence[VectorSource] = (),
) -> LeafletMap:
    """The prior with the reports' and the estimated targets' ``ellipse_prob`` ellipses (means (N, 2) m and
    covariances (N, 2, 2) m² in the prior's CRS) and, for simulations, the true targets (M, 2) m.
    ``vectors``: layers of vector files (roads, water) drawn over the prior, each its own overlay.

    Popups: covariance, reports fused into each target (``track_counts``), and each target's posterior
    association probability when the associator provides one (``assoc_probs`` (Q,))."""
    m = density_map(prior.density, prior.grid.transform, prior.grid.crs, basemap=basemap)
    for v in vectors:
        m.add_vector_file(v.path, v.layer, v.label)
    report_means, track_means = np.reshape(report_means, (-1, 2)), np.reshape(track_means, (-1, 2))
    report_covs, track_covs = np.reshape(report_covs, (-1, 2, 2)), np.reshape(track_covs, (-1, 2, 2))
    pct = f"{ellipse_prob:.0%}"
    if len(report_means):
        popups = [{"report": str(k), "covariance": covariance_popup(c)} for k, c in enumerate(report_covs)]
        m.add_shapes(f"reports ({pct} ellipses)", ellipse_polygons(report_means, report_covs, ellipse_prob),
                     COLOURS["reports"], popups, weight=1.0)
    if len(track_means):
        popups = [{"target": str(q), "fused reports": str(int(n)), "covariance": covariance_popup(c)}
                  for q, (c, n) in enumerate(zip(track_covs, track_counts, strict=True))]
        if assoc_probs is not None:
            for p, prob in zip(popups, np.asarray(assoc_probs, dtype=np.float64), strict=True):
                p["association probability"] = f"{prob:.3f}"
        m.add_shapes(f"estimated targets ({pct} ellipses)", ellipse_polygons(track_means, track_covs, ellipse_prob),
                     COLOURS["tracks"], popups, weight=2.0)
    if targets is not None and len(targets):
        targets = np.reshape(targets, (-1, 2))
        m.add_points("true targets", targets, COLOURS["truth"],
                     [{"true target": str(j), "x, y (m)": f"{x:.1f}, {y:.1f}"} for j, (x, y) in enumerate(targets)])
    return m

