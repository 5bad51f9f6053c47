"""Read sensor reports from CSV or GeoPackage and write estimated targets with covariance ellipses.

Reports: one row per report with columns ``x``, ``y`` (metres in the prior's CRS), ``time`` (seconds),
``cov_xx``, ``cov_xy``, ``cov_yy`` (m²) and optionally ``truth`` (integer target label). In a
GeoPackage, ``x``/``y`` may be omitted when the layer has point geometries. Rows are kept in file order:
that order is the arrival order the tracker follows.

Tracks: a GeoPackage with layer ``targets`` (one point per hypothesis at the mean of its Gaussian part)
and layer ``ellipses`` (the polygon of that Gaussian's ``ellipse_prob`` contour), both carrying the
mean, covariance, number of fused reports and ln c (the normaliser against the prior; the reported
density is exp(-ln c) G(y; mean, cov) r(y) when ``terrain`` is 1, the Gaussian alone otherwise).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pyogrio
import shapely
from pyogrio import raw
from rasterio.crs import CRS

from common.atomic import atomic_paths
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import AssociationResult, Estimate, associate
from tracker.models.motion import MotionModel
from tracker.models.sfunc import ExpS, SModel
from tracker.types.reports import Reports

REPORT_COLUMNS = ("x", "y", "time", "cov_xx", "cov_xy", "cov_yy")
ELLIPSE_VERTICES = 64


def read_reports(path: str | Path, layer: str | None = None) -> tuple[Reports, str | None]:
    """Reports and the file's CRS (None for CSV). Raises ``ValueError`` naming the file and the missing
    columns or the offending rows (0-based, in file order)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        table, crs = pd.read_csv(path), None
    elif suffix in (".gpkg", ".geojson", ".json", ".shp", ".fgb"):
        table, crs = _read_vector(path, layer)
    else:
        raise ValueError(f"{path}: reports must be .csv or a vector file (.gpkg, .geojson, .shp, .fgb)")
    missing = [c for c in REPORT_COLUMNS if c not in table.columns]
    if missing:
        raise ValueError(f"{path}: missing report columns {missing} (need {list(REPORT_COLUMNS)})")
    try:
        values = table[list(REPORT_COLUMNS)].to_numpy(dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: report columns {list(REPORT_COLUMNS)} must be numeric ({exc})") from exc
    covs = np.empty((len(table), 2, 2))
    covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 0], covs[:, 1, 1] = values[:, 3], values[:, 4], values[:, 4], values[:, 5]
    truth = None
    if "truth" in table.columns:
        t = table["truth"].to_numpy()
        if not np.all(np.isfinite(t.astype(float))) or np.any(t.astype(float) % 1 != 0):
            raise ValueError(f"{path}: column truth must hold integers")
        truth = t.astype(np.int64)
    try:
        reports = Reports.create(values[:, :2], covs, values[:, 2], truth)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc} (indices are 0-based data rows)") from exc
    return reports, crs


