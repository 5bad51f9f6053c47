"""Pipeline benchmarks: the bundled 700 x 700 build, a 10,000 x 10,000 grid, and rectangle sums.

Run: ``.venv/bin/python -m bench.run pipeline`` (``--quick`` for small sizes), or
``.venv/bin/python -c "import bench.bench_pipeline as b, json; print(json.dumps(b.run(quick=True), indent=1))"``.

1. ``terrain_data/region.toml`` end to end (features + prior), with the time spent in layer reads
   (file I/O and reprojection onto the grid) measured separately and subtracted. Goal: < 1 s.
2. A synthetic N x N grid (N = 10,000; 2,000 quick) in a child process, so its peak RSS is the whole
   job's: rasterize roads and lakes, distance to roads, Horn slope (over its DEM), slope classes, the
   likelihood product (in bands, the slope freed), normalisation into r's buffer and both summed-area
   tables, as ``pipeline.build.region`` does them. Goal: < 60 s and < 8 GiB (the in-memory build's
   issue-18 goal, <= 10 s and <= 3 GiB with reads and the write, is bench_dask's row).
   Baselines on a smaller grid in the same run: scipy's ``distance_transform_edt`` and a numpy-slicing Horn slope.
3. ``TerrainPrior.rect_sum_px`` on random fractional rectangles (partly off the grid) in rectangles/s,
   against a vectorised numpy evaluation of the same bilinear summed-area-table formula. Goal: >= 20 M/s.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from bench.timing import best_time

ROOT = Path(__file__).resolve().parents[1]
GOAL_BUILD_S = 1.0
GOAL_LARGE_S = 60.0
GOAL_LARGE_GIB = 8.0
GOAL_RECTS_PER_S = 20e6


# --- 1. bundled region ------------------------------------------------------------------------

def bench_bundled_build(repeat: int) -> dict:
    import pipeline.build.region as build
    from pipeline.config.region import load_config

    config = load_config(ROOT / "terrain_data" / "region.toml")
    read_s = [0.0]
    originals = {n: getattr(build, n) for n in ("read_vector", "read_dem", "read_raster")}

    def timed(fn):
        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                read_s[0] += time.perf_counter() - t
        return wrapper

    totals, reads = [], []
    try:
        for name, fn in originals.items():
            setattr(build, name, timed(fn))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the synthetic obstacles carry one repaired geometry
            build.build_region_prior(config, progress=False)  # warm-up: numba caches, GDAL drivers
            for _ in range(repeat):
                read_s[0] = 0.0
                t = time.perf_counter()
                prior = build.build_region_prior(config, progress=False)
                totals.append(time.perf_counter() - t)
                reads.append(read_s[0])
    finally:
        for name, fn in originals.items():
            setattr(build, name, fn)
    k = int(np.argmin(np.subtract(totals, reads)))
    compute = totals[k] - reads[k]
    return {
        "shape": list(prior.grid.shape),
        "total_s": totals[k],
        "reads_s": reads[k],
        "compute_s": compute,
        "goal_s": GOAL_BUILD_S,
        "meets_goal": compute < GOAL_BUILD_S,
    }


# --- 2. large grid (child process) ---------------------------------------------------------------

def _synthetic_layers(n: int, cell: float, rng: np.random.Generator):
    """Road lines, lake polygons, a DEM (float64 m, as ``read_dem`` returns) and vegetation codes for an n x n grid."""
    import shapely

    size = n * cell
    k = max(4, n // 100)
    starts = rng.uniform(0, size, (k, 2))
    ends = starts + rng.normal(0, size / 4, (k, 2))
    roads = shapely.linestrings(np.stack([starts, (starts + ends) / 2 + rng.normal(0, size / 20, (k, 2)), ends], 1))
    lakes = shapely.buffer(shapely.points(rng.uniform(0, size, (k // 2, 2))), rng.uniform(cell, 30 * cell, k // 2))
    x = (np.arange(n, dtype=np.float64) + 0.5) * cell
    wave = 2 * np.pi / size
    dem = 80 * np.sin(3 * wave * x)[None, :] + 60 * np.cos(5 * wave * x)[:, None]
    dem += 40 * np.sin(11 * wave * x)[None, :] * np.sin(7 * wave * x)[:, None]
    coarse = rng.integers(1, 5, (n // 50 + 1, n // 50 + 1)).astype(np.int16)
    vegetation = np.repeat(np.repeat(coarse, 50, 0), 50, 1)[:n, :n]
    return roads, lakes, dem, vegetation


def large_grid_child(n: int) -> dict:
    """Features + prior on an n x n grid of 20 m cells; timings per step and this process's peak RSS."""
    from affine import Affine

    from bench.timing import peak_gib
    from pipeline.build.region import _likelihood
    from pipeline.features import rasterize
    from pipeline.features.distance import distance_m
    from pipeline.features.slope import slope_classes, slope_deg
    from pipeline.features.stack import Feature, FeatureStack
    from pipeline.gis.grid import Grid
    from pipeline.prior.likelihood import (
        CategoricalLikelihood,
        LikelihoodModel,
        RoadDistanceLikelihood,
    )
    from pipeline.prior.terrain import TerrainPrior

    cell = 20.0
    grid = Grid("EPSG:32734", Affine(cell, 0, 0, 0, -cell, n * cell), n, n)
    roads, lakes, dem, vegetation = _synthetic_layers(n, cell, np.random.default_rng(0))
    # compile the numba kernels outside the timings
    distance_m(np.eye(8, dtype=bool), 1.0, 1.0)
    slope_deg(np.eye(8), 1.0, 1.0)
    TerrainPrior.uniform(Grid(grid.crs, grid.transform, 4, 4))

    steps: dict[str, float] = {}
    cpu: dict[str, float] = {}

    def step(name, fn, *args, **kwargs):
        t, c = time.perf_counter(), time.process_time()
        out = fn(*args, **kwargs)
        steps[name] = time.perf_counter() - t
        cpu[name] = time.process_time() - c
        return out

    stack = FeatureStack(grid)
    road_mask = step("rasterize roads", rasterize.mask, roads, grid, all_touched=True)
    water = step("rasterize lakes", rasterize.mask, lakes, grid)
    # float64 throughout and the slope over its DEM, as pipeline.build.region makes them: the memory
    # figure is the real build's
    dist = step("distance to roads", distance_m, road_mask, cell, cell)
    del road_mask
    slope = step("slope", slope_deg, dem, cell, cell, in_place=True)
    del dem
    classes = step("slope classes", slope_classes, slope, [4, 8, 12])
    stack.add(Feature("water", water.view(np.int8), "categorical", labels={0: "dry", 1: "water"}))
    stack.add(Feature("road_distance", dist, "continuous", units="m"))
    stack.add(Feature("slope_class", classes, "categorical", labels={0: "<4", 1: "4-8", 2: "8-12", 3: ">=12"}))
    stack.add(Feature("vegetation", vegetation, "categorical",
                      labels={1: "grass", 2: "shrub", 3: "forest", 4: "bare"}))
    model = LikelihoodModel({
        "water": CategoricalLikelihood({"dry": 1.0, "water": 0.0}),
        "road_distance": RoadDistanceLikelihood(100.0, 0.1),
        "slope_class": CategoricalLikelihood({"<4": 1.0, "4-8": 0.7, "8-12": 0.35, ">=12": 0.1}),
        "vegetation": CategoricalLikelihood({"grass": 1.0, "shrub": 0.7, "forest": 0.5, "bare": 0.8}),
    })
    del slope  # no table reads it once its classes exist (build_region_prior frees it too)
    r = step("likelihood product", _likelihood, stack, model)
    del stack, dist, water, classes, vegetation  # the real build frees its features before normalising
    prior = step("normalise + SATs", TerrainPrior.from_array, r, grid, reuse=True)
    total_mass = float(prior.sat[-1, -1])
    return {
        "n": n,
        "steps_s": steps,
        "total_s": sum(steps.values()),
        "steps_cpu_s": cpu,
        "total_cpu_s": sum(cpu.values()),
        "load_average": list(os.getloadavg()),
        "peak_rss_gib": peak_gib(),  # VmHWM: ru_maxrss would carry over the bench parent's peak
        "total_mass": total_mass,
    }


