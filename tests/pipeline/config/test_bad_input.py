"""Bad configs and likelihood files (issue 13): each gives an error naming the file, table and key, from the
API and as one ``error:`` line from the CLI with exit 1 and no traceback."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.cli import main
from pipeline.config.region import ConfigError, ConfigWarning, load_config, parse_config
from pipeline.gis.grid import Grid, GridError
from pipeline.prior.likelihood import LikelihoodError, LikelihoodModel
from tests.pipeline.gis_helpers import REGION_TOML, region_doc, write_config


def cli_error(capsys, *argv: str) -> str:
    """Run terrain-prior; assert one clean error line and exit 1; return it."""
    rc = main(["-q", *argv])
    err = capsys.readouterr().err
    assert rc == 1, err
    assert "terrain-prior: error:" in err and "Traceback" not in err
    return err


def both(tmp_path: Path, capsys, doc: dict | str | bytes, *needles: str) -> None:
    """The config fails to load naming ``needles``, and ``build`` prints them as an error line."""
    path = tmp_path / "bad.toml"
    if isinstance(doc, bytes):
        path.write_bytes(doc)
    elif isinstance(doc, str):
        path.write_text(doc)
    else:
        write_config(path, doc)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    for n in (str(path), *needles):
        assert n in str(info.value), str(info.value)
    err = cli_error(capsys, "build", str(path), "--out", str(tmp_path / "p.tif"))
    for n in (str(path), *needles):
        assert n in err
    assert not (tmp_path / "p.tif").exists()


def test_config_path_is_a_directory(tmp_path: Path, capsys) -> None:
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)
    assert str(tmp_path) in cli_error(capsys, "features", str(tmp_path), "--out", str(tmp_path / "f"))


def test_binary_config(tmp_path: Path, capsys) -> None:
    both(tmp_path, capsys, b"\x89PNG\r\n\x1a\n\xff\xfe\x00binary", "not a text TOML file", "UTF-8")


@pytest.mark.parametrize("bounds", [[0, 0, math.inf, 1000], [-math.inf, 0, 1000, 1000], [0, math.nan, 1000, 1000]])
def test_bounds_not_finite(tmp_path: Path, capsys, bounds) -> None:
    both(tmp_path, capsys, region_doc(bounds=bounds), "region.bounds", "finite")


def test_grid_bounds_not_finite_api() -> None:
    with pytest.raises(GridError, match="finite") as info:
        Grid.from_bounds((0, 0, math.inf, 10), 1.0, "EPSG:32734")
    assert info.value.key == "bounds"


@pytest.mark.parametrize(
    ("table", "value", "needles"),
    [
        ("water", {"type": "categorical", "values": [1.0, 0.0]}, ["[likelihood.water]", "values must be a table"]),
        ("water", {"type": "categorical", "values": "dry"}, ["[likelihood.water]", "values must be a table"]),
        ("water", "categorical", ["[likelihood.water]", "must be a table"]),
        ("water", [1, 0], ["[likelihood.water]", "must be a table"]),
        ("water", {"type": "categorical", "values": {"dry": "abc", "water": 0.0}}, ["[likelihood.water]", "values.dry must be a number, got 'abc'"]),
        ("water", {"type": "categorical", "values": {"dry": True, "water": 0.0}}, ["[likelihood.water]", "values.dry must be a number"]),
        ("water", {"type": "categorical", "values": {"dry": 1.0, "water": -0.5}}, ["[likelihood.water]", "values.water must be >= 0"]),
        ("water", {"type": "categorical", "values": {"dry": 1.0, "water": 0.0}, "nodata": -1.0}, ["[likelihood.water]", "nodata must be >= 0"]),
        ("water", {"type": "categorical", "values": {"dry": 1.0, "water": 0.0}, "colour": 1}, ["[likelihood.water]", "unknown keys ['colour']"]),
        ("water", {"type": "categorical"}, ["[likelihood.water]", "values is missing"]),
        ("road_distance", {"type": "road", "rmd": math.inf, "mv": 0.2}, ["[likelihood.road_distance]", "rmd must be > 0 and finite, got inf"]),
        ("road_distance", {"type": "road", "rmd": "abc", "mv": 0.2}, ["[likelihood.road_distance]", "rmd must be a number, got 'abc'"]),
        ("road_distance", {"type": "road", "rmd": 100.0, "mv": math.nan}, ["[likelihood.road_distance]", "mv must be > 0 and finite"]),
        ("road_distance", {"type": "road", "rmd": 100.0, "mv": 1.5}, ["[likelihood.road_distance]", "mv must be in (0, 1]"]),
        ("road_distance", {"type": "road", "rmd": 100.0, "mv": 0.2, "nodata": -2}, ["[likelihood.road_distance]", "nodata must be >= 0"]),
        ("road_distance", {"type": "road", "mv": 0.2}, ["[likelihood.road_distance]", "rmd is missing"]),
        ("road_distance", {"type": "binned", "edges": [0, "x"], "values": [1, 1]}, ["[likelihood.road_distance]", "edges must be"]),
        ("road_distance", {"type": "binned", "edges": [0, 100], "values": [1, math.inf]}, ["[likelihood.road_distance]", "values[1] must be >= 0 and finite"]),
        ("road_distance", {"type": "binned", "edges": [0, 100], "values": [1]}, ["[likelihood.road_distance]", "as many"]),
    ],
)
def test_bad_likelihood_table_names_file_table_and_key(tmp_path: Path, capsys, table, value, needles) -> None:
    doc = region_doc()
    doc["likelihood"][table] = value
    both(tmp_path, capsys, doc, *needles)
    # the same table in a --model file: the model file is named
    model = tmp_path / "model.toml"
    write_config(model, {"likelihood": {table: value}})
    with pytest.raises(LikelihoodError) as info:
        LikelihoodModel.read_toml(model)
    for n in (str(model), *needles):
        assert n in str(info.value)
    err = cli_error(capsys, "build", str(REGION_TOML), "--model", str(model), "--out", str(tmp_path / "p.tif"))
    for n in (str(model), *needles):
        assert n in err
    assert not (tmp_path / "p.tif").exists()


@pytest.mark.parametrize(("doc", "needle"), [
    (b"\xff\xfe[likelihood.water]", "not a text TOML file"),
    ('[likelihood.water]\ntype = "categorical"\nvalues = { dry = 1.0 }\n[meta]\n', None),
])
def test_model_file_binary_or_valid(tmp_path: Path, capsys, doc, needle) -> None:
    model = tmp_path / "m.toml"
    model.write_bytes(doc if isinstance(doc, bytes) else doc.encode())
    if needle is None:
        assert LikelihoodModel.read_toml(model).terms["water"].values == {"dry": 1.0}
        return
    err = cli_error(capsys, "build", str(REGION_TOML), "--model", str(model), "--out", str(tmp_path / "p.tif"))
    assert str(model) in err and needle in err


def test_road_table_on_a_categorical_feature_names_the_table(tmp_path: Path, capsys) -> None:
    """A table that does not fit its feature is found once features exist: the error names the table."""
    doc = region_doc()
    doc["likelihood"]["water"] = {"type": "road", "rmd": 100.0, "mv": 0.2}
    path = write_config(tmp_path / "r.toml", doc)
    err = cli_error(capsys, "build", str(path), "--out", str(tmp_path / "p.tif"))
    assert "[likelihood.water]" in err and "continuous distance" in err
    doc["likelihood"]["water"] = {"type": "categorical", "values": {"dry": 1.0, "lake": 0.0}}
    err = cli_error(capsys, "build", str(write_config(path, doc)), "--out", str(tmp_path / "p.tif"))
    assert "[likelihood.water]" in err and "'water'" in err and "has no likelihood" in err
    assert not (tmp_path / "p.tif").exists()


# ---- grid CRS ----------------------------------------------------------------------------------------

US_FT_UTM = "+proj=utm +zone=34 +south +datum=WGS84 +units=us-ft +no_defs"


@pytest.mark.parametrize("crs", [US_FT_UTM, "EPSG:2222", "EPSG:2277"])  # UTM in ftUS, Arizona (ft), Texas (ftUS)
def test_grid_crs_in_feet_is_refused(tmp_path: Path, capsys, crs: str) -> None:
    both(tmp_path, capsys, region_doc(crs=crs, bounds=[1_000_000, 1_000_000, 1_045_940, 1_045_940]),
         "region.crs", "not metres", "foot")


def test_utm_in_metres_accepted_without_warning() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConfigWarning)
        cfg = parse_config(region_doc(), REGION_TOML)
    assert abs(cfg.grid.scale_factor() - 1) < 1e-3


@settings(max_examples=15, deadline=None)
@given(lat=st.floats(-75.0, 75.0), lon=st.floats(-170.0, 170.0))
def test_web_mercator_warns_with_the_scale_factor_at_the_centre(lat: float, lon: float) -> None:
    """Oracle: Web Mercator's point scale is 1/cos φ (its sphere); warned whenever it differs from 1 by > 1 %."""
    from pyproj import Transformer

    x, y = Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(lon, lat)
    doc = region_doc(crs="EPSG:3857", bounds=[x - 5000, y - 5000, x + 5000, y + 5000])
    k = 1 / math.cos(math.radians(lat))
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cfg = parse_config(doc, Path("/cfg/r.toml"))
    assert cfg.grid.scale_factor() == pytest.approx(k, rel=1e-9)
    ours = [w for w in record if issubclass(w.category, ConfigWarning)]
    if k - 1 <= 0.01:
        assert not ours
        return
    msg = str(ours[0].message)
    assert "/cfg/r.toml" in msg and "region.crs" in msg and "Pseudo-Mercator" in msg
    assert f"scale factor of {k:.4g}" in msg and f"latitude {lat:.2f}" in msg and 'crs = "utm"' in msg


