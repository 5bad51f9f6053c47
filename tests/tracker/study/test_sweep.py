"""The experiment sweep on a real 2-process Dask cluster equals the single-process run, record for record."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from affine import Affine

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tests.dask_helpers import shared_client
from tracker.cli import main
from tracker.study.experiment import ExperimentConfig, run_experiment
from tracker.study.simulate import AirborneSensor
from tracker.study.sweep import run_and_write_dask


@pytest.fixture(scope="module")
def prior_path(tmp_path_factory) -> str:
    """A 4 km square prior with a road-like ridge and a lake."""
    n = 200
    yy, xx = np.mgrid[0:n, 0:n]
    r = 0.15 + np.exp(-0.5 * ((xx - 0.6 * yy - 50) / 5.0) ** 2)
    r[(xx - 140) ** 2 + (yy - 60) ** 2 < 20**2] = 0.0
    grid = Grid("EPSG:32734", Affine(20.0, 0.0, 300000.0, 0.0, -20.0, 6200000.0), n, n)
    path = tmp_path_factory.mktemp("prior") / "prior.tif"
    TerrainPrior.from_array(r, grid).write(path)
    return str(path)


def config() -> ExperimentConfig:
    return ExperimentConfig(n_datasets=3, n_reports=20, taus=(-2.0, 1.5), n_targets=50, region_m=None,
                            base_seed=11, sensor=AirborneSensor(standoff_m=15000.0))


def test_dask_sweep_equals_single_process(prior_path, tmp_path):
    cfg = config()
    local = run_experiment(prior_path, cfg, workers=1, progress=False)
    summary, paths = run_and_write_dask(prior_path, tmp_path / "out", cfg, shared_client(), progress=False)
    distributed = pd.read_parquet(paths["results"]) if paths["results"].endswith(".parquet") else pd.read_csv(paths["results"])
    assert len(distributed) == cfg.n_datasets * len(cfg.variants) * len(cfg.taus)
    pd.testing.assert_frame_equal(distributed, local, check_exact=True)
    assert summary["n_datasets"] == cfg.n_datasets and (tmp_path / "out" / "summary.json").exists()


def test_missing_prior_fails_before_any_task(tmp_path):
    with pytest.raises(ValueError, match="missing"):
        run_and_write_dask(tmp_path / "nope.tif", tmp_path / "out", config(), shared_client(), progress=False)


def test_cli_scheduler_flag_runs_on_the_cluster(tmp_path):
    """`terrain-track experiment --scheduler ADDRESS` writes the same results as the local run."""
    n = 800  # 16 km: the CLI keeps the paper's 14 km target region
    yy, xx = np.mgrid[0:n, 0:n]
    grid = Grid("EPSG:32734", Affine(20.0, 0.0, 300000.0, 0.0, -20.0, 6200000.0), n, n)
    prior = tmp_path / "prior.tif"
    TerrainPrior.from_array(0.2 + np.exp(-0.5 * ((xx - yy) / 8.0) ** 2), grid).write(prior)
    args = ["experiment", "--prior", str(prior), "--datasets", "2", "--reports", "15", "--tau", "-1,1",
            "--targets", "60", "--quiet"]
    client = shared_client()
    assert main([*args, "--workers", "1", "--out", str(tmp_path / "local")]) == 0
    assert main([*args, "--scheduler", client.scheduler.address, "--out", str(tmp_path / "dask")]) == 0
    local, dask = (pd.read_parquet(tmp_path / d / "results.parquet") for d in ("local", "dask"))
    pd.testing.assert_frame_equal(dask, local, check_exact=True)
