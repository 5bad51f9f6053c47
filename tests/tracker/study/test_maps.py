"""terrain-track show --html: reports, estimated and true targets on the prior, checked against the
χ² ellipse and in headless Chromium offline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyogrio.raw
import pytest
import shapely
from pyproj import Transformer
from scipy.stats import chi2

from common.maps import VectorSource
from pipeline.prior import TerrainPrior
from tests.browser import geojson_layers, probe
from tracker.cli import main
from tracker.io.reports import write_reports, write_targets
from tracker.io.tracks import write_tracks
from tracker.study.maps import tracks_map
from tracker.types.estimate import Estimate
from tracker.types.reports import Reports

CRS = "EPSG:32734"
RNG = np.random.default_rng(7)
REPORTS = np.array([300500.0, 6186500.0]) + RNG.uniform(0, 1000, (5, 2))
TRACKS = REPORTS[:3] + 5.0
TRUTH = REPORTS[:4] - 5.0
COUNTS = np.array([2, 2, 1])


def _covs(n: int) -> np.ndarray:
    a = RNG.normal(0, 6, (n, 2, 2))
    return a @ a.transpose(0, 2, 1) + 25 * np.eye(2)


REPORT_COVS, TRACK_COVS = _covs(5), _covs(3)
ROADS = [[(300100.0, 6186100.0), (301000.0, 6186900.0), (301900.0, 6187900.0)], [(300100.0, 6187500.0), (301900.0, 6187500.0)]]
LAKE = [(301200.0, 6186200.0), (301700.0, 6186200.0), (301700.0, 6186700.0), (301200.0, 6186700.0)]
LAKE_CRS = "EPSG:32733"  # the lake is stored in the neighbouring UTM zone: the map must reproject from the file's CRS


@pytest.fixture(scope="module")
def region_gpkg(tmp_path_factory) -> Path:
    """A GeoPackage with layers ``roads`` (2 lines, EPSG:32734) and ``lakes`` (1 polygon, EPSG:32733)."""
    gpkg = tmp_path_factory.mktemp("vectors") / "region.gpkg"
    pyogrio.raw.write(gpkg, shapely.to_wkb(np.array([shapely.LineString(r) for r in ROADS])), [np.arange(2)], ["id"], layer="roads",
                      driver="GPKG", geometry_type="LineString", crs=CRS)
    lake = Transformer.from_crs(CRS, LAKE_CRS, always_xy=True).transform(*np.array(LAKE).T)
    pyogrio.raw.write(gpkg, shapely.to_wkb(np.array([shapely.Polygon(np.column_stack(lake))])), [np.arange(1)],
                      ["id"], layer="lakes", driver="GPKG", geometry_type="Polygon", crs=LAKE_CRS, append=True)
    return gpkg


@pytest.fixture(scope="module")
def prior() -> TerrainPrior:
    from pipeline.gis.grid import Grid

    grid = Grid.from_bounds((300000, 6186000, 302000, 6188000), 20.0, CRS)
    return TerrainPrior.from_array(np.ones(grid.shape), grid)


def test_ellipses_are_the_95_percent_contours_and_popups_carry_the_estimate(prior, tmp_path):
    probs = np.array([0.9, 0.75, 0.5])
    out = tracks_map(prior, REPORTS, REPORT_COVS, TRACKS, TRACK_COVS, COUNTS, targets=TRUTH,
                     assoc_probs=probs).save(tmp_path / "tracks.html")
    reports, tracks, truth = geojson_layers(out)
    assert [len(fc["features"]) for fc in (reports, tracks, truth)] == [5, 3, 4]
    back = Transformer.from_crs("EPSG:4326", CRS, always_xy=True)
    radius2 = chi2.ppf(0.95, 2)  # independent of ellipse_polygons' closed form
    for fc, means, covs in ((reports, REPORTS, REPORT_COVS), (tracks, TRACKS, TRACK_COVS)):
        for f, mean, cov in zip(fc["features"], means, covs, strict=True):
            ring = np.array(f["geometry"]["coordinates"][0])
            d = np.column_stack(back.transform(ring[:, 0], ring[:, 1])) - mean
            np.testing.assert_allclose(np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d), radius2, rtol=1e-6)
    props = [f["properties"] for f in tracks["features"]]
    assert [p["fused reports"] for p in props] == ["2", "2", "1"]
    assert [p["association probability"] for p in props] == ["0.900", "0.750", "0.500"]
    assert props[0]["covariance"].startswith(f"[[{TRACK_COVS[0, 0, 0]:.4g}, {TRACK_COVS[0, 0, 1]:.4g}]")
    np.testing.assert_allclose([f["geometry"]["coordinates"] for f in truth["features"]],
                               np.column_stack(Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(*TRUTH.T)),
                               atol=1e-9)


def test_vector_overlays_are_the_file_layers_in_lon_lat(prior, region_gpkg, tmp_path):
    vectors = [VectorSource.parse(f"{region_gpkg}:roads"), VectorSource.parse(f"{region_gpkg}:lakes=water")]
    out = tracks_map(prior, REPORTS, REPORT_COVS, TRACKS, TRACK_COVS, COUNTS, vectors=vectors).save(tmp_path / "m.html")
    roads, water, reports, tracks = geojson_layers(out)
    assert [len(fc["features"]) for fc in (roads, water, reports, tracks)] == [2, 1, 5, 3]
    to_ll = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True)
    for f, line in zip(roads["features"], ROADS, strict=True):
        assert f["geometry"]["type"] == "LineString"
        np.testing.assert_allclose(f["geometry"]["coordinates"], np.column_stack(to_ll.transform(*np.array(line).T)),
                                   atol=1e-9)
    # the lake's file coordinates are in EPSG:32733; back in EPSG:32734 they are the drawn ring (~1e-6 m)
    ring = np.array(water["features"][0]["geometry"]["coordinates"][0])
    back = np.column_stack(Transformer.from_crs("EPSG:4326", CRS, always_xy=True).transform(ring[:, 0], ring[:, 1]))
    np.testing.assert_allclose(back, np.array([*LAKE, LAKE[0]]), atol=1e-4)


@pytest.mark.parametrize(("text", "expected"), [
    ("a/region.gpkg", (Path("a/region.gpkg"), None, None, "region")),
    ("a/region.gpkg:lakes", (Path("a/region.gpkg"), "lakes", None, "lakes")),
    ("a/region.gpkg:lakes=water", (Path("a/region.gpkg"), "lakes", "water", "water")),
    ("roads.shp=main roads", (Path("roads.shp"), None, "main roads", "main roads")),
])
def test_vector_source_syntax(text, expected):
    v = VectorSource.parse(text)
    assert (v.path, v.layer, v.name, v.label) == expected


@pytest.mark.parametrize("text", ["", ":roads", "region.gpkg:", "region.gpkg:roads=", "=water"])
def test_vector_source_with_an_empty_part_is_refused(text):
    with pytest.raises(ValueError, match="PATH\\[:LAYER\\]\\[=NAME\\]"):
        VectorSource.parse(text)


@pytest.fixture(scope="module")
def show_inputs(prior, tmp_path_factory) -> list[str]:
    """``terrain-track show`` arguments for a prior, 5 reports, 3 tracks and 4 true targets (no output)."""
    d = tmp_path_factory.mktemp("show")
    prior_path = prior.write(d / "prior.tif")
    write_reports(d / "reports.csv", Reports.create(REPORTS, REPORT_COVS))
    write_targets(d / "targets.csv", TRUTH)
    estimate = Estimate(TRACKS, TRACK_COVS, np.zeros(3), COUNTS, True, np.full(3, -1))
    write_tracks(d / "tracks.gpkg", estimate, CRS)
    return ["show", "--prior", str(prior_path), "--reports", str(d / "reports.csv"), "--tracks",
            str(d / "tracks.gpkg"), "--truth", str(d / "targets.csv")]


@pytest.mark.parametrize(("vector", "message"), [
    ("{d}/missing.gpkg:roads", "{d}/missing.gpkg: vector file not found"),
    ("{gpkg}:rivers", "{gpkg}: no layer 'rivers'; the file has ['roads', 'lakes']"),
    ("{gpkg}", "{gpkg}: the file has layers ['roads', 'lakes']; name one (PATH:LAYER)"),
    ("{d}/reports.csv.txt", "{d}/reports.csv.txt: not a readable vector file"),
])
def test_cli_bad_vector_is_an_error_line_and_writes_nothing(show_inputs, region_gpkg, tmp_path, capsys, vector, message):
    d, gpkg = tmp_path, region_gpkg
    (d / "reports.csv.txt").write_text("not, a, vector\n")
    out = tmp_path / "tracks.html"
    args = [*show_inputs, "--html", str(out), "--vector", vector.format(d=d, gpkg=gpkg)]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert f"error: {message.format(d=d, gpkg=gpkg)}" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == [d / "reports.csv.txt"]


def test_cli_vector_syntax_is_a_usage_error(show_inputs, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*show_inputs, "--html", str(tmp_path / "m.html"), "--vector", "region.gpkg:"])
    assert exc.value.code == 2
    assert "argument --vector: 'region.gpkg:': expected PATH[:LAYER][=NAME] with no empty part" in capsys.readouterr().err


def test_cli_map_in_headless_chromium_offline(show_inputs, region_gpkg, tmp_path):
    out = tmp_path / "tracks.html"
    assert main([*show_inputs, "--html", str(out), "--vector", f"{region_gpkg}:roads",
                 "--vector", f"{region_gpkg}:lakes=water"]) == 0
    got = probe(Path(out), tmp_path)
    assert got["maps"] == 1
    assert [(o["name"], o.get("count")) for o in got["overlays"]] == [
        ("prior density", None), ("roads", 2), ("water", 1), ("reports (95% ellipses)", 5),
        ("estimated targets (95% ellipses)", 3), ("true targets", 4)]
    assert all(o["off_after_click"] and o["on_after_second_click"] for o in got["overlays"])
    assert got["paths"] == 2 + 1 + 5 + 3 + 4  # every line, polygon, ellipse and circle marker drawn as an SVG path
    assert got["errors"] == [] and got["console"] == [] and got["resources"] == []
