"""Reports files in: CSV and GeoPackage round trips, clear errors; true targets out and in."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
import shapely
from pyogrio import raw

from tracker.io.reports import read_reports, read_targets, write_targets


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


def test_targets_round_trip(tmp_path):
    targets = np.random.default_rng(2).uniform(0, 1e4, (7, 2))
    path = write_targets(tmp_path / "t.csv", targets)
    np.testing.assert_array_equal(read_targets(path), targets)
    np.testing.assert_array_equal(pd.read_csv(path)["truth"], np.arange(7))


@pytest.mark.parametrize(("content", "message"), [
    (b"", "empty file; a CSV of {what} needs a header row"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "not a text CSV of {what} (binary file"),
    (b"x,y\n\xff\xfe,1\n", "not a text CSV of {what} (byte"),
    (b'x,y\n"1,2\n', "not a readable CSV of {what}"),
])
def test_unreadable_csvs_are_named(tmp_path, content, message):
    """Empty, binary, non-UTF-8 and malformed CSVs: the file and what it should hold, not pandas' words."""
    path = tmp_path / "f.csv"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="^" + re.escape(f"{path}: " + message.format(what="reports"))):
        read_reports(path)
    with pytest.raises(ValueError, match="^" + re.escape(f"{path}: " + message.format(what="true targets"))):
        read_targets(path)


def test_targets_csv_errors_name_the_file(tmp_path):
    path = tmp_path / "t.csv"
    pd.DataFrame({"truth": [0], "x": [1.0]}).to_csv(path, index=False)
    with pytest.raises(ValueError, match=re.escape(f"{path}: missing target columns ['y']")):
        read_targets(path)
    pd.DataFrame({"x": [1.0, 2.0], "y": ["a", 3.0]}).to_csv(path, index=False)
    with pytest.raises(ValueError, match=re.escape(f"{path}: target columns ['x', 'y'] must be numeric")):
        read_targets(path)
    pd.DataFrame({"x": [1.0, np.nan], "y": [2.0, 3.0]}).to_csv(path, index=False)
    with pytest.raises(ValueError, match=re.escape(f"{path}: missing or non-finite x/y on data rows [1]")):
        read_targets(path)
