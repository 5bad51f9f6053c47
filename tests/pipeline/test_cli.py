"""terrain-prior end to end on the bundled region; failed runs leave no output behind."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio

from pipeline.cli import main
from pipeline.prior.terrain import TerrainPrior
from tests.pipeline.gis_helpers import REGION_TOML

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "out"
    assert main(["-q", "build", str(REGION_TOML), "--out", str(out / "prior.tif")]) == 0
    return out


def test_build_writes_a_normalised_prior(built: Path) -> None:
    prior = TerrainPrior.read(built / "prior.tif")
    assert prior.grid.shape == (700, 700) and prior.grid.crs.to_epsg() == 32734
    # float32 on disk: the sum carries float32 rounding only
    assert float(np.asarray(prior.density, dtype=np.float64).sum()) * 400.0 == pytest.approx(1.0, rel=1e-5)
    assert prior.sat[-1, -1] == pytest.approx(1.0, rel=1e-12)
    assert prior.model["provenance"]["config"] == str(REGION_TOML)
    assert set(prior.model["likelihood"]) == {"water", "obstacles", "slope_class", "road_distance", "surface", "vegetation"}
    assert sorted(p.name for p in built.iterdir()) == ["prior.qml", "prior.sat.npy", "prior.sat2.npy", "prior.tif"]


def test_show_draws_prior_and_features(built: Path, capsys) -> None:
    """The Makefile's command: the features come from the region config the prior records."""
    assert main(["-q", "show", str(built / "prior.tif"), "--png", str(built / "prior.png"),
                 "--features-png", str(built / "features.png")]) == 0
    for name in ("prior.png", "features.png"):
        data = (built / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 20_000
    assert "features.png" in capsys.readouterr().out


def test_features_writes_one_geotiff_per_feature(tmp_path: Path) -> None:
    out = tmp_path / "features"
    assert main(["-q", "features", str(REGION_TOML), "--out", str(out)]) == 0
    names = {"water", "obstacles", "road_distance", "slope", "slope_class", "surface", "vegetation"}
    assert {p.name for p in out.iterdir()} == {f"{n}{ext}" for n in names for ext in (".tif", ".qml")}
    with rasterio.open(out / "road_distance.tif") as src:
        d = src.read(1)
        assert src.tags()["UNITS"] == "m" and src.crs.to_epsg() == 32734
    with rasterio.open(out / "water.tif") as src:
        water = src.read(1)
    with rasterio.open(out / "slope.tif") as src:
        slope = src.read(1)
        assert src.tags()["UNITS"] == "deg"
    assert d.min() == 0 and (d >= 0).all() and np.isfinite(slope).all() and (slope >= 0).all() and (slope < 90).all()
    assert set(np.unique(water)) == {0, 1}


def test_model_override(tmp_path: Path) -> None:
    model = tmp_path / "model.toml"
    model.write_text('[likelihood.water]\ntype = "categorical"\nvalues = { dry = 1.0, water = 0.0 }\n')
    out = tmp_path / "prior.tif"
    assert main(["-q", "build", str(REGION_TOML), "--model", str(model), "--out", str(out)]) == 0
    prior = TerrainPrior.read(out)
    assert set(prior.model["likelihood"]) == {"water"} and prior.model["provenance"]["model"] == str(model)
    nonzero = np.asarray(prior.density) > 0
    assert len(np.unique(np.asarray(prior.density)[nonzero])) == 1  # uniform off the water


def failing_config(tmp_path: Path) -> Path:
    """The bundled region with its DEM missing: features start, then the slope step fails."""
    folder = tmp_path / "region"
    shutil.copytree(REGION_TOML.parent, folder, ignore=shutil.ignore_patterns("dem.tif", "*.py", "__pycache__"))
    return folder / "region.toml"


@pytest.mark.parametrize("command", ["build", "features"])
def test_failed_run_leaves_no_output(tmp_path: Path, capsys, command: str) -> None:
    config = failing_config(tmp_path)
    out = tmp_path / "out"
    target = out / "prior.tif" if command == "build" else out
    assert main(["-q", command, str(config), "--out", str(target)]) == 1
    err = capsys.readouterr().err
    assert "dem.tif" in err and "[layers.dem]" in err and "file not found" in err
    assert not out.exists() or list(out.iterdir()) == []


def test_show_without_region_for_features(tmp_path: Path, built: Path, capsys) -> None:
    prior = TerrainPrior.read(built / "prior.tif")
    bare = TerrainPrior(prior.grid, np.asarray(prior.density), np.asarray(prior.sat), np.asarray(prior.sat2), {})
    bare.write(tmp_path / "bare.tif")
    assert main(["-q", "show", str(tmp_path / "bare.tif"), "--png", str(tmp_path / "p.png"),
                 "--features-png", str(tmp_path / "f.png")]) == 1
    assert "--region" in capsys.readouterr().err
    assert not (tmp_path / "f.png").exists()


def test_bad_config_exit_code_and_message(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[region]\ncrs = "EPSG:4326"\nbounds = [20, -34, 20.1, -33.9]\n[features.x]\ntype = "slope"\nlayer = "dem"\n')
    assert main(["build", str(bad), "--out", str(tmp_path / "p.tif")]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "geographic" in err
    assert list(tmp_path.iterdir()) == [bad]


def test_console_script_entry_point(tmp_path: Path) -> None:
    exe = Path(sys.executable).parent / "terrain-prior"
    if not exe.exists():
        pytest.skip(f"{exe} not installed (pip install -e .)")
    run = subprocess.run([str(exe), "show", str(tmp_path / "none.tif"), "--png", str(tmp_path / "x.png")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 1 and "none.tif" in run.stderr and "missing" in run.stderr
