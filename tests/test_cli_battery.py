"""No CLI input produces a Python traceback, and no failed run leaves output behind or touches an input.

Each bad command line runs both CLIs' way (``python -m pipeline.cli`` / ``python -m tracker.cli`` in a
subprocess) on a small copy of the bundled region: stderr has an ``error:`` line and no traceback, the
exit code is 1 (2 for argparse usage errors), and every file under the run's folder — inputs and
anything else — is byte for byte what it was, with nothing added (hidden staging files included).
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import shapely
import tomli_w

from common.cli import attach_negative_values, quiet_parent, run_cli
from common.outputs import Output, OutputError, command_outputs
from pipeline.cli import main as prior_main
from tests.pipeline.gis_helpers import REGION_TOML, write_vector
from tracker.cli import main as track_main

REPO = Path(__file__).resolve().parents[1]
BOUNDS = [304000.0, 6190000.0, 306000.0, 6192000.0]  # 2 km square: 100 x 100 cells of 20 m


@pytest.fixture(scope="module")
def region(tmp_path_factory) -> Path:
    """A folder with a small region (config, layers), its prior, reports, tracks and targets files."""
    d = tmp_path_factory.mktemp("battery")
    for name in ("region.gpkg", "dem.tif", "vegetation.tif"):
        shutil.copy(REGION_TOML.parent / name, d / name)
    doc = tomllib.loads(REGION_TOML.read_text())
    doc["region"]["bounds"] = BOUNDS
    (d / "region.toml").write_text(tomli_w.dumps(doc))
    assert prior_main(["-q", "build", str(d / "region.toml"), "--out", str(d / "prior.tif")]) == 0
    rng = np.random.default_rng(5)
    xy = rng.uniform(BOUNDS[:2], BOUNDS[2:], (30, 2))
    pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1], "time": np.arange(30.0), "cov_xx": 900.0, "cov_xy": 0.0,
                  "cov_yy": 900.0}).to_csv(d / "reports.csv", index=False)
    pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1]}).to_csv(d / "targets.csv", index=False)
    pts = list(shapely.points(xy))
    write_vector(d / "targets.gpkg", pts, layer="a", crs="EPSG:32734")
    write_vector(d / "targets.gpkg", pts, layer="b", crs="EPSG:32734")
    assert track_main(["run", "--prior", str(d / "prior.tif"), "--reports", str(d / "reports.csv"), "--off-prior", "skip",
                       "--out", str(d / "tracks.gpkg")]) == 0
    (d / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (d / "empty.csv").write_bytes(b"")
    pd.DataFrame({"x": [0.0], "y": [0.0], "time": [0.0], "cov_xx": [1.0], "cov_xy": [0.0],
                  "cov_yy": [1.0]}).to_csv(d / "far.csv", index=False)
    (d / "header.csv").write_text("x,y\n")
    pd.DataFrame({"x": [20.4, 20.5], "y": [-34.0, -34.1]}).to_csv(d / "lonlat.csv", index=False)
    pd.DataFrame({"x": xy[:3, 0], "y": xy[:3, 1], "w": ["1", "two", "3"]}).to_csv(d / "textweights.csv", index=False)
    (d / "link.tif").symlink_to(d / "dem.tif")
    (d / "folder").mkdir()
    return d


def tree(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (hidden ones included), by relative path; folders as 'dir'."""
    out = {}
    for p in sorted(root.rglob("*")):
        out[str(p.relative_to(root))] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


