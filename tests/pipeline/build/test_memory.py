"""Memory estimate before a build: huge grids refused at once with the figure, the memory available and
the way out (--tiled); the estimate against the measured peak of real builds; features with no table."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.build.region import (
    BuildMemoryError,
    UnusedFeatureWarning,
    available_memory_bytes,
    build_features,
    build_memory_bytes,
    build_region_prior,
    region_model,
)
from pipeline.cli import main
from pipeline.config.region import load_config, parse_config
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.terrain import PriorError
from tests.pipeline.gis_helpers import REGION_TOML, REPO, region_doc, write_config


@pytest.mark.parametrize("side_m", [2e7, 1e6])  # 1e6 x 1e6 and 50k x 50k cells of 20 m
def test_huge_grid_refused_before_allocating(tmp_path: Path, side_m: float, capsys) -> None:
    cfg_path = write_config(tmp_path / "huge.toml", region_doc(bounds=[0, 0, side_m, side_m], cell_size=20.0))
    cfg = load_config(cfg_path)
    cells = int(side_m / 20) ** 2
    assert cfg.grid.height * cfg.grid.width == cells
    t0 = time.perf_counter()
    for build in (lambda: build_region_prior(cfg, progress=False), lambda: build_features(cfg, progress=False)):
        with pytest.raises(BuildMemoryError) as info:
            build()
        msg = str(info.value)
        assert str(cfg_path) in msg and "[region]" in msg and f"{int(side_m / 20):,} x {int(side_m / 20):,} cells" in msg
        assert "GiB available" in msg and "--tiled" in msg
        need = float(msg.split("need about ")[1].split(" GiB")[0].replace(",", ""))
        assert need == pytest.approx(build_memory_bytes(cfg, "features" not in msg) / 2**30, rel=1e-3)
        assert need * 2**30 >= cells * 26  # at least the 7 feature grids themselves (5 int16 + 2 float64)
    assert time.perf_counter() - t0 < 2.0  # refused up front, not after allocating
    rc = main(["-q", "build", str(cfg_path), "--out", str(tmp_path / "p.tif")])
    err = capsys.readouterr().err
    assert rc == 1 and "terrain-prior: error:" in err and "--tiled" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == [cfg_path]


def test_refusal_follows_the_memory_available(monkeypatch, tmp_path: Path) -> None:
    """The same grid is built or refused as the available memory is above or below the estimate."""
    import pipeline.build.region as region

    cfg = load_config(write_config(tmp_path / "r.toml", region_doc(cell_size=200.0)))
    need = build_memory_bytes(cfg)
    monkeypatch.setattr(region, "available_memory_bytes", lambda: need - 1)
    with pytest.raises(BuildMemoryError, match=f"{(need - 1) / 2**30:,.1f} GiB available"):
        build_region_prior(cfg, progress=False)
    monkeypatch.setattr(region, "available_memory_bytes", lambda: need)
    assert build_region_prior(cfg, progress=False).grid.shape == (70, 70)


def test_available_memory_is_capped_by_an_address_space_limit() -> None:
    """Under ``ulimit -v`` the figure is what the limit leaves, not the machine's free memory."""
    code = ("import resource, psutil\n"
            "from pipeline.build.region import available_memory_bytes\n"
            "vms = psutil.Process().memory_info().vms\n"
            "resource.setrlimit(resource.RLIMIT_AS, (vms + (300 << 20), resource.RLIM_INFINITY))\n"
            "print(available_memory_bytes())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert 0 < int(out.stdout) <= 300 << 20
    assert available_memory_bytes() > 300 << 20  # this machine, unlimited


_PEAK = """
import re, sys
def vm(key):  # kB in /proc/self/status
    return int(re.search(key + r":\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) * 1024
open("/proc/self/clear_refs", "w").write("5")  # reset the peak (a forked child starts with its parent's)
base = vm("VmRSS")
import os, tempfile, tomllib, warnings
from pathlib import Path
warnings.simplefilter("ignore")
from pipeline.build.region import build_memory_bytes, build_region_prior
from pipeline.config.region import parse_config
src = Path(sys.argv[1])
doc = tomllib.loads(src.read_text())
doc["region"]["cell_size"] = float(sys.argv[2])
cfg = parse_config(doc, src)
prior = build_region_prior(cfg, progress=False)
with tempfile.TemporaryDirectory() as tmp:
    prior.write(os.path.join(tmp, "p.tif"))
print(vm("VmHWM") - base, build_memory_bytes(cfg))
"""


@pytest.mark.parametrize("cell_size", [10.0, pytest.param(5.0, marks=pytest.mark.slow)])  # 2 and 8 million cells
def test_estimate_bounds_the_measured_peak(cell_size: float) -> None:
    """Oracle: the peak resident memory of a real build of the bundled region (its own process, Linux)."""
    out = subprocess.run([sys.executable, "-c", _PEAK, str(REGION_TOML), str(cell_size)],
                         capture_output=True, text=True, check=True, cwd=REPO)
    peak, estimate = map(int, out.stdout.split())
    assert 0.6 * estimate <= peak <= estimate


# ---- features with no [likelihood.*] table ---------------------------------------------------------

def test_feature_without_a_table_is_an_error(tmp_path: Path, capsys) -> None:
    doc = region_doc()
    del doc["likelihood"]["obstacles"]
    cfg_path = write_config(tmp_path / "r.toml", doc)
    cfg = load_config(cfg_path)
    with pytest.raises(PriorError) as info:
        build_region_prior(cfg, progress=False)
    msg = str(info.value)
    assert str(cfg_path) in msg and "[features.obstacles] has no [likelihood.obstacles] table" in msg
    rc = main(["-q", "build", str(cfg_path), "--out", str(tmp_path / "p.tif")])
    err = capsys.readouterr().err
    assert rc == 1 and "error:" in err and "[likelihood.obstacles]" in err and "Traceback" not in err
    assert not (tmp_path / "p.tif").exists()


def test_classes_source_needs_no_table_but_is_dropped_with_its_classes(tmp_path: Path) -> None:
    """slope has no table because slope_class bins it; without slope_class's table both are unused."""
    cfg = parse_config(region_doc(), REGION_TOML)
    assert "slope" not in cfg.model.terms and region_model(cfg) is cfg.model
    doc = region_doc()
    del doc["likelihood"]["slope_class"]
    with pytest.raises(PriorError, match=r"\[features\.slope\] has no \[likelihood\.slope\] table \(nor do \['slope_class'\]\)"):
        region_model(parse_config(doc, REGION_TOML))


def test_a_model_with_fewer_features_names_those_left_out() -> None:
    cfg = parse_config(region_doc(), REGION_TOML)
    model = LikelihoodModel({"water": cfg.model.terms["water"]})
    with pytest.warns(UnusedFeatureWarning) as record:
        assert region_model(cfg, model) is model
    msg = str(record[0].message)
    for name in ("obstacles", "road_distance", "slope", "slope_class", "surface", "vegetation"):
        assert repr(name) in msg
    assert "left out of the prior" in msg and "'water'" not in msg


def test_unused_feature_check_reaches_tiled_builds(tmp_path: Path) -> None:
    """The tiled build takes its model from region_model too: the same error, before any Dask work."""
    from pipeline.tiled.build import build_prior_tiled

    doc = region_doc()
    del doc["likelihood"]["vegetation"]
    cfg = parse_config(doc, tmp_path / "r.toml")
    with pytest.raises(PriorError, match=r"\[likelihood\.vegetation\]"):
        build_prior_tiled(cfg, tmp_path / "p.tif", None, client=None)
    assert not any(tmp_path.iterdir())


def test_every_feature_type_has_a_size() -> None:
    """The estimate knows each feature type the config accepts (a new type must say its bytes per cell)."""
    from pipeline.build.region import _FEATURE_BYTES
    from pipeline.config.region import FEATURE_TYPES

    assert set(_FEATURE_BYTES) == set(FEATURE_TYPES)
