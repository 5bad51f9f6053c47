"""Reports files in, tracks GeoPackage out: round trips, closed-form ellipse areas, clear errors."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import shapely
from pyogrio import raw

from tracker.association.greedy import Estimate
from tracker.io.tracks import ELLIPSE_VERTICES, read_reports, write_tracks


def _table(n=5, seed=0):
    rng = np.random.default_rng(seed)
    return pd.DataFrame({
        "x": rng.uniform(0, 1000, n), "y": rng.uniform(0, 1000, n), "time": np.arange(n) * 2.0,
        "cov_xx": rng.uniform(10, 20, n), "cov_xy": rng.uniform(-3, 3, n), "cov_yy": rng.uniform(10, 20, n),
        "truth": rng.integers(0, 3, n),
    })


def test_csv_round_trip(tmp_path):
    df = _table()
    df.to_csv(tmp_path / "r.csv", index=False)
    reports, crs = read_reports(tmp_path / "r.csv")
    assert crs is None
    np.testing.assert_array_equal(reports.means, df[["x", "y"]].to_numpy())
    np.testing.assert_array_equal(reports.covs[:, 0, 1], df["cov_xy"].to_numpy())
    np.testing.assert_array_equal(reports.covs[:, 1, 0], df["cov_xy"].to_numpy())
    np.testing.assert_array_equal(reports.times, df["time"].to_numpy())
    np.testing.assert_array_equal(reports.truth, df["truth"].to_numpy())


def test_gpkg_points_without_xy_columns(tmp_path):
    df = _table()
    fields = ["time", "cov_xx", "cov_xy", "cov_yy"]
    geom = shapely.to_wkb(shapely.points(df[["x", "y"]].to_numpy()))
    raw.write(tmp_path / "r.gpkg", geom, [df[f].to_numpy() for f in fields], fields, layer="reports",
              driver="GPKG", geometry_type="Point", crs="EPSG:32634")
    reports, crs = read_reports(tmp_path / "r.gpkg")
    np.testing.assert_allclose(reports.means, df[["x", "y"]].to_numpy())
    assert "32634" in crs
    assert np.all(reports.truth == -1)


def test_bad_report_files(tmp_path):
    df = _table()
    df.drop(columns=["cov_xy"]).to_csv(tmp_path / "a.csv", index=False)
    with pytest.raises(ValueError, match=r"a\.csv: missing report columns \['cov_xy'\]"):
        read_reports(tmp_path / "a.csv")
    bad = df.copy()
    bad.loc[3, "y"] = np.nan
    bad.to_csv(tmp_path / "b.csv", index=False)
    with pytest.raises(ValueError, match=r"b\.csv: .*indices \[3\]"):
        read_reports(tmp_path / "b.csv")
    bad = df.copy()
    bad.loc[1, "cov_xy"] = 100.0  # |cov_xy| > sqrt(cov_xx cov_yy): not positive definite
    bad.to_csv(tmp_path / "c.csv", index=False)
    with pytest.raises(ValueError, match=r"c\.csv: .*positive definite at indices \[1\]"):
        read_reports(tmp_path / "c.csv")
    with pytest.raises(ValueError, match="no such file"):
        read_reports(tmp_path / "missing.csv")
    (tmp_path / "d.txt").write_text("x")
    with pytest.raises(ValueError, match=r"d\.txt: reports must be"):
        read_reports(tmp_path / "d.txt")


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
