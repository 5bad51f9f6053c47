"""Scenario generator for the paper's experiment (paper 1, section 6): targets drawn from the prior
(or picked among real locations read from a vector file, :func:`simulate_points`), the central-window
selection, and reports from an airborne sensor platform.

Units: metres in the prior's CRS, seconds, radians. Everything is seeded (``numpy.random.default_rng``).

Sensor model (ours; the paper cites [BPS92] without giving it). A platform flies a straight,
level leg at ``altitude_m`` and ``speed_mps``; its closest point of approach lies ``standoff_m``
(ground distance) from the centre of the target window, in a direction drawn uniformly per
scenario. It makes one report every ``report_interval_s`` seconds, of a target picked uniformly
with replacement. It measures slant range ρ (standard deviation ``range_std_m``) and azimuth
(``azimuth_std_rad``) and projects onto flat ground, so with g the ground range:

* along the line of sight  σ_g = range_std_m · ρ / g   (d g / d ρ = ρ / g),
* across it                σ_c = azimuth_std_rad · g,

V = σ_g² u uᵀ + σ_c² w wᵀ with u the unit ground vector from platform to target and w ⟂ u.
Cross-range error grows linearly with range, so the ellipses are elongated (with the defaults
σ_c = 50–100 m against σ_g ≈ 12.5 m at 25–50 km: 4–8 : 1), perpendicular to the line of sight, and
rotate as the platform flies by. The defaults put σ_c at the scale of the prior's structure (road-side
ridges ~100 m wide) and of the target spacing, where the paper (section 5) expects the prior to matter.
V is evaluated at the true target position and reported without error, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.prior import TerrainPrior

if TYPE_CHECKING:
    from pipeline.gis.grid import Grid
from tracker.types.reports import Reports

Bounds = tuple[float, float, float, float]  # (xmin, ymin, xmax, ymax), metres


@dataclass(frozen=True)
class AirborneSensor:
    """Range/azimuth sensor on a platform flying a straight leg past the target window (see module doc)."""

    altitude_m: float = 6000.0
    standoff_m: float = 25000.0
    speed_mps: float = 150.0
    report_interval_s: float = 6.0
    range_std_m: float = 12.0
    azimuth_std_rad: float = 0.002

    def __post_init__(self) -> None:
        for name in ("altitude_m", "standoff_m", "speed_mps", "report_interval_s", "range_std_m", "azimuth_std_rad"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"AirborneSensor.{name} must be positive and finite, got {value}")

    def platform_track(self, times: np.ndarray, centre: np.ndarray, bearing_rad: float) -> np.ndarray:
        """Platform ground positions (K, 2) at ``times`` (s); closest approach at the leg's mid-time."""
        times = np.asarray(times, dtype=np.float64)
        outward = np.array([np.cos(bearing_rad), np.sin(bearing_rad)])
        along = np.array([-outward[1], outward[0]])
        t_mid = 0.5 * (times.min() + times.max()) if times.size else 0.0
        return centre + self.standoff_m * outward + np.outer((times - t_mid) * self.speed_mps, along)

    def covariances(self, platform_xy: np.ndarray, target_xy: np.ndarray) -> np.ndarray:
        """Ground-plane error covariances (K, 2, 2) in m² of targets seen from platform positions."""
        d = np.asarray(target_xy, dtype=np.float64) - np.asarray(platform_xy, dtype=np.float64)
        g = np.hypot(d[:, 0], d[:, 1])
        if np.any(g <= 0):
            raise ValueError("AirborneSensor.covariances: a target lies directly below the platform")
        u = d / g[:, None]
        w = np.stack([-u[:, 1], u[:, 0]], axis=1)
        rho = np.hypot(g, self.altitude_m)
        var_g = (self.range_std_m * rho / g) ** 2
        var_c = (self.azimuth_std_rad * g) ** 2
        return var_g[:, None, None] * u[:, :, None] * u[:, None, :] + var_c[:, None, None] * w[:, :, None] * w[:, None, :]


@dataclass(frozen=True)
class Scenario:
    """One simulated data set: the kept targets (N, 2) in metres, the reports (``truth`` indexes
    ``targets``), the platform position (K, 2) at each report, and the sampling/keep windows."""

    targets: np.ndarray
    reports: Reports
    platform: np.ndarray
    region: Bounds
    keep: Bounds
    seed: int

    @property
    def n_detected(self) -> int:
        """N_D: the number of distinct targets that made at least one report."""
        return int(np.unique(self.reports.truth).size)


def central_windows(prior: TerrainPrior, region_m: float | None, keep_fraction: float) -> tuple[Bounds, Bounds]:
    """The sampling region (a ``region_m`` square centred on the grid, clipped to it; the whole grid
    when None) snapped to whole cells, and the central keep window (``keep_fraction`` of each side)."""
    if not 0 < keep_fraction <= 1:
        raise ValueError(f"keep_fraction must be in (0, 1], got {keep_fraction}")
    grid = prior.grid
    xmin, ymin, xmax, ymax = grid.bounds
    if region_m is not None:
        if not region_m > 0:
            raise ValueError(f"region_m must be positive metres, got {region_m}")
        cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
        half = 0.5 * region_m
        # Snap to whole cells so the sampling region is exactly a set of cells.
        c0 = max(0, int(np.floor((cx - half - xmin) / grid.dx + 1e-9)))
        c1 = min(grid.width, int(np.ceil((cx + half - xmin) / grid.dx - 1e-9)))
        r0 = max(0, int(np.floor((ymax - (cy + half)) / grid.dy + 1e-9)))
        r1 = min(grid.height, int(np.ceil((ymax - (cy - half)) / grid.dy - 1e-9)))
        xmin, xmax = grid.transform.c + c0 * grid.dx, grid.transform.c + c1 * grid.dx
        ymax, ymin = grid.transform.f - r0 * grid.dy, grid.transform.f - r1 * grid.dy
    region = (xmin, ymin, xmax, ymax)
    kx = 0.5 * keep_fraction * (xmax - xmin)
    ky = 0.5 * keep_fraction * (ymax - ymin)
    cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    return region, (cx - kx, cy - ky, cx + kx, cy + ky)