def test_web_mercator_at_london_warns_from_the_cli(tmp_path: Path, capsys) -> None:
    from pyproj import Transformer

    x, y = Transformer.from_crs("EPSG:4326", "EPSG:3857", always_xy=True).transform(-0.12, 51.5)
    doc = region_doc(crs="EPSG:3857", bounds=[x - 1000, y - 1000, x + 1000, y + 1000])
    with pytest.warns(ConfigWarning, match=r"scale factor of 1\.606"):
        load_config(write_config(tmp_path / "london.toml", doc))


# ---- layer where filters -------------------------------------------------------------------------

@pytest.mark.parametrize(("where", "needle"), [
    ("1=1; DROP TABLE roads", "';' at character 4"),
    ("highway = 'primary';", "';' at character 20"),
    ("1=1 -- and highway = 'x'", "SQL comment '--'"),
    ("1=1 /* x */", "SQL comment '/*'"),
    ("highway = 'primary", "unclosed ' quote"),
    ("  ", "empty filter"),
])
def test_where_must_be_one_expression(tmp_path: Path, capsys, where: str, needle: str) -> None:
    doc = region_doc()
    doc["layers"]["roads"]["where"] = where
    both(tmp_path, capsys, doc, "layers.roads.where", needle, "one SQL expression")


def test_where_with_semicolon_inside_a_literal_is_one_expression(tmp_path: Path) -> None:
    """A ';' or '--' inside quotes is text, not a separator: accepted and passed to OGR whole."""
    from pipeline.gis.layers import read_vector

    doc = region_doc()
    doc["layers"]["roads"]["where"] = "highway IN ('primary', 'a;b', 'c--d', 'it''s')"
    cfg = parse_config(doc, tmp_path / "r.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        n = read_vector(cfg.layers["roads"], cfg.grid).geometries.size
        doc["layers"]["roads"]["where"] = "highway = 'primary'"
        assert n == read_vector(parse_config(doc, tmp_path / "r.toml").layers["roads"], cfg.grid).geometries.size > 0


def test_layer_spec_checks_where_itself() -> None:
    from pipeline.gis.layers import LayerError, LayerSpec

    with pytest.raises(LayerError, match=r"roads\.gpkg \(\[layers\.roads\]\): where = '1=1; DROP TABLE roads'"):
        LayerSpec("roads", Path("roads.gpkg"), "vector", where="1=1; DROP TABLE roads")