PRIOR = "terrain-prior"
TRACK = "terrain-track"
CASES = {
    # inputs overwritten: an output that is an input of the run (a symlink to one too)
    "build over the DEM": (PRIOR, ["build", "{d}/region.toml", "--out", "{d}/dem.tif"], 1, "is an input"),
    "build over the config": (PRIOR, ["build", "{d}/region.toml", "--out", "{d}/region.toml"], 1, "is an input"),
    "build over a symlink to the DEM": (PRIOR, ["build", "{d}/region.toml", "--out", "{d}/link.tif"], 1, "is an input"),
    "run over the prior": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv",
                                   "--out", "{d}/prior.tif"], 1, "is an input"),
    "run: assignments over the reports": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv",
                                                  "--out", "{d}/new.gpkg", "--assignments", "{d}/reports.csv"], 1, "is an input"),
    "simulate over a table of the prior": (TRACK, ["simulate", "--prior", "{d}/prior.tif", "--out", "{d}/prior.sat.npy"],
                                           1, "is an input"),
    "show over the tracks": (TRACK, ["show", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv", "--tracks",
                                     "{d}/tracks.gpkg", "--png", "{d}/tracks.gpkg"], 1, "is an input"),
    "learn over the targets": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/targets.csv",
                                       "--out", "{d}/targets.csv"], 1, "is an input"),
    # half-written output: a folder as a file output, an output under a regular file
    "build into a folder": (PRIOR, ["build", "{d}/region.toml", "--out", "{d}/folder"], 1, "is a folder"),
    "build under a file": (PRIOR, ["build", "{d}/region.toml", "--out", "{d}/reports.csv/prior.tif"], 1, "not a folder"),
    "features under a file": (PRIOR, ["features", "{d}/region.toml", "--out", "{d}/reports.csv/features"], 1, "not a folder"),
    "features into a file": (PRIOR, ["features", "{d}/region.toml", "--out", "{d}/targets.gpkg"], 1, "not a folder"),
    "show --png under a file": (PRIOR, ["show", "{d}/prior.tif", "--png", "{d}/reports.csv/p.png"], 1, "not a folder"),
    "run: assignments under a file": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv",
                                              "--out", "{d}/new.gpkg", "--assignments", "{d}/reports.csv/a.csv"], 1,
                                      "not a folder"),
    "run: two outputs on one path": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv",
                                             "--out", "{d}/new.gpkg", "--assignments", "{d}/new.gpkg"], 1, "same path"),
    "experiment under a file": (TRACK, ["experiment", "--prior", "{d}/prior.tif", "--datasets", "2",
                                        "--out", "{d}/reports.csv/exp"], 1, "not a folder"),
    # raw messages: binary and empty CSVs, several layers in a targets file
    "run on a binary CSV": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/binary.csv",
                                    "--out", "{d}/new.gpkg"], 1, "binary.csv: not a text CSV"),
    "run on an empty CSV": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/empty.csv",
                                    "--out", "{d}/new.gpkg"], 1, "empty.csv: empty file"),
    "show with a binary truth CSV": (TRACK, ["show", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv", "--tracks",
                                             "{d}/tracks.gpkg", "--truth", "{d}/binary.csv", "--png", "{d}/new.png"], 1,
                                     "binary.csv: not a text CSV"),
    "run off the prior names the reports": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/far.csv",
                                                    "--out", "{d}/new.gpkg"], 1, "far.csv: reports at indices"),
    "learn on a multi-layer targets file": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/targets.gpkg", "--no-cv",
                                                    "--out", "{d}/model.toml"], 1, "--layer"),
    "learn on a binary CSV": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/binary.csv", "--no-cv",
                                      "--out", "{d}/model.toml"], 1, "binary.csv: not a text CSV of target points"),
    "learn on an empty CSV": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/empty.csv", "--no-cv",
                                      "--out", "{d}/model.toml"], 1, "empty.csv: empty file"),
    "learn on a header without rows": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/header.csv", "--no-cv",
                                               "--out", "{d}/model.toml"], 1, "header.csv: no data rows"),
    "learn on lon/lat targets": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/lonlat.csv", "--no-cv",
                                         "--out", "{d}/model.toml"], 1,
                                 "lonlat.csv: none of its 2 target points lies on the grid"),
    "learn: --layer of a CSV": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/targets.csv", "--layer", "a",
                                        "--no-cv", "--out", "{d}/model.toml"], 1, "targets.csv: --layer"),
    "learn: text weights": (PRIOR, ["learn", "{d}/region.toml", "--targets", "{d}/textweights.csv", "--weights", "w",
                                    "--no-cv", "--out", "{d}/model.toml"], 1,
                            "column 'w' (--weights): non-numeric values on data rows [1]"),
    # usage errors exit 2
    "unknown option": (PRIOR, ["build", "{d}/region.toml", "--out", "{d}/p.tif", "--bogus"], 2, "unrecognized"),
    "bad choice": (TRACK, ["run", "--prior", "{d}/prior.tif", "--reports", "{d}/reports.csv", "--variant", "XX",
                           "--out", "{d}/new.gpkg"], 2, "invalid choice"),
}


def run_case(root: Path, case: str, in_subprocess: bool, capsys) -> tuple[int, str]:
    """Run ``case`` on the files under ``root``: exit code and stderr. In-process, an exception that
    escapes ``main`` fails the test as a traceback would; argparse's exit is its code."""
    prog, argv, _, _ = CASES[case]
    argv = ["-q", *(a.format(d=root) for a in argv)]
    if in_subprocess:
        module = "pipeline.cli" if prog == PRIOR else "tracker.cli"
        run = subprocess.run([sys.executable, "-m", module, *argv], capture_output=True, text=True, cwd=REPO,
                             env=os.environ | {"PYTHONPATH": str(REPO)}, timeout=300)
        return run.returncode, run.stderr
    capsys.readouterr()
    try:
        code = (prior_main if prog == PRIOR else track_main)(argv)
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err


