"""Gate inputs validated once and kept in the kernels' layout.

:meth:`Scene.validate` checks everything :func:`tracker.gating.gate.gate` is given (shapes,
finiteness, positive-definite covariances through :func:`tracker.types.reports.check_gaussians`,
times and process noise) and raises ``ValueError`` naming the argument and the bad indices.
:meth:`Scene.assume_valid` builds the same layout without any check, for callers that validated
their arrays already (the association's hypotheses and reports); pass the result to
:func:`tracker.gating.gate.gate_checked`. Positions in metres, times in seconds, velocities in m/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tracker.types.reports import check_gaussians


@dataclass(frozen=True)
class Scene:
    """Tracks and reports in kernel layout: ``tpos`` (N, d) m, ``tvel`` (N, d) m/s (zeros when
    static), ``tcov`` (N, s, s) state covariances (s = d static, 2d moving), ``ttime`` (N,) s,
    ``tq`` (N,) m²/s³, ``rpos`` (M, d) m, ``rcov`` (M, d, d) m², ``rtime`` (M,) s; d in {2, 3}."""

    dim: int
    moving: bool
    tpos: np.ndarray
    tvel: np.ndarray
    tcov: np.ndarray
    ttime: np.ndarray
    tq: np.ndarray
    rpos: np.ndarray
    rcov: np.ndarray
    rtime: np.ndarray

    @classmethod
    def validate(cls, track_means, track_covs, report_means, report_covs, report_times=None,
                 track_times=0.0, process_noise=0.0) -> Scene:
        """The checked scene of :func:`tracker.gating.gate.gate`'s arguments (same meanings)."""
        tm = _as_float("track_means", track_means, 2)
        tc = _as_float("track_covs", track_covs, 3)
        rm = _as_float("report_means", report_means, 2)
        rc = _as_float("report_covs", report_covs, 3)
        dim = rm.shape[1]
        if dim not in (2, 3):
            raise ValueError(f"report_means must be (M, 2) or (M, 3), got shape {rm.shape}")
        if rc.shape != (rm.shape[0], dim, dim):
            raise ValueError(f"report_covs must have shape {(rm.shape[0], dim, dim)}, got {rc.shape}")
        if tm.shape[1] not in (dim, 2 * dim):
            raise ValueError(f"track_means must be (N, {dim}) or (N, {2 * dim}) for {dim}-D reports,"
                             f" got shape {tm.shape}")
        sd = tm.shape[1]
        if tc.shape != (tm.shape[0], sd, sd):
            raise ValueError(f"track_covs must have shape {(tm.shape[0], sd, sd)}, got {tc.shape}")
        moving = sd == 2 * dim
        nt, nr = tm.shape[0], rm.shape[0]
        if moving and report_times is None:
            raise ValueError("track_means carry velocities: report_times= (M,) is required")
        check_gaussians(tm, tc, "gate", means_name="track_means", covs_name="track_covs")
        check_gaussians(rm, rc, "gate", means_name="report_means", covs_name="report_covs")
        if not moving:
            return cls.assume_valid(tm, tc, rm, rc)
        rtime = _as_float("report_times", report_times, 1)
        if rtime.shape != (nr,):
            raise ValueError(f"report_times must have shape ({nr},), got {rtime.shape}")
        _check_finite("report_times", rtime)
        ttime = np.broadcast_to(np.asarray(track_times, float), (nt,))
        _check_finite("track_times", ttime)
        tq = np.broadcast_to(np.asarray(process_noise, float), (nt,))
        bad = ~(np.isfinite(tq) & (tq >= 0.0))
        if bad.any():
            raise ValueError(f"process_noise must be finite and >= 0; bad at tracks "
                             f"{np.flatnonzero(bad)[:10]}")
        return cls.assume_valid(tm, tc, rm, rc, rtime, ttime, tq)

    @classmethod
    def assume_valid(cls, track_means, track_covs, report_means, report_covs, report_times=None,
                     track_times=0.0, process_noise=0.0) -> Scene:
        """The scene of arguments the caller has already validated (float arrays of consistent
        shapes, finite, positive-definite covariances, ``report_times`` given for moving tracks):
        layout only, no check."""
        tm = np.ascontiguousarray(track_means, dtype=float)
        rm = np.ascontiguousarray(report_means, dtype=float)
        nt, nr, dim = tm.shape[0], rm.shape[0], rm.shape[1]
        moving = tm.shape[1] == 2 * dim
        if moving:
            rtime = np.ascontiguousarray(report_times, dtype=float)
            ttime = np.ascontiguousarray(np.broadcast_to(np.asarray(track_times, float), (nt,)))
            tq = np.ascontiguousarray(np.broadcast_to(np.asarray(process_noise, float), (nt,)))
            tvel = np.ascontiguousarray(tm[:, dim:])
        else:
            rtime, ttime, tq, tvel = np.zeros(nr), np.zeros(nt), np.zeros(nt), np.zeros((nt, dim))
        return cls(dim, moving, np.ascontiguousarray(tm[:, :dim]), tvel,
                   np.ascontiguousarray(track_covs, dtype=float), ttime, tq, rm,
                   np.ascontiguousarray(report_covs, dtype=float), rtime)


def _as_float(name: str, x, ndim: int) -> np.ndarray:
    a = np.ascontiguousarray(x, dtype=float)
    if a.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {a.shape}")
    return a


def _check_finite(name: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"{name} has non-finite values at indices {np.flatnonzero(bad)[:10]}")
