"""``terrain-track run --method batch`` end to end on a small crowded scene, against the library called
directly: ln p(Λ|Z) of the written partition is >= greedy's, membership in (0, 1], seeded sampling,
UT = UU association with r in the estimate, bad options as ``error:`` lines, and greedy unchanged."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from pyogrio import raw

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.batch import batch_estimate, log_posterior
from tracker.association.greedy import associate
from tracker.cli import main
from tracker.io.reports import read_reports
from tracker.models.sfunc import ExpS

GREEDY_GOLDEN = [0, 1, 1, 0, 2, 1, 2, 3, 2, 2, 2, 0, 1, 1, 2, 2, 4, 1, 3, 3, 0, 2, 2, 0, 2, 4, 2, 2, 4, 1]
"""Greedy TT, τ = -1.7, on the scene below (as written before the batch method existed)."""


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Six targets within 1 km, 40–150 m noise: greedy's one pass leaves ln p to gain."""
    d = tmp_path_factory.mktemp("batch")
    g = Grid.from_bounds((0.0, 0.0, 6000.0, 6000.0), 20.0, "EPSG:32634")
    yy, xx = np.mgrid[0 : g.height, 0 : g.width]
    TerrainPrior.from_array(1.0 + 0.8 * np.cos(xx / 7.0) * np.sin(yy / 11.0), g).write(d / "prior.tif")
    rng = np.random.default_rng(2)
    n = 30
    targets, truth, sd = rng.uniform(2500, 3500, (6, 2)), rng.integers(0, 6, n), rng.uniform(40, 150, (n, 2))
    z = targets[truth] + rng.normal(0, 1, (n, 2)) * sd
    pd.DataFrame({"x": z[:, 0], "y": z[:, 1], "time": np.arange(float(n)), "cov_xx": sd[:, 0] ** 2, "cov_xy": 0.0,
                  "cov_yy": sd[:, 1] ** 2}).to_csv(d / "reports.csv", index=False)
    return d, TerrainPrior.read(d / "prior.tif"), read_reports(d / "reports.csv")[0]


def _run(d, name, *extra) -> int:
    return main(["run", "-q", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"),
                 "--out", str(d / f"{name}.gpkg"), "--assignments", str(d / f"{name}.csv"), *extra])


def _targets(path) -> dict[str, np.ndarray]:
    meta, _, _, data = raw.read(path, layer="targets", read_geometry=False)
    return dict(zip(meta["fields"], data, strict=True))


def test_greedy_output_is_unchanged(scene):
    """``--method greedy`` (and the default) write greedy's assignments, with no membership column."""
    d, prior, reports = scene
    assert _run(d, "default") == 0 and _run(d, "greedy", "--method", "greedy") == 0
    table = pd.read_csv(d / "greedy.csv")
    assert list(table.columns) == ["report", "hypothesis"]
    np.testing.assert_array_equal(table["hypothesis"], GREEDY_GOLDEN)
    np.testing.assert_array_equal(table["hypothesis"], associate(prior, reports, "TT", tau=-1.7).assignments)
    assert (d / "greedy.csv").read_bytes() == (d / "default.csv").read_bytes()
    for key, value in _targets(d / "default.gpkg").items():
        np.testing.assert_array_equal(_targets(d / "greedy.gpkg")[key], value)


def test_batch_map_beats_greedy(scene, capsys):
    d, prior, reports = scene
    assert _run(d, "map", "--method", "batch", "--sweeps", "3") == 0
    out = capsys.readouterr().out
    table = pd.read_csv(d / "map.csv")
    labels = table["hypothesis"].to_numpy()
    np.testing.assert_array_equal(table["membership"], 1.0)  # map mode: a point estimate
    s = ExpS(-1.7)
    lp, lp_greedy = log_posterior(prior, reports, labels, s), log_posterior(prior, reports, GREEDY_GOLDEN, s)
    assert lp > lp_greedy + 0.1  # this scene: -383.50 against -383.82
    assert f"greedy {lp_greedy:.3f}, batch {lp:.3f}" in out
    tracks, want = _targets(d / "map.gpkg"), batch_estimate(prior, reports, labels, "TT")
    assert f"-> {want.counts.size} targets" in out
    np.testing.assert_allclose(np.stack([tracks["x"], tracks["y"]], 1), want.means)
    np.testing.assert_array_equal(tracks["count"], want.counts)
    np.testing.assert_array_equal(tracks["count"], np.bincount(labels))  # hypothesis = the track's row


