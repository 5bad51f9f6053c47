"""Estimated targets as a GeoPackage with covariance ellipses, and report assignments as CSV.

Tracks: a GeoPackage with layer ``targets`` (one point per hypothesis at the mean of its Gaussian part)
and layer ``ellipses`` (the polygon of that Gaussian's ``ellipse_prob`` contour), both carrying the
mean, covariance (``cov_xx``, ``cov_xy``, ``cov_yy``, m²), number of fused reports and ln c (the
normaliser against the prior; the reported density is exp(-ln c) G(y; mean, cov) r(y) when ``terrain``
is 1, the Gaussian alone otherwise).

Assignments: CSV with columns ``report`` (0-based row of the reports file) and ``hypothesis`` (index of
the target it was fused into; -1 skipped).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pyogrio
import shapely
from pyogrio import raw

from common.atomic import atomic_paths
from tracker.io.columns import COV_COLUMNS, cov_columns, covs_from_columns
from tracker.types.estimate import Estimate

ELLIPSE_VERTICES = 64


def ellipse_polygons(means: np.ndarray, covs: np.ndarray, prob: float = 0.95) -> np.ndarray:
    """Shapely polygons of the ``prob`` contours of 2-D Gaussians (Mahalanobis radius √(-2 ln(1-prob)))."""
    if not 0 < prob < 1:
        raise ValueError(f"ellipse_prob must lie in (0, 1), got {prob}")
    radius = math.sqrt(-2.0 * math.log1p(-prob))
    theta = np.linspace(0.0, 2.0 * np.pi, ELLIPSE_VERTICES, endpoint=False)
    circle = np.stack([np.cos(theta), np.sin(theta)], axis=1) * radius
    chol = np.linalg.cholesky(covs)
    rings = means[:, None, :] + np.einsum("nij,vj->nvi", chol, circle)
    rings = np.concatenate([rings, rings[:, :1]], axis=1)
    return shapely.polygons(rings)


def write_tracks(path: str | Path, estimate: Estimate, crs: str | None, ellipse_prob: float = 0.95) -> Path:
    """Write layers ``targets`` (points) and ``ellipses`` (polygons) to a GeoPackage, atomically."""
    path = Path(path)
    n = estimate.means.shape[0]
    columns = {
        "id": np.arange(n, dtype=np.int64),
        "x": estimate.means[:, 0],
        "y": estimate.means[:, 1],
        **cov_columns(estimate.covs),
        "count": np.asarray(estimate.counts, dtype=np.int64),
        "log_c": np.asarray(estimate.log_c, dtype=np.float64),
        "terrain": np.full(n, int(estimate.terrain), dtype=np.int64),
        "label": np.asarray(estimate.labels, dtype=np.int64),
    }
    fields, data = list(columns), list(columns.values())
    points = shapely.to_wkb(shapely.points(estimate.means)) if n else np.zeros(0, dtype=object)
    polys = shapely.to_wkb(ellipse_polygons(estimate.means, estimate.covs, ellipse_prob)) if n else np.zeros(0, dtype=object)
    with atomic_paths(path) as (tmp,):
        raw.write(tmp, points, data, fields, layer="targets", driver="GPKG", geometry_type="Point", crs=crs)
        raw.write(tmp, polys, data, fields, layer="ellipses", driver="GPKG", geometry_type="Polygon", crs=crs, append=True)
    return path


def write_assignments(path: str | Path, assignments: np.ndarray) -> Path:
    """Write the hypothesis index of every report (``assignments`` (K,), -1 skipped) as CSV, atomically."""
    with atomic_paths(path) as (tmp,):
        pd.DataFrame({"report": np.arange(len(assignments)), "hypothesis": assignments}).to_csv(tmp, index=False)
    return Path(path)


def read_tracks(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means (Q, 2), covariances (Q, 2, 2) and report counts (Q,) from a tracks GeoPackage."""
    path = Path(path)
    try:
        meta, _, _, field_data = raw.read(path, layer="targets", read_geometry=False)
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError) as exc:
        raise ValueError(f"{path}: cannot read layer 'targets' of a tracks file ({exc})") from exc
    table = dict(zip(meta["fields"], field_data, strict=True))
    missing = [c for c in ("x", "y", *COV_COLUMNS, "count") if c not in table]
    if missing:
        raise ValueError(f"{path}: layer 'targets' lacks columns {missing}; is it a tracks file of terrain-track run?")
    means = np.column_stack([table["x"], table["y"]]).astype(np.float64)
    covs = covs_from_columns(*(table[c] for c in COV_COLUMNS))
    return means, covs, np.asarray(table["count"], dtype=np.int64)
