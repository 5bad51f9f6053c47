"""Small writers of test GIS files (vector layers, rasters, region configs) shared by the pipeline tests."""

from __future__ import annotations

import hashlib
import tomllib
from pathlib import Path

import numpy as np
import pyogrio.raw
import rasterio
import shapely
import tomli_w
from affine import Affine

REPO = Path(__file__).resolve().parents[2]
REGION_TOML = REPO / "terrain_data" / "region.toml"


def write_vector(path: Path, geoms: list, fields: dict[str, list] | None = None, layer: str | None = None,
                 crs: str | None = "EPSG:32734", driver: str | None = None) -> Path:
    """Write shapely geometries (all one type) with string/number attributes."""
    fields = fields or {}
    types = {shapely.get_type_id(g) for g in geoms}
    name = {0: "Point", 1: "LineString", 3: "Polygon", 6: "MultiPolygon"}[types.pop()] if geoms else "Polygon"
    pyogrio.raw.write(
        path, shapely.to_wkb(np.asarray(geoms, dtype=object)),
        [np.asarray(v) for v in fields.values()], list(fields),
        layer=layer, driver=driver, crs=crs, geometry_type=name,
    )
    return path


def write_raster(path: Path, data: np.ndarray, transform: Affine, crs: str | None, nodata=None) -> Path:
    profile = {"driver": "GTiff", "height": data.shape[0], "width": data.shape[1], "count": 1,
               "dtype": data.dtype.name, "transform": transform, "nodata": nodata}
    if crs is not None:
        profile["crs"] = crs
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
    return path


def write_config(path: Path, doc: dict) -> Path:
    path.write_text(tomli_w.dumps(doc))
    return path


def tree_hashes(folder: Path, pattern: str = "*") -> dict[str, str]:
    """sha256 of every file matching ``pattern`` in ``folder``."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.glob(pattern))}


def cell_boxes(transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """shapely boxes of every cell, (H, W)."""
    h, w = shape
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    x0, y0 = transform @ (cols, rows)
    x1, y1 = transform @ (cols + 1, rows + 1)
    return shapely.box(np.minimum(x0, x1), np.minimum(y0, y1), np.maximum(x0, x1), np.maximum(y0, y1))


def region_doc(**region) -> dict:
    """The bundled region config with absolute layer paths and ``region`` keys replaced."""
    doc = tomllib.loads(REGION_TOML.read_text())
    for layer in doc["layers"].values():
        layer["path"] = str((REGION_TOML.parent / layer["path"]).resolve())
    doc["region"].update(region)
    return doc


def handset_targets(region_toml: Path, n: int, seed: int = 0) -> np.ndarray:
    """(n, 2) target locations in metres drawn from the region's hand-set prior (its features built quietly)."""
    import warnings

    from pipeline.build.region import build_features, build_prior
    from pipeline.config.learn import load_learn_config

    region, _ = load_learn_config(region_toml)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stack = build_features(region, progress=False)
    return build_prior(stack, region.model).sample(n, np.random.default_rng(seed))
