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
