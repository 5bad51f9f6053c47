"""``terrain-track simulate`` and ``show``: files equal the library's output, round trips are exact."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import associate
from tracker.cli import main
from tracker.io.reports import read_reports, write_reports
from tracker.io.tracks import read_tracks, write_tracks
from tracker.study.simulate import simulate


def _upper(covs: np.ndarray) -> np.ndarray:
    """The (xx, xy, yy) entries the files store (the xy/yx pair is one column)."""
    return np.stack([covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 1]], axis=1)


@pytest.fixture(scope="module")
def prior_path(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    g = Grid.from_bounds((0.0, 0.0, 16000.0, 16000.0), 40.0, "EPSG:32634")
    yy, xx = np.mgrid[0 : g.height, 0 : g.width]
    TerrainPrior.from_array(1.0 + 0.9 * np.cos(xx / 9.0) * np.sin(yy / 13.0), g).write(d / "prior.tif")
    return d / "prior.tif"


def test_simulate_writes_the_library_scenario(prior_path, tmp_path, capsys):
    out, truth = tmp_path / "reports.csv", tmp_path / "targets.csv"
    assert main(["simulate", "--prior", str(prior_path), "--seed", "5", "--reports", "40",
                 "--out", str(out), "--truth-out", str(truth)]) == 0
    scenario = simulate(TerrainPrior.read(prior_path), 5, 200, 40)
    reports, crs = read_reports(out)
    assert crs is None
    np.testing.assert_array_equal(reports.means, scenario.reports.means)
    np.testing.assert_array_equal(_upper(reports.covs), _upper(scenario.reports.covs))
    np.testing.assert_array_equal(reports.times, scenario.reports.times)
    np.testing.assert_array_equal(reports.truth, scenario.reports.truth)
    targets = pd.read_csv(truth)
    np.testing.assert_array_equal(targets[["x", "y"]].to_numpy(), scenario.targets)
    assert "40 reports" in capsys.readouterr().out


def test_reports_and_tracks_round_trip(prior_path, tmp_path):
    prior = TerrainPrior.read(prior_path)
    reports = simulate(prior, 1, 200, 30).reports
    assert read_reports(write_reports(tmp_path / "r.csv", reports))[0].means.tolist() == reports.means.tolist()
    estimate = associate(prior, reports, "TT", tau=-3.0).estimate
    means, covs, counts = read_tracks(write_tracks(tmp_path / "t.gpkg", estimate, prior.grid.crs.to_wkt()))
    np.testing.assert_array_equal(means, estimate.means)
    np.testing.assert_array_equal(_upper(covs), _upper(estimate.covs))
    np.testing.assert_array_equal(counts, estimate.counts)
    assert counts.sum() == len(reports)


def test_show_draws_a_map_and_names_bad_tracks(prior_path, tmp_path, capsys):
    reports_csv = tmp_path / "r.csv"
    main(["simulate", "--prior", str(prior_path), "--reports", "20", "--out", str(reports_csv)])
    tracks = tmp_path / "t.gpkg"
    assert main(["run", "--prior", str(prior_path), "--reports", str(reports_csv), "--out", str(tracks)]) == 0
    png = tmp_path / "map.png"
    assert main(["show", "--prior", str(prior_path), "--reports", str(reports_csv), "--tracks", str(tracks),
                 "--png", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["show", "--prior", str(prior_path), "--reports", str(reports_csv), "--tracks",
                 str(reports_csv), "--png", str(tmp_path / "bad.png")]) == 1
    assert "r.csv" in capsys.readouterr().err
    assert not (tmp_path / "bad.png").exists()


@pytest.fixture(scope="module")
def buildings(prior_path, tmp_path_factory):
    """Building footprints (squares, read as centroids) in a two-layer GeoPackage on the prior's CRS."""
    import shapely

    from tests.pipeline.gis_helpers import write_vector

    d = tmp_path_factory.mktemp("buildings")
    centres = np.random.default_rng(4).uniform(1000, 15000, size=(400, 2))
    gpkg = d / "places.gpkg"
    write_vector(gpkg, [shapely.box(x - 5, y - 5, x + 5, y + 5) for x, y in centres], layer="buildings", crs="EPSG:32634")
    write_vector(gpkg, [shapely.Point(0, 0)], layer="roads", crs="EPSG:32634")
    return gpkg, centres


def test_simulate_targets_file_picks_the_file_locations(prior_path, buildings, tmp_path, capsys):
    from tracker.study.simulate import simulate_points

    gpkg, centres = buildings
    out, truth = tmp_path / "reports.csv", tmp_path / "targets.csv"
    assert main(["-q", "simulate", "--prior", str(prior_path), "--targets-file", str(gpkg), "--layer", "buildings",
                 "--targets", "25", "--reports", "40", "--seed", "3", "--out", str(out), "--truth-out", str(truth)]) == 0
    expected = simulate_points(TerrainPrior.read(prior_path), centres, 3, 25, 40)
    targets = pd.read_csv(truth)[["x", "y"]].to_numpy()
    np.testing.assert_allclose(targets, expected.targets, atol=1e-6)  # centroids of the squares
    assert len(targets) == 25
    reports, _ = read_reports(out)
    np.testing.assert_allclose(reports.means, expected.reports.means, atol=1e-6)
    assert "40 reports" in capsys.readouterr().out


@pytest.mark.parametrize(("extra", "message"), [
    ([], "has several layers ['buildings', 'roads']; pick one with --layer"),
    (["--layer", "shops"], "no layer 'shops' (--layer)"),
])
def test_simulate_targets_file_names_a_bad_layer(prior_path, buildings, tmp_path, capsys, extra, message):
    gpkg, _ = buildings
    out = tmp_path / "reports.csv"
    assert main(["-q", "simulate", "--prior", str(prior_path), "--targets-file", str(gpkg), *extra, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"terrain-track: error: {gpkg}: " in err and message in err and "Traceback" not in err
    assert not out.exists()


def test_simulate_targets_file_names_an_empty_window(prior_path, tmp_path, capsys):
    csv = tmp_path / "far.csv"
    csv.write_text("x,y\n100,100\n200,15900\n")  # both outside the central half
    assert main(["-q", "simulate", "--prior", str(prior_path), "--targets-file", str(csv), "--out", str(tmp_path / "r.csv")]) == 1
    assert f"error: {csv}: none of its 2 locations lies in the window" in capsys.readouterr().err


def test_experiment_targets_file_tracks_the_file_locations(prior_path, buildings, tmp_path):
    gpkg, _ = buildings
    out = tmp_path / "exp"
    assert main(["-q", "experiment", "--prior", str(prior_path), "--targets-file", str(gpkg), "--layer", "buildings",
                 "--targets", "20", "--datasets", "2", "--reports", "30", "--tau", "-1,1", "--workers", "1",
                 "--out", str(out)]) == 0
    results = pd.read_parquet(out / "results.parquet")
    assert set(results["n_targets"]) == {20} and set(results["variant"]) == {"UU", "UT", "TT"}
    assert results["rms_error_m"].between(0, 500).all()
