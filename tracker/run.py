"""The ``terrain-track run`` use case: reports file in, association (greedy in file order, or the batch
search / sampler over partitions started from it), tracks file out."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rasterio.crs import CRS

from common.atomic import atomic_paths
from pipeline.prior import TerrainPrior
from tracker.association.batch import BatchAssociator, batch_estimate
from tracker.association.greedy import DEFAULT_GAMMA, Tracker
from tracker.io.reports import read_reports
from tracker.io.tracks import write_assignments, write_tracks
from tracker.models.motion import MotionModel, Static
from tracker.models.sfunc import ExpS, SModel
from tracker.types.estimate import Estimate

ASSOCIATION_METHODS = ("greedy", "batch")
DEFAULT_SWEEPS = 20
"""Batch sweeps when ``sweeps`` is not given: annealed Gibbs sweeps (map mode) or burn-in sweeps (sampling)."""
SPLIT_MERGE = 2
"""Split–merge proposals per sweep in sampling mode (docs/batch.md)."""


@dataclass(frozen=True)
class TrackRun:
    """What a run wrote: ``assignments`` (K,) track index per report (-1 skipped off the prior),
    ``estimate`` the tracks, ``n_detected`` N̂_D. Batch only (else None): ``membership`` (K,) each
    report's posterior probability of belonging to its track (1 in map mode, NaN where skipped),
    and ln p(Λ|Z) (+const, under the associating model: UU for UT) of the written partition
    (``log_posterior``) and of greedy's (``greedy_log_posterior``)."""

    assignments: np.ndarray
    estimate: Estimate
    n_detected: int
    membership: np.ndarray | None = None
    log_posterior: float | None = None
    greedy_log_posterior: float | None = None


def check_method(method: str, motion: MotionModel, sweeps: int | None, samples: int | None, seed: int | None) -> None:
    """Reject options that do not fit ``method``: batch options with greedy, motion with batch, bad counts."""
    if method not in ASSOCIATION_METHODS:
        raise ValueError(f"method must be one of {ASSOCIATION_METHODS}, got {method!r}")
    given = [f"--{name}" for name, v in (("sweeps", sweeps), ("samples", samples), ("seed", seed)) if v is not None]
    if method == "greedy" and given:
        raise ValueError(f"--method greedy takes no {', '.join(given)} (batch options)")
    if method == "batch" and not isinstance(motion, Static):
        raise ValueError("--method batch needs static targets (--motion static); constant velocity is greedy only")
    if sweeps is not None and sweeps < 0:
        raise ValueError(f"--sweeps must be >= 0, got {sweeps}")
    if samples is not None and samples < 1:
        raise ValueError(f"--samples must be >= 1, got {samples}")


def track_files(
    prior_path: str | Path,
    reports_path: str | Path,
    out: str | Path,
    variant: str = "TT",
    s_model: SModel | None = None,
    motion: MotionModel | None = None,
    layer: str | None = None,
    ellipse_prob: float = 0.95,
    assignments_csv: str | Path | None = None,
    method: str = "greedy",
    sweeps: int | None = None,
    samples: int | None = None,
    seed: int | None = None,
    progress: bool = False,
    **tracker_kwargs,
) -> TrackRun:
    """Read the prior and the reports, associate, write the tracks GeoPackage ``out`` (and, optionally,
    the track index of every report as CSV, with the batch methods' membership probability).

    ``method="greedy"``: paper 1's tracker in file order. ``method="batch"``: the batch associator
    from greedy's partition (of the reports greedy kept), map mode with ``sweeps`` annealed sweeps
    (default :data:`DEFAULT_SWEEPS`), or sampling mode when ``samples`` is given (``sweeps`` burn-in
    sweeps, :data:`SPLIT_MERGE` split–merge proposals per sweep), tracks from the best partition
    visited; UT associates as UU and estimates with r. ``seed`` (batch, default 0) seeds the chain;
    ``progress`` shows tqdm over sweeps. ``s_model`` defaults to S = e^{-nτ} with τ = -1.7;
    ``tracker_kwargs`` go to :class:`~tracker.association.greedy.Tracker` (``gamma`` and
    ``integrator`` also to the batch associator). A reports file with a CRS must use the prior's.
    Errors about the reports name ``reports_path``; the outputs are committed together or not at all."""
    motion = motion or Static()
    check_method(method, motion, sweeps, samples, seed)
    s_model = s_model or ExpS(-1.7)
    prior = TerrainPrior.read(prior_path)
    reports, crs = read_reports(reports_path, layer)
    if crs is not None and CRS.from_user_input(crs) != prior.grid.crs:
        raise ValueError(
            f"{reports_path}: CRS {crs} differs from the prior's {prior.grid.crs.to_string()}; reproject the reports"
        )
    tracker = Tracker(prior, variant, s_model=s_model, motion=motion, **tracker_kwargs)
    try:
        assignments = tracker.update(reports)
    except ValueError as exc:  # the tracker names rows; say which file they are in
        raise ValueError(f"{reports_path}: {exc}") from exc
    if method == "greedy":
        result = tracker.result(assignments)
        run = TrackRun(assignments, result.estimate, result.n_detected)
    else:
        associator = BatchAssociator(
            prior, "UU" if variant == "UT" else variant, s_model=s_model, mode="map" if samples is None else "sample",
            gamma=tracker_kwargs.get("gamma", DEFAULT_GAMMA), anneal=DEFAULT_SWEEPS if sweeps is None else sweeps,
            burn_in=DEFAULT_SWEEPS if sweeps is None else sweeps, samples=samples or 1,
            split_merge=0 if samples is None else SPLIT_MERGE, seed=0 if seed is None else seed, progress=progress,
            integrator=tracker_kwargs.get("integrator"),
        )
        run = _batch_run(prior, reports, assignments, associator, variant)
    outputs = [out] if assignments_csv is None else [out, assignments_csv]
    with atomic_paths(*outputs) as temps:
        write_tracks(temps[0], run.estimate, prior.grid.crs.to_wkt(), ellipse_prob)
        if assignments_csv is not None:
            write_assignments(temps[1], run.assignments, run.membership)
    return run


def _batch_run(prior: TerrainPrior, reports, greedy: np.ndarray, associator: BatchAssociator, variant: str) -> TrackRun:
    """Batch association of the reports greedy kept (``greedy`` >= 0), from greedy's partition."""
    kept = np.flatnonzero(greedy >= 0)
    sub = reports.subset(kept)
    res = associator.fit(sub, init=greedy[kept])
    labels = np.full(len(greedy), -1, np.int64)
    labels[kept] = res.labels
    membership = np.full(len(greedy), np.nan)
    membership[kept] = res.membership
    estimate = batch_estimate(prior, sub, res.labels, "UU" if variant == "UU" else "TT", associator.integrator)
    return TrackRun(labels, estimate, res.n_detected, membership, res.log_posterior, res.greedy_log_posterior)
