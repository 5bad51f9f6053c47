"""Streaming tracker throughput: reports/second of the TT tracker (paper 1, Fig. 3) on a synthetic
prior, with the one-report-at-a-time path (block = 1) and UU measured in the same run as baselines.

Full: 1,000,000 reports of 100,000 static targets on a 100 km x 100 km prior of 40 m cells
(10 targets per km², 5-60 m report noise: about 1.5 gated candidates per report; goal < 60 s).
Quick: 100,000 reports of 10,000 targets on 32 km x 32 km (same density).
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from tracker.association.greedy import Tracker
from tracker.types.reports import Reports

CHUNK = 50_000  # reports per update() call: the stream arrives in chunks


def synthetic_prior(size_m: float, cell_m: float = 40.0) -> TerrainPrior:
    """Road-like ridges on a floor, with lakes as structural zeros."""
    g = Grid.from_bounds((0.0, 0.0, size_m, size_m), cell_m, "EPSG:32634")
    yy, xx = np.mgrid[0 : g.height, 0 : g.width].astype(np.float32)
    r = 0.1 + np.exp(-0.5 * (np.sin(xx / 37.0) * np.cos(yy / 53.0) * 6.0) ** 2)
    r[(np.sin(xx / 211.0) * np.sin(yy / 173.0)) > 0.97] = 0.0
    return TerrainPrior.from_array(r, g)


def scenario(prior: TerrainPrior, n_targets: int, n_reports: int, seed: int = 0) -> Reports:
    """Targets from the prior (cell by inverse CDF, uniform inside), reports of uniformly picked targets
    with elongated covariances (5-60 m standard deviations, random orientation)."""
    rng = np.random.default_rng(seed)
    g = prior.grid
    cdf = np.cumsum(prior.density.ravel())
    cells = np.minimum(np.searchsorted(cdf, rng.random(n_targets) * cdf[-1], side="right"), cdf.size - 1)
    rows, cols = np.divmod(cells, g.width)
    x = g.transform.c + (cols + rng.random(n_targets)) * g.dx
    y = g.transform.f - (rows + rng.random(n_targets)) * g.dy
    targets = np.stack([x, y], 1)
    truth = rng.integers(0, n_targets, n_reports)
    ang = rng.uniform(0, np.pi, n_reports)
    sd = rng.uniform(5.0, 60.0, (n_reports, 2))
    c, s = np.cos(ang), np.sin(ang)
    covs = np.empty((n_reports, 2, 2))
    covs[:, 0, 0] = c * c * sd[:, 0] ** 2 + s * s * sd[:, 1] ** 2
    covs[:, 1, 1] = s * s * sd[:, 0] ** 2 + c * c * sd[:, 1] ** 2
    covs[:, 0, 1] = covs[:, 1, 0] = c * s * (sd[:, 0] ** 2 - sd[:, 1] ** 2)
    noise = np.einsum("kij,kj->ki", np.linalg.cholesky(covs), rng.standard_normal((n_reports, 2)))
    return Reports.create(targets[truth] + noise, covs, np.arange(n_reports, dtype=float), truth)


def _stream(prior: TerrainPrior, reports: Reports, variant: str, block: int | None = None) -> tuple[float, Tracker]:
    kw = {} if block is None else {"block": block}
    tr = Tracker(prior, variant, tau=-1.7, off_prior="skip", **kw)
    t0, c0 = time.perf_counter(), time.process_time()
    for s in range(0, len(reports), CHUNK):
        tr.update(reports.subset(slice(s, s + CHUNK)))
    tr.stats_["cpu_seconds"] = time.process_time() - c0
    return time.perf_counter() - t0, tr


def run(quick: bool = False) -> dict:
    size_m, n_targets, n_reports = (32_000.0, 10_000, 100_000) if quick else (100_000.0, 100_000, 1_000_000)
    prior = synthetic_prior(size_m)
    reports = scenario(prior, n_targets, n_reports)
    warm = reports.subset(slice(0, 2000))
    for v in ("TT", "UU"):  # compile the numba kernels outside the timings
        _stream(prior, warm, v)
    t_tt, tr = _stream(prior, reports, "TT")
    t_uu, tr_uu = _stream(prior, reports, "UU")
    # Baseline: the same first reports one at a time (block = 1) and in blocks, on the same short stream.
    n_base = 2000
    head = reports.subset(slice(0, n_base))
    t_one, _ = _stream(prior, head, "TT", block=1)
    t_head, _ = _stream(prior, head, "TT")
    rate_tt, rate_uu, rate_one = n_reports / t_tt, n_reports / t_uu, n_base / t_one
    return {
        "n_reports": n_reports,
        "n_targets": n_targets,
        "tt_seconds": t_tt,
        "tt_reports_per_s": rate_tt,
        "uu_reports_per_s": rate_uu,
        "tt_one_at_a_time_reports_per_s": rate_one,
        "speedup_vs_one_at_a_time_same_reports": t_one / t_head,
        "tt_over_uu_time": t_tt / t_uu,
        "tt_cpu_seconds": tr.stats_["cpu_seconds"],
        "uu_cpu_seconds": tr_uu.stats_["cpu_seconds"],
        "n_detected": tr.n_detected_,
        "stats": tr.stats_,
        "goal_seconds": 60.0,
        "table": [
            f"tracker TT streaming {n_reports:,} reports / {n_targets:,} targets: {t_tt:.1f} s wall, "
            f"{tr.stats_['cpu_seconds']:.1f} s CPU ({rate_tt:,.0f} reports/s)",
            f"tracker UU same stream: {t_uu:.1f} s ({rate_uu:,.0f} reports/s)",
            f"tracker TT first {n_base} reports: one at a time {rate_one:,.0f} reports/s, in blocks x{t_one / t_head:.1f} faster",
        ],
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=1))
