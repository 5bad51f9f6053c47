"""The ``terrain-track run`` use case: reports file in, association in file order, tracks file out."""

from __future__ import annotations

from pathlib import Path

from rasterio.crs import CRS

from common.atomic import atomic_paths
from pipeline.prior import TerrainPrior
from tracker.association.greedy import AssociationResult, Tracker
from tracker.io.reports import read_reports
from tracker.io.tracks import write_assignments, write_tracks
from tracker.models.motion import MotionModel
from tracker.models.sfunc import ExpS, SModel


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
    **tracker_kwargs,
) -> AssociationResult:
    """Read the prior and the reports, associate in file order, write the tracks GeoPackage ``out``
    (and, optionally, the hypothesis index of every report as CSV). ``s_model`` defaults to
    S = e^{-nτ} with τ = -1.7; ``tracker_kwargs`` go to :class:`~tracker.association.greedy.Tracker`.
    A reports file with a CRS must use the prior's. Errors about the reports name ``reports_path``;
    the outputs are committed together or not at all."""
    prior = TerrainPrior.read(prior_path)
    reports, crs = read_reports(reports_path, layer)
    if crs is not None and CRS.from_user_input(crs) != prior.grid.crs:
        raise ValueError(
            f"{reports_path}: CRS {crs} differs from the prior's {prior.grid.crs.to_string()}; reproject the reports"
        )
    tracker = Tracker(prior, variant, s_model=s_model or ExpS(-1.7), motion=motion, **tracker_kwargs)
    try:
        assignments = tracker.update(reports)
    except ValueError as exc:  # the tracker names rows; say which file they are in
        raise ValueError(f"{reports_path}: {exc}") from exc
    result = tracker.result(assignments)
    outputs = [out] if assignments_csv is None else [out, assignments_csv]
    with atomic_paths(*outputs) as temps:
        write_tracks(temps[0], result.estimate, prior.grid.crs.to_wkt(), ellipse_prob)
        if assignments_csv is not None:
            write_assignments(temps[1], result.assignments)
    return result
