"""terrain-track show --html: reports, estimated and true targets on the prior, checked against the
χ² ellipse and in headless Chromium offline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer
from scipy.stats import chi2

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


def test_cli_map_in_headless_chromium_offline(prior, tmp_path):
    prior_path = prior.write(tmp_path / "prior.tif")
    write_reports(tmp_path / "reports.csv", Reports.create(REPORTS, REPORT_COVS))
    write_targets(tmp_path / "targets.csv", TRUTH)
    estimate = Estimate(TRACKS, TRACK_COVS, np.zeros(3), COUNTS, True, np.full(3, -1))
    write_tracks(tmp_path / "tracks.gpkg", estimate, CRS)
    out = tmp_path / "tracks.html"
    assert main(["show", "--prior", str(prior_path), "--reports", str(tmp_path / "reports.csv"), "--tracks",
                 str(tmp_path / "tracks.gpkg"), "--truth", str(tmp_path / "targets.csv"), "--html", str(out)]) == 0
    got = probe(Path(out), tmp_path)
    assert got["maps"] == 1
    assert [(o["name"], o.get("count")) for o in got["overlays"]] == [
        ("prior density", None), ("reports (95% ellipses)", 5), ("estimated targets (95% ellipses)", 3), ("true targets", 4)]
    assert all(o["off_after_click"] and o["on_after_second_click"] for o in got["overlays"])
    assert got["paths"] == 5 + 3 + 4  # every ellipse and circle marker drawn as an SVG path
    assert got["errors"] == [] and got["console"] == [] and got["resources"] == []
