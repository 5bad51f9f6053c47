"""Estimated targets as a GeoPackage with covariance ellipses, and report assignments as CSV.

Tracks: a GeoPackage with layer ``targets`` (one point per hypothesis at the mean of its Gaussian part)
and layer ``ellipses`` (the polygon of that Gaussian's ``ellipse_prob`` contour), both carrying the
mean, covariance (``cov_xx``, ``cov_xy``, ``cov_yy``, m²), number of fused reports and ln c (the
normaliser against the prior; the reported density is exp(-ln c) G(y; mean, cov) r(y) when ``terrain``
is 1, the Gaussian alone otherwise).

Both layers carry a default QGIS style in the GeoPackage's ``layer_styles`` table (as QGIS saves
one): ellipses outlined and unfilled, targets as dots labelled with their report count.

Assignments: CSV with columns ``report`` (0-based row of the reports file) and ``hypothesis`` (index of
the target it was fused into, the ``id`` of its row in the tracks; -1 skipped). The batch method adds
``membership``: the report's posterior probability of belonging to that target (1 in map mode, empty
where skipped). Greedy has no posterior, so its file has no such column (it is not a probability 1).
"""

from __future__ import annotations

import contextlib
import math
import sqlite3
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pyogrio
import shapely
from pyogrio import raw

from common.atomic import atomic_paths
from pipeline.prior import QGIS_VERSION, qml_document
from tracker.io.columns import COV_COLUMNS, cov_columns, covs_from_columns
from tracker.types.estimate import Estimate

ELLIPSE_VERTICES = 64
TRACK_COLOUR = "228,26,28,255"
"""QGIS r,g,b,a colour of the tracks' dots and ellipse outlines."""


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


def _symbol_qml(kind: str, layer_class: str, options: dict[str, str], label_field: str | None = None) -> str:
    """QML of a single-symbol vector style: one ``layer_class`` symbol layer of ``kind`` (marker, fill)
    with ``options``; ``label_field``: features labelled with that field."""
    root = ET.Element("qgis", version=QGIS_VERSION, styleCategories="Symbology|Labeling",
                      labelsEnabled="1" if label_field else "0")
    renderer = ET.SubElement(root, "renderer-v2", type="singleSymbol", forceraster="0", symbollevels="0", enableorderby="0")
    symbol = ET.SubElement(ET.SubElement(renderer, "symbols"), "symbol", type=kind, name="0", alpha="1",
                           clip_to_extent="1", force_rhr="0")
    layer = ET.SubElement(symbol, "layer", {"class": layer_class, "enabled": "1", "pass": "0", "locked": "0"})
    option_map = ET.SubElement(layer, "Option", type="Map")
    for name, value in options.items():
        ET.SubElement(option_map, "Option", type="QString", name=name, value=value)
    if label_field:
        settings = ET.SubElement(ET.SubElement(root, "labeling", type="simple"), "settings", calloutType="simple")
        ET.SubElement(settings, "text-style", fieldName=label_field, isExpression="0", fontFamily="Sans Serif",
                      fontSize="9", fontSizeUnit="Point", textColor="0,0,0,255", textOpacity="1")
        ET.SubElement(settings, "text-buffer", bufferDraw="1", bufferSize="1", bufferSizeUnits="MM",
                      bufferColor="255,255,255,255", bufferOpacity="1")
        # placement 1: around the point, 1.5 mm off it
        ET.SubElement(settings, "placement", placement="1", dist="1.5", distUnits="MM")
        ET.SubElement(settings, "rendering", drawLabels="1", obstacle="1")
    return qml_document(root)


def track_styles() -> dict[str, str]:
    """QML of each tracks layer: ``targets`` dots labelled with ``count``, ``ellipses`` outlined and unfilled."""
    return {
        "targets": _symbol_qml("marker", "SimpleMarker", {
            "name": "circle", "color": TRACK_COLOUR, "outline_color": "35,35,35,255", "outline_style": "solid",
            "outline_width": "0.2", "outline_width_unit": "MM", "size": "2", "size_unit": "MM"}, label_field="count"),
        "ellipses": _symbol_qml("fill", "SimpleFill", {
            "style": "no", "color": "0,0,0,0", "outline_color": TRACK_COLOUR, "outline_style": "solid",
            "outline_width": "0.5", "outline_width_unit": "MM", "joinstyle": "round"}),
    }


_LAYER_STYLES = """CREATE TABLE IF NOT EXISTS layer_styles (
    id INTEGER PRIMARY KEY AUTOINCREMENT, f_table_catalog TEXT(256), f_table_schema TEXT(256),
    f_table_name TEXT(256), f_geometry_column TEXT(256), styleName TEXT(30), styleQML TEXT, styleSLD TEXT,
    useAsDefault BOOLEAN, description TEXT, owner TEXT(30), ui TEXT(30),
    update_time DATETIME DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')))"""


def write_layer_styles(path: str | Path, styles: dict[str, str]) -> None:
    """Store ``styles`` (layer name -> QML) as the default styles of a GeoPackage's layers, in its
    ``layer_styles`` table registered as an attributes table, the way QGIS saves a style to a GeoPackage."""
    with contextlib.closing(sqlite3.connect(path)) as db, db:  # closed, and committed only if all succeeds
        geometry_columns = dict(db.execute("SELECT table_name, column_name FROM gpkg_geometry_columns"))
        missing = sorted(set(styles) - set(geometry_columns))
        if missing:
            raise ValueError(f"{path}: no layer {missing[0]!r} to style")
        db.execute(_LAYER_STYLES)
        db.execute("INSERT OR IGNORE INTO gpkg_contents (table_name, data_type, identifier) "
                   "VALUES ('layer_styles', 'attributes', 'layer_styles')")
        db.executemany(
            "INSERT INTO layer_styles (f_table_catalog, f_table_schema, f_table_name, f_geometry_column, styleName, "
            "styleQML, styleSLD, useAsDefault, description, owner, ui) VALUES ('', '', ?, ?, ?, ?, '', 1, ?, '', '')",
            [(name, geometry_columns[name], name, qml, f"default style of {name}") for name, qml in styles.items()],
        )
        # GDAL keeps feature counts in gpkg_ogr_contents when it exists
        if db.execute("SELECT 1 FROM sqlite_master WHERE name = 'gpkg_ogr_contents'").fetchone():
            db.execute("INSERT OR REPLACE INTO gpkg_ogr_contents (table_name, feature_count) "
                       "SELECT 'layer_styles', COUNT(*) FROM layer_styles")


def write_tracks(path: str | Path, estimate: Estimate, crs: str | None, ellipse_prob: float = 0.95) -> Path:
    """Write layers ``targets`` (points) and ``ellipses`` (polygons) with their default QGIS styles
    (:func:`track_styles`) to a GeoPackage, atomically."""
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
        write_layer_styles(tmp, track_styles())
    return path


def write_assignments(path: str | Path, assignments: np.ndarray, membership: np.ndarray | None = None) -> Path:
    """Write the hypothesis index of every report (``assignments`` (K,), -1 skipped) and, if given, its
    ``membership`` probability (K,) (NaN: empty) as CSV, atomically."""
    table = {"report": np.arange(len(assignments)), "hypothesis": assignments}
    if membership is not None:
        table["membership"] = membership
    with atomic_paths(path) as (tmp,):
        pd.DataFrame(table).to_csv(tmp, index=False)
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
