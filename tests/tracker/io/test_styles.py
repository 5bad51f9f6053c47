"""Default QGIS styles of the tracks GeoPackage: ``layer_styles`` rows as QGIS saves them, read back
through GDAL and sqlite; a failing style write leaves no tracks file."""

from __future__ import annotations

import sqlite3
import xml.etree.ElementTree as ET

import numpy as np
import pyogrio
import pytest
from pyogrio import raw

from tracker.io import tracks
from tracker.io.tracks import write_tracks
from tracker.types.estimate import Estimate

QGIS_COLUMNS = {
    "f_table_catalog", "f_table_schema", "f_table_name", "f_geometry_column", "styleName", "styleQML",
    "styleSLD", "useAsDefault", "description", "owner", "ui", "update_time",
}


def _estimate(n: int = 3) -> Estimate:
    means = np.column_stack([np.arange(n) * 100.0, np.arange(n) * -50.0])
    covs = np.tile(np.array([[400.0, 120.0], [120.0, 100.0]]), (n, 1, 1))
    return Estimate(means, covs, np.full(n, -18.0), np.arange(1, n + 1), True, np.full(n, -1))


def _styles(path) -> dict[str, dict]:
    with sqlite3.connect(path) as db:
        db.row_factory = sqlite3.Row
        rows = [dict(r) for r in db.execute("SELECT * FROM layer_styles")]
    return {r["f_table_name"]: r for r in rows}


@pytest.mark.parametrize("n", [0, 3])
def test_each_layer_has_a_default_style_as_qgis_saves_it(tmp_path, n):
    out = tmp_path / "tracks.gpkg"
    write_tracks(out, _estimate(n), "EPSG:32634")
    styles = _styles(out)
    assert set(styles) == {"targets", "ellipses"}
    with sqlite3.connect(out) as db:
        columns = {row[1] for row in db.execute("PRAGMA table_info(layer_styles)")}
        geometry = dict(db.execute("SELECT table_name, column_name FROM gpkg_geometry_columns"))
        kind = db.execute("SELECT data_type FROM gpkg_contents WHERE table_name = 'layer_styles'").fetchone()
    assert QGIS_COLUMNS <= columns
    assert kind == ("attributes",)  # registered, so GDAL (and QGIS through it) lists the table
    for name, row in styles.items():
        assert row["useAsDefault"] == 1
        assert row["f_geometry_column"] == geometry[name]
        assert row["update_time"]
        ET.fromstring(row["styleQML"].split("\n", 1)[1])  # parses (past the doctype line)
    # GDAL reads the table as a layer with one row per styled layer, and the data layers are intact
    assert "layer_styles" in pyogrio.list_layers(out)[:, 0]
    meta, _, _, data = raw.read(out, layer="layer_styles", read_geometry=False)
    table = dict(zip(meta["fields"], data, strict=True))
    assert sorted(table["f_table_name"]) == ["ellipses", "targets"]
    assert len(raw.read(out, layer="targets")[2]) == n


def test_ellipses_outlined_and_points_labelled_with_their_count(tmp_path):
    out = tmp_path / "tracks.gpkg"
    write_tracks(out, _estimate(), "EPSG:32634")
    styles = {k: ET.fromstring(v["styleQML"].split("\n", 1)[1]) for k, v in _styles(out).items()}

    ellipse = styles["ellipses"]
    assert ellipse.get("labelsEnabled") == "0" and ellipse.find("labeling") is None
    layer = ellipse.find("renderer-v2[@type='singleSymbol']/symbols/symbol[@type='fill']/layer")
    assert layer.get("class") == "SimpleFill"
    opts = {o.get("name"): o.get("value") for o in layer.iter("Option") if o.get("name")}
    assert opts["style"] == "no" and opts["outline_style"] == "solid" and float(opts["outline_width"]) > 0

    target = styles["targets"]
    assert target.get("labelsEnabled") == "1"
    assert target.find("renderer-v2/symbols/symbol[@type='marker']/layer").get("class") == "SimpleMarker"
    text = target.find("labeling[@type='simple']/settings/text-style")
    assert text.get("fieldName") == "count" and text.get("isExpression") == "0"
    fields = pyogrio.read_info(out, layer="targets")["fields"]
    assert "count" in fields  # the labelled field exists in the layer


def test_failing_style_write_leaves_no_tracks(tmp_path, monkeypatch):
    out = tmp_path / "tracks.gpkg"

    def broken() -> dict[str, str]:
        raise RuntimeError("style writer failed")

    monkeypatch.setattr(tracks, "track_styles", broken)
    with pytest.raises(RuntimeError, match="style writer failed"):
        write_tracks(out, _estimate(), "EPSG:32634")
    assert list(tmp_path.iterdir()) == []


def test_styling_a_missing_layer_is_named(tmp_path):
    out = tmp_path / "tracks.gpkg"
    write_tracks(out, _estimate(), "EPSG:32634")
    with pytest.raises(ValueError, match="no layer 'roads' to style"):
        tracks.write_layer_styles(out, {"roads": "<qgis/>"})
