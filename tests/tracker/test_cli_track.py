"""``terrain-track run`` end to end on a small written prior, against the library called directly."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import shapely
from pyogrio import raw

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import associate
from tracker.cli import main
from tracker.models.sfunc import PoissonS


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("track")
    g = Grid.from_bounds((0.0, 0.0, 6000.0, 6000.0), 20.0, "EPSG:32634")
    yy, xx = np.mgrid[0 : g.height, 0 : g.width]
    prior = TerrainPrior.from_array(1.0 + 0.8 * np.cos(xx / 7.0) * np.sin(yy / 11.0), g)
    prior.write(d / "prior.tif")
    rng = np.random.default_rng(3)
    targets = rng.uniform(1500, 4500, (8, 2))
    truth = rng.integers(0, 8, 40)
    sd = rng.uniform(15, 60, (40, 2))
    df = pd.DataFrame({
        "x": targets[truth, 0] + rng.normal(0, 1, 40) * sd[:, 0], "y": targets[truth, 1] + rng.normal(0, 1, 40) * sd[:, 1],
        "time": np.arange(40.0), "cov_xx": sd[:, 0] ** 2, "cov_xy": 0.0, "cov_yy": sd[:, 1] ** 2, "truth": truth,
    })
    df.to_csv(d / "reports.csv", index=False)
    return d, TerrainPrior.read(d / "prior.tif"), df


@pytest.mark.parametrize("variant", ["TT", "UU"])
def test_run_matches_library(files, variant, capsys):
    d, prior, df = files
    from tracker.io.reports import read_reports

    out, assign = d / f"{variant}.gpkg", d / f"{variant}.csv"
    code = main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"), "--variant", variant,
                 "--tau", "-1.0", "--out", str(out), "--assignments", str(assign)])
    assert code == 0
    want = associate(prior, read_reports(d / "reports.csv")[0], variant, tau=-1.0)
    assert f"-> {want.n_detected} targets" in capsys.readouterr().out
    np.testing.assert_array_equal(pd.read_csv(assign)["hypothesis"].to_numpy(), want.assignments)
    meta, _, geom, data = raw.read(out, layer="targets")
    pts = shapely.from_wkb(geom)
    np.testing.assert_allclose(np.stack([shapely.get_x(pts), shapely.get_y(pts)], 1), want.estimate.means)
    assert "32634" in meta["crs"] or "UTM zone 34" in meta["crs"]


def test_run_with_the_terraces(files):
    """``--integrator terraces`` reaches the terraces: assignments equal the library run with them."""
    d, prior, _ = files
    from functools import partial

    from tracker.integrate import integrate
    from tracker.io.reports import read_reports

    code = main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"), "--integrator", "terraces",
                 "--tau", "-1.0", "--assignments", str(d / "t.csv"), "--out", str(d / "t.gpkg")])
    assert code == 0
    want = associate(prior, read_reports(d / "reports.csv")[0], "TT", tau=-1.0,
                     integrator=partial(integrate, method="terraces"))
    np.testing.assert_array_equal(pd.read_csv(d / "t.csv")["hypothesis"].to_numpy(), want.assignments)
    with pytest.raises(SystemExit):
        main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"), "--integrator", "strips",
              "--out", str(d / "x.gpkg")])


def test_run_poisson(files):
    d, prior, _ = files
    from tracker.io.reports import read_reports

    code = main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"), "--poisson-mu", "10",
                 "--assignments", str(d / "p.csv"), "--out", str(d / "p.gpkg")])
    assert code == 0
    want = associate(prior, read_reports(d / "reports.csv")[0], "TT", s_model=PoissonS(10.0))
    np.testing.assert_array_equal(pd.read_csv(d / "p.csv")["hypothesis"].to_numpy(), want.assignments)


def test_run_bad_inputs(files, capsys):
    d, _, df = files
    bad = df.copy()
    bad.loc[5, "cov_yy"] = -1.0
    bad.to_csv(d / "bad.csv", index=False)
    code = main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "bad.csv"), "--out", str(d / "x.gpkg")])
    assert code == 1
    err = capsys.readouterr().err
    assert "bad.csv" in err and "indices [5]" in err
    assert not (d / "x.gpkg").exists()
    off = df.copy()
    off.loc[2, "x"] = -90000.0
    off.to_csv(d / "off.csv", index=False)
    assert main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "off.csv"), "--out", str(d / "y.gpkg")]) == 1
    assert "indices [2]" in capsys.readouterr().err
    assert main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "off.csv"), "--off-prior", "skip",
                 "--out", str(d / "y.gpkg")]) == 0
    assert "1 skipped" in capsys.readouterr().out
    geom = shapely.to_wkb(shapely.points(df[["x", "y"]].to_numpy()))
    fields = ["time", "cov_xx", "cov_xy", "cov_yy"]
    raw.write(d / "wgs.gpkg", geom, [df[f].to_numpy() for f in fields], fields, driver="GPKG",
              geometry_type="Point", crs="EPSG:4326")
    assert main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "wgs.gpkg"), "--out", str(d / "z.gpkg")]) == 1
    assert "differs from the prior" in capsys.readouterr().err
    assert main(["run", "--prior", str(d / "missing.tif"), "--reports", str(d / "reports.csv"), "--out", str(d / "z.gpkg")]) == 1
    assert "missing.tif" in capsys.readouterr().err


def test_track_files_commits_tracks_and_assignments_together(files, tmp_path):
    """The API's outputs are one commit: assignments under a regular file leave no tracks file either."""
    from tracker.run import track_files

    d, _, _ = files
    with pytest.raises(OSError):
        track_files(d / "prior.tif", d / "reports.csv", tmp_path / "t.gpkg", assignments_csv=d / "reports.csv" / "a.csv")
    assert list(tmp_path.iterdir()) == []


def test_run_on_a_windowed_prior_with_tiles_built_on_a_cluster(files, monkeypatch, capsys):
    """A prior above the size limits (lowered here): `run` reads it window by window, and with
    ``--scheduler`` the pyramid's cell-level tiles are built on the cluster; decisions are the library's."""
    from distributed import Client

    from pipeline.prior import terrain
    from tracker.integrate import scalespace
    from tracker.io.reports import read_reports

    d, prior, df = files
    cells = prior.grid.height * prior.grid.width
    monkeypatch.setattr(scalespace, "MAX_CELLS", cells - 1)
    monkeypatch.setattr(terrain, "WINDOWED_CELLS", cells - 1)
    want = associate(TerrainPrior.read(d / "prior.tif", windowed=False), read_reports(d / "reports.csv")[0], "TT", tau=-1.0)
    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        code = main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"), "--tau", "-1.0",
                     "--scheduler", client.scheduler.address, "--out", str(d / "win.gpkg"), "--assignments", str(d / "win.csv")])
        sent = client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.transition_counter)
    assert code == 0 and sent > 0
    np.testing.assert_array_equal(pd.read_csv(d / "win.csv")["hypothesis"].to_numpy(), want.assignments)
    assert f"-> {want.n_detected} targets" in capsys.readouterr().out


def test_run_with_an_unreachable_scheduler_names_it(files, capsys, monkeypatch):
    d, _, _ = files
    monkeypatch.setattr("common.dask.CONNECT_TIMEOUT", "1s")  # port 9 refuses at once; Dask retries until the timeout
    code = main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"),
                 "--scheduler", "tcp://127.0.0.1:9", "--out", str(d / "never.gpkg")])
    err = capsys.readouterr().err
    assert code == 1 and "error: --scheduler tcp://127.0.0.1:9: cannot connect" in err and "Traceback" not in err
    assert not (d / "never.gpkg").exists()
