"""Sensor reports and true targets as files.

Reports: one row per report with columns ``x``, ``y`` (metres in the prior's CRS), ``time`` (seconds),
``cov_xx``, ``cov_xy``, ``cov_yy`` (m²) and optionally ``truth`` (integer target label), as CSV or a
vector file. In a vector file, ``x``/``y`` may be omitted when the layer has point geometries. Rows are
kept in file order: that order is the arrival order the tracker follows.

True targets (simulations): CSV with columns ``truth`` (the label reports carry), ``x``, ``y`` (metres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyogrio
import shapely
from pyogrio import raw

from common.atomic import atomic_paths
from common.tables import read_csv_table
from tracker.io.columns import COV_COLUMNS, cov_columns, covs_from_columns
from tracker.types.reports import Reports

REPORT_COLUMNS = ("x", "y", "time", *COV_COLUMNS)


def read_reports(path: str | Path, layer: str | None = None) -> tuple[Reports, str | None]:
    """Reports and the file's CRS (None for CSV). Raises ``ValueError`` naming the file and the missing
    columns or the offending rows (0-based, in file order)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        table, crs = read_csv_table(path, "reports"), None
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
    covs = covs_from_columns(values[:, 3], values[:, 4], values[:, 5])
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


def write_reports(path: str | Path, reports: Reports) -> Path:
    """Write reports as CSV (the columns :func:`read_reports` reads, plus ``truth``), atomically."""
    table = pd.DataFrame(
        {
            "x": reports.means[:, 0],
            "y": reports.means[:, 1],
            "time": reports.times,
            **cov_columns(reports.covs),
            "truth": reports.truth,
        }
    )
    with atomic_paths(path) as (tmp,):
        table.to_csv(tmp, index=False, float_format="%.17g")
    return Path(path)


def write_targets(path: str | Path, targets: np.ndarray) -> Path:
    """Write true target positions ``targets`` (T, 2) metres as CSV (``truth`` = row index, ``x``, ``y``), atomically."""
    targets = np.asarray(targets, dtype=np.float64)
    table = pd.DataFrame({"truth": np.arange(len(targets)), "x": targets[:, 0], "y": targets[:, 1]})
    with atomic_paths(path) as (tmp,):
        table.to_csv(tmp, index=False, float_format="%.17g")
    return Path(path)


def read_targets(path: str | Path) -> np.ndarray:
    """True target positions (T, 2) metres from a CSV written by :func:`write_targets` (columns ``x``, ``y``).
    Raises ``ValueError`` naming the file and what is missing or not numeric."""
    path = Path(path)
    table = read_csv_table(path, "true targets")
    missing = [c for c in ("x", "y") if c not in table.columns]
    if missing:
        raise ValueError(f"{path}: missing target columns {missing} (need ['x', 'y'])")
    try:
        xy = table[["x", "y"]].to_numpy(dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: target columns ['x', 'y'] must be numeric ({exc})") from exc
    bad = np.flatnonzero(~np.isfinite(xy).all(axis=1))
    if bad.size:
        raise ValueError(f"{path}: missing or non-finite x/y on data rows {bad[:10].tolist()} (0-based)")
    return xy
