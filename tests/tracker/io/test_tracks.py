"""Tracks GeoPackage out: closed-form ellipse areas, empty estimates; assignments CSV; covariance columns."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import shapely
from pyogrio import raw

from tracker.io.columns import COV_COLUMNS, cov_columns, covs_from_columns
from tracker.io.tracks import ELLIPSE_VERTICES, read_tracks, write_assignments, write_tracks
from tracker.types.estimate import Estimate


def test_write_tracks_points_and_ellipses(tmp_path):
    means = np.array([[100.0, 200.0], [500.0, -40.0]])
    covs = np.array([[[400.0, 120.0], [120.0, 100.0]], [[25.0, 0.0], [0.0, 9.0]]])
    est = Estimate(means, covs, np.array([-18.0, -19.5]), np.array([3, 1]), True, np.array([-1, -1]))
    out = tmp_path / "t.gpkg"
    out.write_text("old")  # replaced atomically
    write_tracks(out, est, "EPSG:32634", ellipse_prob=0.9)
    meta, _, geom, data = raw.read(out, layer="targets")
    pts = shapely.from_wkb(geom)
    np.testing.assert_allclose(np.stack([shapely.get_x(pts), shapely.get_y(pts)], 1), means)
    fields = dict(zip(meta["fields"], data, strict=True))
    np.testing.assert_array_equal(fields["count"], [3, 1])
    np.testing.assert_allclose(fields["cov_xy"], [120.0, 0.0])
    _, _, geom, _ = raw.read(out, layer="ellipses")
    polys = shapely.from_wkb(geom)
    # A regular n-gon inscribed in the ellipse of Mahalanobis radius ρ: area (n/2) sin(2π/n) ρ² √det.
    rho2 = -2.0 * math.log(0.1)
    n = ELLIPSE_VERTICES
    want = 0.5 * n * math.sin(2 * math.pi / n) * rho2 * np.sqrt(np.linalg.det(covs))
    np.testing.assert_allclose(shapely.area(polys), want, rtol=1e-9)
    np.testing.assert_allclose(shapely.get_coordinates(shapely.centroid(polys)), means, atol=1e-6)
    assert not list(tmp_path.glob(".t.*"))  # no temporary left behind


def test_write_empty_tracks(tmp_path):
    est = Estimate(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0, int), False, np.zeros(0, int))
    write_tracks(tmp_path / "e.gpkg", est, "EPSG:32634")
    meta, _, geom, _ = raw.read(tmp_path / "e.gpkg", layer="ellipses")
    assert len(geom) == 0


def test_write_assignments(tmp_path):
    path = write_assignments(tmp_path / "a.csv", np.array([0, 1, -1, 0]))
    table = pd.read_csv(path)
    assert list(table.columns) == ["report", "hypothesis"]
    np.testing.assert_array_equal(table["hypothesis"], [0, 1, -1, 0])


def test_cov_columns_round_trip():
    covs = np.array([[[4.0, 1.5], [1.5, 9.0]], [[2.0, -0.5], [-0.5, 1.0]]])
    columns = cov_columns(covs)
    assert tuple(columns) == COV_COLUMNS
    np.testing.assert_array_equal(covs_from_columns(*columns.values()), covs)


def test_read_tracks_names_a_file_that_is_no_tracks_file(tmp_path):
    """A GeoPackage with a ``targets`` layer but not the tracks columns: named, not a KeyError."""
    path = tmp_path / "other.gpkg"
    raw.write(path, shapely.to_wkb(shapely.points(np.zeros((1, 2)))), [np.array([1])], ["n"], layer="targets",
              driver="GPKG", geometry_type="Point", crs="EPSG:32634")
    with pytest.raises(ValueError, match=r"other\.gpkg: layer 'targets' lacks columns \['x', 'y', 'cov_xx'"):
        read_tracks(path)