def _read_vector(path: Path, layer: str | None) -> tuple[pd.DataFrame, str | None]:
    try:
        meta, _, geometry, field_data = raw.read(path, layer=layer)
    except pyogrio.errors.DataSourceError as exc:
        raise ValueError(f"{path}: cannot read ({exc})") from exc
    except pyogrio.errors.DataLayerError as exc:
        raise ValueError(f"{path}: layer {layer!r}: {exc}") from exc
    table = pd.DataFrame({name: col for name, col in zip(meta["fields"], field_data, strict=True)})
    if ("x" not in table.columns or "y" not in table.columns) and geometry is not None:
        pts = shapely.from_wkb(geometry)
        if not np.all(shapely.get_type_id(pts) == 0):
            raise ValueError(f"{path}: geometries must be points when the x and y columns are absent")
        table["x"], table["y"] = shapely.get_x(pts), shapely.get_y(pts)
    return table, meta.get("crs")


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
    fields = ["id", "x", "y", "cov_xx", "cov_xy", "cov_yy", "count", "log_c", "terrain", "label"]
    data = [
        np.arange(n, dtype=np.int64),
        estimate.means[:, 0],
        estimate.means[:, 1],
        estimate.covs[:, 0, 0],
        estimate.covs[:, 0, 1],
        estimate.covs[:, 1, 1],
        np.asarray(estimate.counts, dtype=np.int64),
        np.asarray(estimate.log_c, dtype=np.float64),
        np.full(n, int(estimate.terrain), dtype=np.int64),
        np.asarray(estimate.labels, dtype=np.int64),
    ]
    points = shapely.to_wkb(shapely.points(estimate.means)) if n else np.zeros(0, dtype=object)
    polys = shapely.to_wkb(ellipse_polygons(estimate.means, estimate.covs, ellipse_prob)) if n else np.zeros(0, dtype=object)
    with atomic_paths(path) as (tmp,):
        raw.write(tmp, points, data, fields, layer="targets", driver="GPKG", geometry_type="Point", crs=crs)
        raw.write(tmp, polys, data, fields, layer="ellipses", driver="GPKG", geometry_type="Polygon", crs=crs, append=True)
    return path


def track_files(
    prior_path: str | Path,
    reports_path: str | Path,
    out: str | Path,
    variant: str = "TT",
    s_model: SModel | None = None,
    motion: MotionModel | None = None,
    layer: str | None = None,
    ellipse_prob: float = 0.95,
    assignments_csv: str | Path | None = None,
    **tracker_kwargs,
) -> AssociationResult:
    """``terrain-track run``: read the prior and the reports, associate in file order, write the tracks
    (and, optionally, the hypothesis index of every report as CSV). A reports file with a CRS must use
    the prior's."""
    prior = TerrainPrior.read(prior_path)
    reports, crs = read_reports(reports_path, layer)
    if crs is not None and CRS.from_user_input(crs) != prior.grid.crs:
        raise ValueError(
            f"{reports_path}: CRS {crs} differs from the prior's {prior.grid.crs.to_string()}; reproject the reports"
        )
    result = associate(prior, reports, variant, s_model=s_model or ExpS(-1.7), motion=motion, **tracker_kwargs)
    write_tracks(out, result.estimate, prior.grid.crs.to_wkt(), ellipse_prob)
    if assignments_csv is not None:
        with atomic_paths(assignments_csv) as (tmp,):
            pd.DataFrame({"report": np.arange(len(reports)), "hypothesis": result.assignments}).to_csv(tmp, index=False)
    return result


def write_reports(path: str | Path, reports: Reports) -> Path:
    """Write reports as CSV (the columns :func:`read_reports` reads, plus ``truth``), atomically."""
    table = pd.DataFrame(
        {
            "x": reports.means[:, 0],
            "y": reports.means[:, 1],
            "time": reports.times,
            "cov_xx": reports.covs[:, 0, 0],
            "cov_xy": reports.covs[:, 0, 1],
            "cov_yy": reports.covs[:, 1, 1],
            "truth": reports.truth,
        }
    )
    with atomic_paths(path) as (tmp,):
        table.to_csv(tmp, index=False, float_format="%.17g")
    return Path(path)


def read_tracks(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means (Q, 2), covariances (Q, 2, 2) and report counts (Q,) from a tracks GeoPackage."""
    path = Path(path)
    try:
        meta, _, _, field_data = raw.read(path, layer="targets", read_geometry=False)
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError) as exc:
        raise ValueError(f"{path}: cannot read layer 'targets' of a tracks file ({exc})") from exc
    table = dict(zip(meta["fields"], field_data, strict=True))
    means = np.column_stack([table["x"], table["y"]]).astype(np.float64)
    covs = np.empty((means.shape[0], 2, 2))
    covs[:, 0, 0], covs[:, 0, 1] = table["cov_xx"], table["cov_xy"]
    covs[:, 1, 0], covs[:, 1, 1] = table["cov_xy"], table["cov_yy"]
    return means, covs, np.asarray(table["count"], dtype=np.int64)
