"""Make the synthetic 14 km x 14 km region (20 m cells, EPSG:32734) with a fixed seed.

Writes beside this file: ``dem.tif`` (float32 metres, hills and valleys, a river valley),
``vegetation.tif`` (uint8 classes 1 grass, 2 shrub, 3 forest, 4 bare; 0 no data) and ``region.gpkg``
with layers ``roads`` (lines, ``highway`` in primary/secondary/tertiary/track), ``rivers`` (lines),
``lakes`` (polygons), ``obstacles`` (polygons, ``kind``; one deliberately self-intersecting, so the
pipeline's make_valid repair shows in its log) and ``surface`` (Voronoi polygons, ``material``).

Run: ``python -m terrain_data.generate`` (rewrites the files with the same content; the GeoPackage's
bytes differ by the timestamp GDAL stamps into it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyogrio.raw
import rasterio
import shapely
from scipy.ndimage import gaussian_filter

from common.atomic import atomic_paths
from pipeline.gis.grid import Grid

SEED = 20261122
CRS = "EPSG:32734"
X0, Y1 = 300_000.0, 6_200_000.0  # north-west corner, metres
SIZE_M, CELL_M = 14_000.0, 20.0
HERE = Path(__file__).resolve().parent
GRID = Grid.from_bounds((X0, Y1 - SIZE_M, X0 + SIZE_M, Y1), CELL_M, CRS)


def river_line(rng: np.random.Generator) -> shapely.LineString:
    """A meandering river from the northern to the southern edge."""
    t = np.linspace(0.0, 1.0, 120)
    x = X0 + 6500 + 1800 * np.sin(2 * np.pi * 1.3 * t + 0.4) + 500 * np.sin(2 * np.pi * 4.1 * t)
    y = Y1 + 200 - (SIZE_M + 400) * t
    x += np.cumsum(rng.normal(0, 25, t.size))
    return shapely.LineString(np.column_stack([x, y]))


def make_dem(rng: np.random.Generator, river: shapely.LineString) -> np.ndarray:
    """Elevation (metres) on GRID: Gaussian hills, a carved river valley, smooth noise."""
    xs, ys = GRID.cell_centres()
    dem = np.full(GRID.shape, 250.0)
    for _ in range(18):
        cx, cy = X0 + rng.uniform(0, SIZE_M), Y1 - rng.uniform(0, SIZE_M)
        h, s = rng.uniform(60, 380), rng.uniform(700, 2600)
        dem += h * np.exp(-((xs - cx) ** 2 + (ys - cy) ** 2) / (2 * s * s))
    d_river = shapely.distance(river, shapely.points(xs.ravel(), ys.ravel())).reshape(GRID.shape)
    dem -= 120.0 * np.exp(-((d_river / 900.0) ** 2))
    dem += gaussian_filter(rng.normal(0, 1, GRID.shape), 12) * 300.0
    return np.round(dem, 1).astype(np.float32)


def make_lakes(rng: np.random.Generator, river: shapely.LineString) -> list[shapely.Polygon]:
    """Four lakes of irregular outline, kept clear of the river."""
    lakes: list[shapely.Polygon] = []
    while len(lakes) < 4:
        cx, cy = X0 + rng.uniform(1500, SIZE_M - 1500), Y1 - rng.uniform(1500, SIZE_M - 1500)
        if shapely.distance(river, shapely.Point(cx, cy)) < 1500:
            continue
        a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        r = rng.uniform(250, 600) * (1 + 0.25 * np.sin(3 * a + rng.uniform(0, 6)) + 0.1 * np.sin(7 * a))
        lakes.append(shapely.Polygon(np.column_stack([cx + r * np.cos(a), cy + 0.7 * r * np.sin(a)])))
    return lakes


def wiggly(p: np.ndarray, q: np.ndarray, rng: np.random.Generator, amp: float) -> shapely.LineString:
    """A road from p to q that bends sideways by up to ``amp`` metres."""
    t = np.linspace(0, 1, 30)[:, None]
    normal = np.array([-(q - p)[1], (q - p)[0]]) / np.linalg.norm(q - p)
    bend = amp * np.sin(np.pi * t) * rng.uniform(-1, 1) + gaussian_filter(rng.normal(0, amp / 6, t.shape), 2)
    return shapely.LineString(p + t * (q - p) + bend * normal)


def make_roads(rng: np.random.Generator) -> tuple[list[shapely.LineString], list[str]]:
    """Primary roads through five towns, secondary spurs to the edges, tertiary links and tracks."""
    towns = np.column_stack([X0 + rng.uniform(1500, SIZE_M - 1500, 5), Y1 - rng.uniform(1500, SIZE_M - 1500, 5)])
    towns = towns[np.argsort(towns[:, 0])]
    roads, kinds = [], []
    for a, b in zip(towns[:-1], towns[1:], strict=True):
        roads.append(wiggly(a, b, rng, 600))
        kinds.append("primary")
    edges = [(X0 - 100, None), (X0 + SIZE_M + 100, None), (None, Y1 + 100), (None, Y1 - SIZE_M - 100)]
    for town in towns:
        ex, ey = edges[rng.integers(4)]
        end = np.array([ex if ex is not None else town[0] + rng.uniform(-3000, 3000),
                        ey if ey is not None else town[1] + rng.uniform(-3000, 3000)])
        roads.append(wiggly(town, end, rng, 400))
        kinds.append("secondary")
    for _ in range(6):
        i, j = rng.choice(5, 2, replace=False)
        mid = (towns[i] + towns[j]) / 2 + rng.normal(0, 1500, 2)
        roads.append(wiggly(towns[i], mid, rng, 300))
        kinds.append("tertiary")
    for _ in range(25):
        start = np.array([X0 + rng.uniform(0, SIZE_M), Y1 - rng.uniform(0, SIZE_M)])
        end = start + rng.normal(0, 1200, 2)
        roads.append(wiggly(start, end, rng, 150))
        kinds.append("track")
    return roads, kinds


def make_obstacles(rng: np.random.Generator) -> tuple[list[shapely.Geometry], list[str]]:
    """Rotated rectangles (quarries, fenced sites) and one self-intersecting 'bow-tie' site."""
    geoms, kinds = [], []
    for k in range(12):
        cx, cy = X0 + rng.uniform(500, SIZE_M - 500), Y1 - rng.uniform(500, SIZE_M - 500)
        w, h = rng.uniform(100, 500, 2)
        box = shapely.box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)
        geoms.append(shapely.affinity.rotate(box, rng.uniform(0, 90)))
        kinds.append("quarry" if k % 2 else "fenced")
    cx, cy = X0 + 11_000, Y1 - 3_000
    geoms.append(shapely.Polygon([(cx, cy), (cx + 400, cy + 300), (cx + 400, cy), (cx, cy + 300)]))
    kinds.append("fenced")
    return geoms, kinds


def make_surface(rng: np.random.Generator, dem: np.ndarray) -> tuple[list[shapely.Geometry], list[str]]:
    """Voronoi patches of surface material; rock favoured high up, sand low down."""
    seeds = shapely.multipoints(np.column_stack([X0 + rng.uniform(0, SIZE_M, 60), Y1 - rng.uniform(0, SIZE_M, 60)]))
    region = shapely.box(*GRID.bounds)
    cells = [shapely.intersection(c, region) for c in shapely.get_parts(shapely.voronoi_polygons(seeds, extend_to=region))]
    lo, hi = np.percentile(dem, [25, 75])
    materials = []
    for c in cells:
        col, row = GRID.to_pixel(c.centroid.x, c.centroid.y)
        z = dem[min(int(row), GRID.height - 1), min(int(col), GRID.width - 1)]
        p = [0.4, 0.2, 0.2, 0.2] if lo <= z <= hi else ([0.2, 0.1, 0.6, 0.1] if z > hi else [0.3, 0.4, 0.05, 0.25])
        materials.append(str(rng.choice(["soil", "sand", "rock", "clay"], p=p)))
    return cells, materials


def make_vegetation(rng: np.random.Generator, dem: np.ndarray) -> np.ndarray:
    """uint8 classes from smooth noise and elevation: 1 grass, 2 shrub, 3 forest, 4 bare (0 no data)."""
    noise = gaussian_filter(rng.normal(0, 1, GRID.shape), 15)
    noise /= noise.std()
    veg = np.where(noise > 0.6, 3, np.where(noise > -0.2, 2, 1)).astype(np.uint8)
    veg[dem > np.percentile(dem, 92)] = 4
    return veg


def write_raster(path: Path, data: np.ndarray, nodata: float | int | None) -> None:
    profile = {
        "driver": "GTiff", "height": GRID.height, "width": GRID.width, "count": 1, "dtype": data.dtype.name,
        "crs": GRID.crs, "transform": GRID.transform, "nodata": nodata, "compress": "deflate",
        "predictor": 3 if data.dtype.kind == "f" else 2, "zlevel": 9, "tiled": True,
        "blockxsize": 256, "blockysize": 256,
    }
    with atomic_paths(path) as (tmp,), rasterio.open(tmp, "w", **profile) as dst:
        dst.write(data, 1)


def write_layers(path: Path, layers: dict[str, tuple[list, dict[str, list[str]]]]) -> None:
    """All vector layers into one GeoPackage (written to a temporary file, then renamed)."""
    with atomic_paths(path) as (tmp,):
        for name, (geoms, fields) in layers.items():
            geom_type = shapely.get_type_id(geoms[0])
            pyogrio.raw.write(
                tmp, shapely.to_wkb(np.asarray(geoms, dtype=object)),
                [np.asarray(v, dtype=object) for v in fields.values()], list(fields),
                layer=name, driver="GPKG", crs=CRS,
                geometry_type={1: "LineString", 3: "Polygon"}[geom_type],
            )


def main(out_dir: Path = HERE) -> None:
    """Write the region's files into ``out_dir`` (default: beside this file)."""
    rng = np.random.default_rng(SEED)
    river = river_line(rng)
    dem = make_dem(rng, river)
    lakes = make_lakes(rng, river)
    roads, highway = make_roads(rng)
    obstacles, obstacle_kind = make_obstacles(rng)
    surface, material = make_surface(rng, dem)
    write_raster(out_dir / "dem.tif", dem, -9999.0)
    write_raster(out_dir / "vegetation.tif", make_vegetation(rng, dem), 0)
    write_layers(out_dir / "region.gpkg", {
        "roads": (roads, {"highway": highway}),
        "rivers": ([river], {"waterway": ["river"]}),
        "lakes": (lakes, {"natural": ["water"] * len(lakes)}),
        "obstacles": (obstacles, {"kind": obstacle_kind}),
        "surface": (surface, {"material": material}),
    })


if __name__ == "__main__":
    main()