def bench_large_grid(n: int) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "bench.bench_pipeline", "--large", str(n)],
        cwd=ROOT, capture_output=True, text=True, check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"large-grid child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["goal_s"], out["goal_gib"] = GOAL_LARGE_S, GOAL_LARGE_GIB
    out["meets_goal"] = bool(out["total_s"] < GOAL_LARGE_S and out["peak_rss_gib"] < GOAL_LARGE_GIB)
    # CPU seconds bound the wall time on idle cores (the steps are serial or parallel, never waiting on I/O)
    out["meets_goal_cpu"] = bool(out["total_cpu_s"] < GOAL_LARGE_S and out["peak_rss_gib"] < GOAL_LARGE_GIB)
    if n != 10_000:
        out["note"] = f"quick size; 10,000 x 10,000 has {(10_000 / n) ** 2:.0f}x the cells"
    return out


def _horn_numpy(dem: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Baseline: Horn's slope with numpy slicing on an edge-extrapolated copy (no NaN handling)."""
    p = np.pad(dem, 1, mode="reflect", reflect_type="odd")
    gx = ((p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[1:-1, :-2] + p[2:, :-2])) / (8 * dx)
    gy = ((p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[:-2, 1:-1] + p[:-2, 2:])) / (8 * dy)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def bench_feature_baselines(n: int, repeat: int) -> dict:
    from scipy.ndimage import distance_transform_edt

    from pipeline.features.distance import distance_m
    from pipeline.features.slope import slope_deg

    roads, _, dem, _ = _synthetic_layers(n, 20.0, np.random.default_rng(1))
    mask = np.random.default_rng(2).random((n, n)) < 2e-4
    distance_m(mask[:8, :8], 1.0, 1.0)
    slope_deg(dem[:8, :8], 1.0, 1.0)
    t_ours, d = best_time(lambda: distance_m(mask, 20.0, 20.0), repeat)
    t_scipy, ref = best_time(lambda: distance_transform_edt(~mask, sampling=(20.0, 20.0)), repeat)
    t_slope, s = best_time(lambda: slope_deg(dem, 20.0, 20.0), repeat)
    t_slope_np, s_np = best_time(lambda: _horn_numpy(dem, 20.0, 20.0), repeat)
    return {
        "n": n,
        "distance_s": t_ours,
        "scipy_edt_s": t_scipy,
        "distance_speedup": t_scipy / t_ours,
        "distance_max_abs_diff_m": float(np.abs(d - ref).max()),
        "slope_s": t_slope,
        "numpy_horn_s": t_slope_np,
        "slope_speedup": t_slope_np / t_slope,
        "slope_interior_max_abs_diff_deg": float(np.abs(s - s_np)[1:-1, 1:-1].max()),
    }


# --- 3. rectangle sums ---------------------------------------------------------------------------

def _rect_sums_numpy(sat: np.ndarray, u0, u1, v0, v1) -> np.ndarray:
    """Baseline: the same clamped bilinear summed-area-table evaluation, vectorised with numpy."""
    h, w = sat.shape[0] - 1, sat.shape[1] - 1

    def integral(u, v):
        u = np.clip(u, 0.0, w)
        v = np.clip(v, 0.0, h)
        i = np.minimum(u.astype(np.intp), w - 1)
        j = np.minimum(v.astype(np.intp), h - 1)
        fu, fv = u - i, v - j
        return (sat[j, i] * (1 - fu) + sat[j, i + 1] * fu) * (1 - fv) + (sat[j + 1, i] * (1 - fu) + sat[j + 1, i + 1] * fu) * fv

    return integral(u1, v1) - integral(u0, v1) - integral(u1, v0) + integral(u0, v0)


def bench_rect_sums(n_rects: int, repeat: int) -> dict:
    from affine import Affine

    from pipeline.gis.grid import Grid
    from pipeline.prior.terrain import TerrainPrior

    rng = np.random.default_rng(3)
    grid = Grid("EPSG:32734", Affine(20.0, 0, 0, 0, -20.0, 14000.0), 700, 700)
    prior = TerrainPrior.from_array(rng.random(grid.shape) ** 2, grid)
    # rectangles up to 40 cells a side, centres up to 20 cells beyond the grid's edges
    cu, cv = rng.uniform(-20, 720, (2, n_rects))
    hu, hv = rng.uniform(0, 20, (2, n_rects))
    u0, u1, v0, v1 = cu - hu, cu + hu, cv - hv, cv + hv
    prior.rect_sum_px(u0[:10], u1[:10], v0[:10], v1[:10])  # compile
    t_ours, ours = best_time(lambda: prior.rect_sum_px(u0, u1, v0, v1), repeat)
    cpu_ours = best_time(lambda: prior.rect_sum_px(u0, u1, v0, v1), repeat, time.process_time)[0]
    sat = np.asarray(prior.sat)
    t_np, base = best_time(lambda: _rect_sums_numpy(sat, u0, u1, v0, v1), repeat)
    return {
        "n_rects": n_rects,
        "rect_sum_px_per_s": n_rects / t_ours,
        "rect_sum_px_per_cpu_s": n_rects / cpu_ours,
        "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()),
        "numpy_per_s": n_rects / t_np,
        "speedup": t_np / t_ours,
        "max_abs_diff": float(np.abs(ours - base).max()),
        "goal_per_s": GOAL_RECTS_PER_S,
        "meets_goal": n_rects / t_ours >= GOAL_RECTS_PER_S,
        # two idle cores run two CPU-seconds per second
        "meets_goal_cpu": n_rects / cpu_ours * min(os.cpu_count() or 1, 2) >= GOAL_RECTS_PER_S,
    }


# --- entry points ----------------------------------------------------------------------------------

def run(quick: bool = False) -> dict:
    """All pipeline benchmarks; JSON-serialisable, with a ``"table"`` of summary rows."""
    repeat = 2 if quick else 3
    build = bench_bundled_build(repeat)
    large = bench_large_grid(2000 if quick else 10_000)
    base = bench_feature_baselines(1000 if quick else 3000, repeat)
    rects = bench_rect_sums(1_000_000 if quick else 4_000_000, 3 if quick else 7)
    table = [
        {"what": f"bundled build {build['shape'][0]}x{build['shape'][1]} (excl. reads)",
         "value": f"{build['compute_s']:.2f} s (+{build['reads_s']:.2f} s reads)", "goal": "< 1 s",
         "ok": build["meets_goal"]},
        {"what": f"features + prior {large['n']}x{large['n']}",
         "value": f"{large['total_s']:.1f} s ({large['total_cpu_s']:.1f} s CPU), {large['peak_rss_gib']:.2f} GiB peak",
         "goal": "< 60 s, < 8 GiB",
         "ok": large["meets_goal"], "ok on idle cores (CPU time)": large["meets_goal_cpu"]},
        {"what": f"distance transform {base['n']}x{base['n']}",
         "value": f"{base['distance_s']:.3f} s ({base['distance_speedup']:.1f}x scipy edt)", "goal": "exact", "ok": True},
        {"what": f"Horn slope {base['n']}x{base['n']}",
         "value": f"{base['slope_s']:.3f} s ({base['slope_speedup']:.1f}x numpy slicing)", "goal": "", "ok": True},
        {"what": "rect_sum_px",
         "value": f"{rects['rect_sum_px_per_s'] / 1e6:.1f} M rect/s wall ({rects['speedup']:.1f}x numpy), "
                  f"{rects['rect_sum_px_per_cpu_s'] / 1e6:.1f} M per CPU-second",
         "goal": ">= 20 M/s", "ok": rects["meets_goal"], "ok on idle cores (CPU time)": rects["meets_goal_cpu"]},
    ]
    return {"bundled_build": build, "large_grid": large, "feature_baselines": base, "rect_sums": rects, "table": table}


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--large":
        print(json.dumps(large_grid_child(int(sys.argv[2]))))
    else:
        print(json.dumps(run(quick="--quick" in sys.argv), indent=1))
