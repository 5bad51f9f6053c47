"""The lazy, tiled pyramid on a 50,000 x 50,000 prior, against the whole pyramid on a small one.

Run: ``python -m bench.run [--quick] lazy``.

The large prior is never written: its cells come from :class:`RepeatedTile`, one 2,048² synthetic
tile (bench_terrace's prior pattern) read window by window as a mosaic of 50,000² cells (a 10 GB
float32 raster if it were stored; its whole pyramid would take ~40 GiB). A stream of report Gaussians
(σ 1-8 cells, eccentricity up to 3, any angle) from targets gathered in clusters spread over the whole
square is integrated in blocks of 10,000, as the tracker sends them, in a child process whose peak RSS
is the whole job's. Baseline in the same run: the whole in-memory pyramid on a 2,000² prior with the
same Gaussians, its rate measured after its first call (pyramid built, as bench_terrace reports it).

Rows: the cold stream (every tile built on first use, included), the same stream again (tiles
cached: the look-up cost alone), tiles built, peak memory. Goal: >= 50 % of the small-prior rate,
<= 4 GiB peak.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOAL_RATIO = 0.5
GOAL_GIB = 4.0
BLOCK = 10_000


class RepeatedTile:
    """A (rows, cols) cell source that repeats one tile; windows are read on demand (a :class:`CellSource`)."""

    def __init__(self, tile: np.ndarray, shape: tuple[int, int]) -> None:
        self.tile = np.asarray(tile, dtype=np.float32)
        self.shape = shape

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = (np.arange(*k.indices(n)) for k, n in zip(key, self.shape, strict=True))
        return self.tile[np.ix_(rows % self.tile.shape[0], cols % self.tile.shape[1])]


def stream(shape: tuple[int, int], n_reports: int, n_clusters: int, cluster_cells: float, seed: int = 0):
    """Report Gaussians in pixel units: ``n_reports`` around targets in ``n_clusters`` clusters (σ
    ``cluster_cells``) whose centres are uniform over the grid; report σ 1-8 cells, eccentricity <= 3."""
    rng = np.random.default_rng(seed)
    h, w = shape
    centres = np.column_stack([rng.uniform(0, w, n_clusters), rng.uniform(0, h, n_clusters)])
    which = rng.integers(0, n_clusters, n_reports)
    pos = centres[which] + rng.normal(0.0, cluster_cells, (n_reports, 2))
    major = np.exp(rng.uniform(0.0, np.log(8.0), n_reports))
    minor = np.maximum(major / np.exp(rng.uniform(0.0, np.log(3.0), n_reports)), 1.0)
    th = rng.uniform(0, np.pi, n_reports)
    c, s = np.cos(th), np.sin(th)
    cuu = c * c * major**2 + s * s * minor**2
    cvv = s * s * major**2 + c * c * minor**2
    cuv = c * s * (major**2 - minor**2)
    return pos[:, 0], pos[:, 1], cuu, cuv, cvv


def _blocks(f, px) -> float:
    """Seconds to integrate ``px`` in blocks of BLOCK."""
    t = time.perf_counter()
    for lo in range(0, px[0].size, BLOCK):
        f(*(a[lo : lo + BLOCK] for a in px))
    return time.perf_counter() - t


def child(n: int, n_reports: int, n_clusters: int, cluster_cells: float, cache_gib: float) -> dict:
    """Both measurements in this process: the small whole pyramid, then the lazy one on the n² mosaic."""
    from bench.bench_terrace import synthetic_prior
    from tracker.integrate import lazy, scalespace

    tile = synthetic_prior(2048).density
    small = synthetic_prior(2000)
    px_small = stream(small.grid.shape, n_reports, n_clusters, cluster_cells, seed=1)
    scalespace.integrate_pixels(small, *(a[:BLOCK] for a in px_small), False)  # compile, build its levels
    scalespace.integrate_pixels(small, *px_small, False)  # all levels the stream needs
    whole_s = _blocks(lambda *a: scalespace.integrate_pixels(small, *a, False), px_small)
    source = RepeatedTile(tile, (n, n))
    pyr = lazy.LazyPyramid(source, cache_bytes=int(cache_gib * 2**30))
    pyr.integrate_pixels(*stream((4096, 4096), 1000, 4, cluster_cells, seed=2))  # compile (another corner's tiles)
    built0 = pyr.tiles_built
    px = stream((n, n), n_reports, n_clusters, cluster_cells)
    cold_s = _blocks(pyr.integrate_pixels, px)
    built = pyr.tiles_built - built0
    warm_s = _blocks(pyr.integrate_pixels, px)
    return {
        "n": n, "n_reports": n_reports, "n_clusters": n_clusters, "cluster_cells": cluster_cells,
        "cache_gib": cache_gib, "levels": pyr.levels_built(),
        "whole_small_per_s": n_reports / whole_s, "lazy_cold_per_s": n_reports / cold_s,
        "lazy_warm_per_s": n_reports / warm_s, "tiles_built": built, "tiles_rebuilt_warm": pyr.tiles_built - built0 - built,
        "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "load_average": list(os.getloadavg()),
    }


def run(quick: bool = False) -> dict:
    n, n_reports = (10_000, 100_000) if quick else (50_000, 1_000_000)
    args = [str(n), str(n_reports), "100", "20", "2.0"]
    proc = subprocess.run([sys.executable, "-m", "bench.bench_lazy", *args], cwd=ROOT, capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"lazy-pyramid child failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    cold, warm = out["lazy_cold_per_s"] / out["whole_small_per_s"], out["lazy_warm_per_s"] / out["whole_small_per_s"]
    out.update(ratio_cold=cold, ratio_warm=warm, goal_ratio=GOAL_RATIO, goal_gib=GOAL_GIB)
    ok_mem = out["peak_rss_gib"] <= GOAL_GIB
    where = f"{out['n_clusters']} clusters (σ {out['cluster_cells']:.0f} cells) spread over the grid"
    table = [
        {"what": f"lazy pyramid {n:,}² prior, {n_reports:,} report Gaussians in {where}, first pass (tiles built)",
         "value": f"{out['lazy_cold_per_s']:,.0f}/s = {cold:.2f}x the whole 2,000² pyramid ({out['whole_small_per_s']:,.0f}/s); "
                  f"{out['tiles_built']:,} tiles; {out['peak_rss_gib']:.2f} GiB peak",
         "goal": ">= 0.5x, <= 4 GiB", "ok": bool(cold >= GOAL_RATIO and ok_mem)},
        {"what": f"lazy pyramid {n:,}², the same stream again (tiles cached)",
         "value": f"{out['lazy_warm_per_s']:,.0f}/s = {warm:.2f}x the whole pyramid; {out['tiles_rebuilt_warm']} rebuilt",
         "goal": ">= 0.5x, <= 4 GiB", "ok": bool(warm >= GOAL_RATIO and ok_mem)},
    ]
    return {"lazy": out, "table": table}


if __name__ == "__main__":
    n, reports, clusters, cells, cache = sys.argv[1:6]
    print(json.dumps(child(int(n), int(reports), int(clusters), float(cells), float(cache))))