def test_batch_sampling_is_seeded(scene):
    d, prior, reports = scene
    for name in ("s1", "s1b"):
        assert _run(d, name, "--method", "batch", "--sweeps", "5", "--samples", "40", "--seed", "1") == 0
    assert (d / "s1.csv").read_bytes() == (d / "s1b.csv").read_bytes()
    for key, value in _targets(d / "s1.gpkg").items():
        np.testing.assert_array_equal(_targets(d / "s1b.gpkg")[key], value)
    table = pd.read_csv(d / "s1.csv")
    membership = table["membership"].to_numpy()
    assert ((membership > 0) & (membership <= 1)).all() and (membership < 1).any()  # a posterior, not a point
    s = ExpS(-1.7)
    assert log_posterior(prior, reports, table["hypothesis"], s) >= log_posterior(prior, reports, GREEDY_GOLDEN, s) - 1e-9


def test_batch_ut_associates_as_uu_and_estimates_with_r(scene):
    d, prior, reports = scene
    assert _run(d, "ut", "--method", "batch", "--variant", "UT", "--sweeps", "3") == 0
    assert _run(d, "uu", "--method", "batch", "--variant", "UU", "--sweeps", "3") == 0
    ut, uu = pd.read_csv(d / "ut.csv"), pd.read_csv(d / "uu.csv")
    pd.testing.assert_frame_equal(ut, uu)
    tracks_ut, tracks_uu = _targets(d / "ut.gpkg"), _targets(d / "uu.gpkg")
    assert (tracks_ut["terrain"] == 1).all() and (tracks_uu["terrain"] == 0).all()
    want = batch_estimate(prior, reports, ut["hypothesis"].to_numpy(), "TT")
    np.testing.assert_allclose(tracks_ut["log_c"], want.log_c)


def test_batch_skips_reports_off_the_prior(scene, tmp_path):
    """``--off-prior skip``: batch runs on the reports greedy kept; skipped ones get -1 and no membership."""
    d, _, _ = scene
    df = pd.read_csv(d / "reports.csv")
    df.loc[4, "x"] = -90000.0
    df.to_csv(tmp_path / "reports.csv", index=False)
    (tmp_path / "prior.tif").symlink_to(d / "prior.tif")
    for sat in d.glob("prior.sat*"):
        (tmp_path / sat.name).symlink_to(sat)
    assert _run(tmp_path, "a", "--method", "batch", "--sweeps", "2", "--off-prior", "skip") == 0
    table = pd.read_csv(tmp_path / "a.csv")
    assert table["hypothesis"][4] == -1 and np.isnan(table["membership"][4])
    assert (table["hypothesis"].drop(4) >= 0).all() and (table["membership"].drop(4) == 1).all()


@pytest.mark.parametrize("extra, message", [
    (["--samples", "10"], "--method greedy takes no --samples"),
    (["--sweeps", "3", "--seed", "1"], "--method greedy takes no --sweeps, --seed"),
    (["--method", "batch", "--motion", "cv"], "--method batch needs static targets"),
])
def test_bad_options_are_errors(scene, capsys, extra, message):
    d, _, _ = scene
    assert _run(d, "bad", *extra) == 1
    err = capsys.readouterr().err
    assert f"error: {message}" in err and "Traceback" not in err
    assert not (d / "bad.gpkg").exists() and not (d / "bad.csv").exists()
    with pytest.raises(SystemExit) as exc:
        _run(d, "bad", "--method", "mcmc")
    assert exc.value.code == 2