def simulate(
    prior: TerrainPrior,
    seed: int,
    n_targets: int = 200,
    n_reports: int = 100,
    region_m: float | None = 14000.0,
    keep_fraction: float = 0.5,
    sensor: AirborneSensor | None = None,
) -> Scenario:
    """The paper's data set: ``n_targets`` from r over the region, keep those in the central window,
    then ``n_reports`` reports of targets picked uniformly with replacement through ``sensor``."""
    rng, region, keep = _start(prior, seed, n_targets, n_reports, region_m, keep_fraction)
    drawn = prior.sample(n_targets, rng, region)
    targets = drawn[_inside(drawn, keep)]
    if not targets.shape[0]:
        raise ValueError(f"seed {seed}: none of the {n_targets} targets fell in the keep window {keep}; raise n_targets")
    return _observe(targets, rng, n_reports, sensor or AirborneSensor(), region, keep, seed)


def simulate_points(
    prior: TerrainPrior,
    points: np.ndarray,
    seed: int,
    n_targets: int = 200,
    n_reports: int = 100,
    region_m: float | None = 14000.0,
    keep_fraction: float = 0.5,
    sensor: AirborneSensor | None = None,
    source: str = "targets file",
) -> Scenario:
    """A data set on real locations: ``n_targets`` of ``points`` (N, 2) in metres that lie in the keep
    window, picked without replacement (all of them when fewer), then reports as :func:`simulate`.
    ``source`` names the points in the error raised when the window holds none."""
    rng, region, keep = _start(prior, seed, n_targets, n_reports, region_m, keep_fraction)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    candidates = points[_inside(points, keep)]
    if not len(candidates):
        raise ValueError(f"{source}: none of its {len(points)} locations lies in the window {tuple(round(v, 1) for v in keep)} m")
    pick = rng.choice(len(candidates), size=min(n_targets, len(candidates)), replace=False)
    return _observe(candidates[np.sort(pick)], rng, n_reports, sensor or AirborneSensor(), region, keep, seed)


def _start(prior: TerrainPrior, seed: int, n_targets: int, n_reports: int, region_m: float | None,
           keep_fraction: float) -> tuple[np.random.Generator, Bounds, Bounds]:
    """The checked counts' data set generator, sampling region and keep window."""
    if n_targets < 1 or n_reports < 1:
        raise ValueError(f"n_targets and n_reports must be >= 1, got {n_targets} and {n_reports}")
    return np.random.default_rng(seed), *central_windows(prior, region_m, keep_fraction)


def _inside(points: np.ndarray, window: Bounds) -> np.ndarray:
    """Mask of points (N, 2) in the half-open window [xmin, xmax) x [ymin, ymax)."""
    x, y = points[:, 0], points[:, 1]
    return (x >= window[0]) & (x < window[2]) & (y >= window[1]) & (y < window[3])


def _observe(
    targets: np.ndarray, rng: np.random.Generator, n_reports: int, sensor: AirborneSensor, region: Bounds, keep: Bounds,
    seed: int,
) -> Scenario:
    """``n_reports`` reports of ``targets`` picked uniformly with replacement, through ``sensor`` on a leg past ``keep``."""
    truth = rng.integers(0, targets.shape[0], size=n_reports)
    times = np.arange(n_reports) * sensor.report_interval_s
    centre = np.array([0.5 * (keep[0] + keep[2]), 0.5 * (keep[1] + keep[3])])
    platform = sensor.platform_track(times, centre, rng.uniform(0.0, 2 * np.pi))
    covs = sensor.covariances(platform, targets[truth])
    chol = np.linalg.cholesky(covs)
    means = targets[truth] + np.einsum("kij,kj->ki", chol, rng.standard_normal((n_reports, 2)))
    reports = Reports.create(means, covs, times, truth)
    return Scenario(targets, reports, platform, region, keep, int(seed))


_POINTS: dict[tuple, np.ndarray] = {}  # per process: (file version, layer, grid) -> points


def file_targets(path: str | Path, layer: str | None, grid: Grid) -> np.ndarray:
    """Target locations (N, 2) in metres in ``grid``'s CRS from a vector file (points, or polygon and
    line centroids) or a CSV with x, y columns, read once per process and file version by
    :func:`pipeline.learn.read_targets` (its errors name the file and layer)."""
    path = Path(path)
    key = (str(path.resolve()), path.stat().st_mtime_ns if path.exists() else 0, layer, str(grid.crs),
           tuple(grid.transform)[:6], grid.width, grid.height)
    if key not in _POINTS:
        from pipeline.learn import read_targets  # scikit-learn loads only for file targets

        pts = read_targets(path, grid, layer)
        pts.setflags(write=False)
        _POINTS[key] = pts
    return _POINTS[key]
