"""The paper's experiment sweep on Dask workers: one task per data set (seed).

A data set is the unit of work because all its variants and τ values share one simulation and one
Gram matrix of mixture-component integrals (see :mod:`tracker.study.experiment`); a sweep over many data
sets, priors or configs spreads over the cluster as those tasks. Each task is
:func:`tracker.study.experiment.run_dataset`, unchanged, so the records equal the local run's.
The prior file must be readable by every worker at the same path (a shared filesystem).
"""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd
from distributed import Client, as_completed
from tqdm.auto import tqdm

from common.dask import using_client
from pipeline.prior import TerrainPrior
from tracker.study.experiment import (
    ExperimentConfig,
    add_batch_nd,
    run_dataset,
    summarise,
    write_outputs,
)


def _one_numba_thread() -> None:
    # Worker processes already use the cores; numba's own threads would oversubscribe them.
    import numba

    numba.set_num_threads(1)


def run_experiment_dask(
    prior_path: str | os.PathLike, config: ExperimentConfig, client: Client | None = None, progress: bool = True
) -> pd.DataFrame:
    """All data sets, variants and τ values on ``client`` (default: an in-process cluster); the same
    long table as :func:`tracker.study.experiment.run_experiment` (rows sorted by seed, variant, τ)."""
    with using_client(client) as client:
        client.run(_one_numba_thread)
        seeds = config.seeds
        futures = client.map(run_dataset, [str(prior_path)] * len(seeds), seeds, config=config, pure=False)
        rows: list[dict] = []
        for fut in tqdm(as_completed(futures), total=len(futures), desc="data sets", unit="set", disable=not progress):
            rows.extend(fut.result())
        results = pd.DataFrame(rows).sort_values(["seed", "variant", "tau"], kind="stable").reset_index(drop=True)
        return add_batch_nd(results, prior_path, config, lambda fn, seeds: client.gather(client.map(fn, seeds, pure=False)))


def run_and_write_dask(
    prior_path: str | os.PathLike, out_dir: str | os.PathLike, config: ExperimentConfig,
    client: Client | None = None, progress: bool = True, title: str = "",
) -> tuple[dict, dict]:
    """As :func:`tracker.study.experiment.run_and_write`, with the data sets on Dask workers."""
    prior_path = Path(prior_path).resolve()
    TerrainPrior.read(prior_path)  # fail fast, naming the file, before any task is sent
    results = run_experiment_dask(prior_path, config, client, progress)
    summary = summarise(results, config)
    return summary, write_outputs(results, summary, out_dir, title=title or prior_path.stem)