def check_case(root: Path, case: str, in_subprocess: bool, capsys) -> None:
    before = tree(root)
    code, err = run_case(root, case, in_subprocess, capsys)
    _, _, expected_code, message = CASES[case]
    assert "Traceback" not in err
    assert code == expected_code, err
    assert "error:" in err and message in err, err
    assert "[layers.targets]" not in err, "names a config key that does not exist"
    assert tree(root) == before


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_gives_an_error_line_and_leaves_everything_as_it_was(region: Path, case: str, capsys) -> None:
    check_case(region, case, False, capsys)


SUBPROCESS_CASES = ["build over the DEM", "run: assignments under a file", "run on a binary CSV", "learn on an empty CSV",
                    "bad choice"]


@pytest.mark.parametrize("case", [pytest.param(c, marks=[] if c in SUBPROCESS_CASES else pytest.mark.slow) for c in CASES])
def test_bad_input_in_a_subprocess(region: Path, case: str, capsys) -> None:
    """The same battery as the installed commands run it: a fresh interpreter, stderr, exit code."""
    check_case(region, case, True, capsys)


@pytest.mark.parametrize("command", ["build", "run"])
def test_full_disk_is_an_error_naming_the_output_and_leaves_nothing(region: Path, tmp_path: Path, monkeypatch,
                                                                     capsys, command: str) -> None:
    """ENOSPC from the writer (a full disk) → an ``error:`` line naming the output; nothing written."""
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    out = tmp_path / "out"
    if command == "build":
        monkeypatch.setattr("pipeline.prior.terrain.TerrainPrior.write", full)
        code = prior_main(["-q", "build", str(region / "region.toml"), "--out", str(out / "prior.tif")])
    else:
        monkeypatch.setattr("tracker.run.write_assignments", full)  # the second output: the first is staged
        code = track_main(["run", "--prior", str(region / "prior.tif"), "--reports", str(region / "reports.csv"),
                           "--off-prior", "skip", "--out", str(out / "tracks.gpkg"), "--assignments", str(out / "a.csv")])
    err = capsys.readouterr().err
    assert code == 1 and "No space left on device" in err and str(out) in err and "Traceback" not in err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_outputs_of_one_command_are_committed_together(region: Path, tmp_path: Path) -> None:
    """run with --assignments writes both files, and the folders they need; -q after the subcommand."""
    out = tmp_path / "a" / "b"
    assert track_main(["run", "-q", "--prior", str(region / "prior.tif"), "--reports", str(region / "reports.csv"),
                       "--off-prior", "skip", "--out", str(out / "t.gpkg"), "--assignments", str(out / "a.csv")]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["a.csv", "t.gpkg"]
    assert len(pd.read_csv(out / "a.csv")) == 30


def test_build_commits_the_prior_set_and_refuses_a_folder(region: Path, tmp_path: Path, capsys) -> None:
    assert prior_main(["build", str(region / "region.toml"), "-q", "--out", str(tmp_path / "p.tif")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.qml", "p.sat.npy", "p.sat2.npy", "p.tif"]
    assert prior_main(["build", str(region / "region.toml"), "--out", str(tmp_path)]) == 1
    assert "is a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.qml", "p.sat.npy", "p.sat2.npy", "p.tif"]


@pytest.mark.parametrize("tau", ["-inf", "-1e-3", "-2.5"])
def test_negative_values_need_no_equals_sign(region: Path, tmp_path: Path, tau: str, capsys) -> None:
    """``--tau -inf`` is read as ``--tau=-inf`` (argparse alone calls it a missing argument, exit 2)."""
    def run(*tau_args: str) -> tuple[int, str]:
        code = track_main(["run", "--prior", str(region / "prior.tif"), "--reports", str(region / "reports.csv"),
                           "--off-prior", "skip", *tau_args, "--out", str(tmp_path / "t.gpkg")])
        return code, capsys.readouterr().err

    if tau == "-inf":  # S = e^{-n tau} needs a finite tau: a usage error naming --tau, in either spelling
        for tau_args in (("--tau", tau), (f"--tau={tau}",)):
            with pytest.raises(SystemExit) as exc:
                run(*tau_args)
            assert exc.value.code == 2
            assert "terrain-track run: error: argument --tau: must be a finite number, got '-inf'" in capsys.readouterr().err
        return
    assert run("--tau", tau) == run(f"--tau={tau}") == (0, "")


@pytest.mark.parametrize("command, option, value, rule", [
    ("run", "--tau", "nan", "a finite number"),
    ("run", "--poisson-mu", "-1", "a finite number > 0"),
    ("run", "--q", "-0.1", "a finite number >= 0"),
    ("run", "--velocity-std", "0", "a finite number > 0"),
    ("run", "--gamma", "inf", "a finite number > 0"),
    ("run", "--ellipse-prob", "1.5", "a finite number > 0 and < 1"),
    ("run", "--sweeps", "-1", "an integer >= 0"),
    ("run", "--samples", "0", "an integer >= 1"),
    ("run", "--seed", "-3", "an integer >= 0"),
    ("experiment", "--datasets", "1", "an integer >= 2"),
    ("experiment", "--reports", "0", "an integer >= 1"),
    ("experiment", "--workers", "-1", "an integer >= 1"),
    ("experiment", "--azimuth-std-mrad", "nan", "a finite number > 0"),
    ("heldout", "--block-m", "0", "a finite number > 0"),
    ("heldout", "--folds", "1", "an integer >= 2"),
    ("heldout", "--range-std-m", "-12", "a finite number > 0"),
    ("simulate", "--seed", "-1", "an integer >= 0"),
])
def test_bad_numbers_are_usage_errors_naming_the_option(tmp_path: Path, capsys, command: str, option: str,
                                                        value: str, rule: str) -> None:
    """Every numeric option refuses a value out of its range before anything is read or written (exit 2)."""
    with pytest.raises(SystemExit) as exc:
        track_main([command, "--prior", str(tmp_path / "missing.tif"), option, value, "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"error: argument {option}: must be {rule}, got '{value}'" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_bad_tile_is_a_usage_error(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        prior_main(["build", str(tmp_path / "region.toml"), "--tile", "0", "--out", str(tmp_path / "p.tif")])
    assert exc.value.code == 2
    assert "error: argument --tile: must be an integer >= 1, got '0'" in capsys.readouterr().err


def test_attach_negative_values_leaves_options_and_positionals() -> None:
    argv = ["-q", "run", "--tau", "-3:3:0.25", "--quiet", "--q", "-1", "x", "-nan"]
    assert attach_negative_values(argv) == ["-q", "run", "--tau=-3:3:0.25", "--quiet", "--q=-1", "x", "-nan"]


def test_warnings_are_one_line_without_a_source_line(capsys) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="t")
    parser.add_argument("-q", "--quiet", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("go", parents=[quiet_parent()])
    p.set_defaults(func=lambda args: warnings.warn(f"layer is empty (quiet={args.quiet})", stacklevel=1))
    assert run_cli("t", parser, ["go", "-q"]) == 0
    assert capsys.readouterr().err == "t: warning: layer is empty (quiet=True)\n"


def test_command_outputs_refuses_a_hard_link_to_an_input(tmp_path: Path) -> None:
    src = tmp_path / "in.csv"
    src.write_text("x\n")
    os.link(src, tmp_path / "hard.csv")
    with pytest.raises(OutputError, match="is an input"), command_outputs(
        [Output("--out", tmp_path / "hard.csv")], {"--reports": [src]}
    ):
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hard.csv", "in.csv"]


def test_command_outputs_refuses_a_sidecar_that_would_replace_an_input(tmp_path: Path) -> None:
    """A file a writer puts beside its output is checked against the inputs before anything is committed."""
    (tmp_path / "in.sat.npy").write_text("input")
    with pytest.raises(OutputError, match="would replace an input"), command_outputs(
        [Output("--out", tmp_path / "new" / "a.txt"), Output("--prior", tmp_path / "in.tif")], {"prior": [tmp_path / "in.sat.npy"]}
    ) as out:
        out.path("--out").write_text("a")
        out.path("--prior").with_suffix(".sat.npy").write_text("clobber")
    assert (tmp_path / "in.sat.npy").read_text() == "input"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.sat.npy"]


def test_command_outputs_removes_stale_stages_of_killed_runs(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".terrain-stage-{int(dead.stdout)}-abc"
    stale.mkdir()
    (stale / "x.tif").write_text("half")
    with command_outputs([Output("--out", tmp_path / "x.tif")], {}) as out:
        out.path("--out").write_text("whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.tif"]
    assert (tmp_path / "x.tif").read_text() == "whole"
