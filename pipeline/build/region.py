"""Region config -> FeatureStack -> TerrainPrior, and the feature GeoTIFFs.

Each input layer is read once and shared by the features that use it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import psutil
from tqdm import tqdm

from common.atomic import atomic_paths
from pipeline.config.region import FeatureSpec, RegionConfig
from pipeline.features import rasterize
from pipeline.features.distance import distance_m
from pipeline.features.slope import slope_classes, slope_deg
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE
from pipeline.gis.layers import LayerError, VectorLayer, read_dem, read_raster, read_vector
from pipeline.gis.lidar import LidarError, LidarSurface
from pipeline.prior.likelihood import LikelihoodModel
from pipeline.prior.style import paletted_qml, pseudocolor_qml, style_path
from pipeline.prior.terrain import PriorError, TerrainPrior
from pipeline.prior.write import cog_writer


class BuildMemoryError(ValueError):
    """A grid too large to build in this machine's memory; the message gives the estimate and the way out."""


class UnusedFeatureWarning(UserWarning):
    """Features of the config that a ``--model`` has no table for, left out of the prior."""


FIXED_BYTES = 384 << 20
"""Memory a build needs whatever the grid size (numpy, GDAL, numba and the other libraries loaded, GDAL's
block cache), bytes."""
WORK_BYTES_PER_CELL = 24
"""Peak temporaries while one feature is built (distance transform, DEM and its slope), bytes per cell."""
PRIOR_BYTES_PER_CELL = 48
"""r, the density and the two float64 summed-area tables (plus float32 copies on writing), bytes per cell."""
_FEATURE_BYTES = {"mask": 2, "classes": 2, "categories": 4, "distance": 8, "slope": 8, "elevation": 8, "raster": 8}
"""Bytes per cell of each feature type's grid (int16 masks and classes, int32 codes, float64 values)."""


def build_memory_bytes(config: RegionConfig, prior: bool = True) -> int:
    """Estimated peak memory (bytes) of building the features of ``config`` (and its prior if ``prior``)
    in memory. Measured peaks (the process's whole resident memory) of the bundled region's prior at
    0.5-8 million cells are 0.75-0.85 of it (tests/pipeline/build/test_memory.py)."""
    per_cell = sum(_FEATURE_BYTES[f.type] for f in config.features.values()) + WORK_BYTES_PER_CELL
    per_cell += PRIOR_BYTES_PER_CELL if prior else 0
    return FIXED_BYTES + config.grid.height * config.grid.width * per_cell


def available_memory_bytes() -> int:
    """Memory this process can still get: the system's available memory, capped by an address-space
    limit (``ulimit -v``) when one is set."""
    available = psutil.virtual_memory().available
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        available = min(available, soft - psutil.Process().memory_info().vms)
    return max(int(available), 0)


def check_memory(config: RegionConfig, prior: bool = True) -> None:
    """Refuse, before allocating anything, a build whose estimated memory exceeds what is available."""
    need, have = build_memory_bytes(config, prior), available_memory_bytes()
    if need > have:
        what = "prior" if prior else "features"
        raise BuildMemoryError(
            f"{config.path}: [region]: the {what} of {config.grid.height:,} x {config.grid.width:,} cells need about "
            f"{need / 2**30:,.1f} GiB of memory; this machine has {have / 2**30:,.1f} GiB available. Build it tile by "
            "tile (terrain-prior build --tiled, or learn --tiled), or use a larger cell_size or smaller bounds"
        )


class _Layers:
    """Vector layers of one config read on first use (with the union of attributes asked for)."""

    def __init__(self, config: RegionConfig) -> None:
        self.config = config
        self._vectors: dict[tuple[str, tuple[str, ...]], VectorLayer] = {}
        self._surfaces: dict[str, LidarSurface] = {}
        self._dems: dict[str, Future] = {}

    def vector(self, name: str, columns: tuple[str, ...] = ()) -> VectorLayer:
        key = (name, columns)
        if key not in self._vectors:
            self._vectors[key] = read_vector(self.config.layers[name], self.config.grid, list(columns))
        return self._vectors[key]

    def surface(self, name: str) -> LidarSurface:
        """Elevation and slope of a point-cloud layer, gridded once for the features sharing it."""
        if name not in self._surfaces:
            from pipeline.gis.lidar import lidar_surface  # laspy / open3d are an optional extra

            spec = self.config.layers[name]
            try:
                self._surfaces[name] = lidar_surface(spec.path, self.config.grid, crs=spec.crs, keep=spec.points)
            except LidarError as exc:
                raise LidarError(f"[layers.{name}]: {exc}") from None
        return self._surfaces[name]

    def prefetch_dems(self, names: set[str], pool: ThreadPoolExecutor) -> None:
        """Start reading the DEM layers ``names`` onto the grid on ``pool`` (GDAL's read and warp release
        the GIL, so they run beside the features built before them)."""
        for name in sorted(names):
            self._dems[name] = pool.submit(read_dem, self.config.layers[name], self.config.grid)

    def dem(self, name: str) -> np.ndarray:
        """Elevation (m) of raster layer ``name`` on the grid, an array of the caller's own: the prefetched
        read the first time, a new read after that."""
        future = self._dems.pop(name, None)
        return future.result() if future is not None else read_dem(self.config.layers[name], self.config.grid)

    def geometries(self, names: tuple[str, ...]) -> np.ndarray:
        parts = [self.vector(n).geometries for n in names]
        return np.concatenate(parts) if parts else np.empty(0, dtype=object)


def _mask_feature(spec: FeatureSpec, layers: _Layers, grid) -> Feature:
    m = rasterize.mask(layers.geometries(spec.layers), grid, spec.buffer_m, spec.all_touched, np.int16)
    return Feature(spec.name, m, "categorical", labels={0: spec.labels[0], 1: spec.labels[1]})


def _distance_feature(spec: FeatureSpec, layers: _Layers, grid) -> Feature:
    # burn on the grid grown by margin_m on each side, so features just outside the bounds count
    pad_r, pad_c = int(np.ceil(spec.margin_m / grid.dy)), int(np.ceil(spec.margin_m / grid.dx))
    padded = grid.window_grid(-pad_r, -pad_c, grid.height + 2 * pad_r, grid.width + 2 * pad_c)
    geoms = layers.geometries(spec.layers)
    if spec.to == "ends":
        try:
            geoms = rasterize.line_ends(geoms)
        except ValueError as e:
            raise LayerError(f"[features.{spec.name}] (to = \"ends\") of layers {list(spec.layers)}: {e}") from None
    m = rasterize.mask(geoms, padded, spec.buffer_m, spec.all_touched)
    # float32 (7 digits, 0.1 mm at 1 km), as the feature GeoTIFF stores it: half the memory of float64
    d = distance_m(m, grid.dx, grid.dy, spec.max_distance_m, np.float32, window=(pad_r, pad_c, grid.height, grid.width))
    return Feature(spec.name, d, "continuous", units="m")


def _slope_feature(spec: FeatureSpec, layers: _Layers, grid) -> Feature:
    layer = layers.config.layers[spec.layer]
    if layer.kind == "pointcloud":
        slope = layers.surface(spec.layer).slope
    else:
        slope = slope_deg(layers.dem(spec.layer), grid.dx, grid.dy, in_place=True)  # the DEM is ours: no second grid
    return Feature(spec.name, slope, "continuous", units="deg")


def _elevation_feature(spec: FeatureSpec, layers: _Layers, grid) -> Feature:
    layer = layers.config.layers[spec.layer]
    z = layers.surface(spec.layer).elevation if layer.kind == "pointcloud" else layers.dem(spec.layer)
    return Feature(spec.name, z, "continuous", units="m")


def _categories_feature(spec: FeatureSpec, layers: _Layers, grid) -> Feature:
    layer = layers.vector(spec.layer, (spec.attribute,))
    values = np.array([str(v) for v in layer.attributes[spec.attribute]], dtype=object)
    classes = list(spec.classes) or sorted(set(values.tolist()))
    unknown = sorted(set(values.tolist()) - set(classes))
    if unknown:
        src = layers.config.layers[spec.layer]
        raise LayerError(
            f"{src.path} ([layers.{spec.layer}]): attribute {spec.attribute!r} has value {unknown[0]!r}, "
            f"not in [features.{spec.name}] classes {classes}"
        )
    lookup = {c: k for k, c in enumerate(classes)}
    labels = dict(enumerate(classes))
    fill = NODATA_CODE
    if spec.background is not None:
        fill = lookup.get(spec.background, len(classes))
        labels[fill] = spec.background
    codes = np.array([lookup[v] for v in values], dtype=np.int32)
    return Feature(spec.name, rasterize.categories(layer.geometries, codes, grid, fill), "categorical", labels=labels)


def _raster_feature(spec: FeatureSpec, layers: _Layers, grid) -> Feature:
    values = read_raster(layers.config.layers[spec.layer], grid, spec.categorical)
    if spec.categorical:
        return Feature(spec.name, values, "categorical", labels=dict(spec.code_labels))
    return Feature(spec.name, values, "continuous", units=spec.units)


def _classes_feature(spec: FeatureSpec, stack: FeatureStack) -> Feature:
    codes = slope_classes(stack[spec.source].values, spec.breaks)
    return Feature(spec.name, codes, "categorical", labels=dict(enumerate(spec.labels)))


_BUILDERS = {
    "mask": _mask_feature,
    "distance": _distance_feature,
    "slope": _slope_feature,
    "elevation": _elevation_feature,
    "categories": _categories_feature,
    "raster": _raster_feature,
}


def build_features(config: RegionConfig, progress: bool = True) -> FeatureStack:
    """All features of a region config on its grid (classes features after the features they bin);
    BuildMemoryError when they would not fit in memory."""
    check_memory(config, prior=False)
    stack = FeatureStack(config.grid)
    layers = _Layers(config)
    specs = sorted(config.features.values(), key=lambda f: f.type == "classes")
    with ThreadPoolExecutor(max_workers=1) as pool:
        # the DEMs are read and warped (GDAL) while the features before them are built: 0.5-0.9 s of a
        # 10,000^2 build whose rasterizing and page faults leave a core idle
        layers.prefetch_dems({s.layer for s in specs if s.type in ("slope", "elevation") and config.layers[s.layer].kind != "pointcloud"}, pool)
        for spec in tqdm(specs, desc=f"features of {config.name}", unit="feature", disable=not progress):
            if spec.type == "classes":
                stack.add(_classes_feature(spec, stack))
            else:
                stack.add(_BUILDERS[spec.type](spec, layers, config.grid))
    return stack


BAND_ROWS = 64
"""Rows of the grid whose likelihood is evaluated at a time: each table's grid-size float64 temporaries
(several for the road distance's formula) shrink to a band's. Small enough (5 MB at 10,000 columns)
that malloc reuses them from its heap: 512-row bands (40 MB) were fresh zeroed pages from the kernel
every time, ~1 s of system time more at 10,000 x 10,000."""


def _likelihood(stack: FeatureStack, model: LikelihoodModel) -> np.ndarray:
    """Unnormalised r = Π r_i(F_i) of a feature stack, band of rows by band (the same products, cell by
    cell), with a learned model's tempering and defensive mixture (:func:`calibrate`); PriorError
    naming a table that alone zeroes the grid."""
    grid = stack.grid
    r = np.empty(grid.shape, dtype=np.float64)

    def band(r0: int) -> None:
        rows = min(BAND_ROWS, grid.height - r0)
        window = FeatureStack(grid.window_grid(r0, 0, rows, grid.width),
                              {n: dataclasses.replace(f, values=f.values[r0 : r0 + rows]) for n, f in stack.features.items()})
        r[r0 : r0 + rows] = model.evaluate(window)

    # bands are independent and numpy releases the GIL on them, so threads use every core; each band's
    # arithmetic is the serial one, so r is the same bit for bit
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        list(pool.map(band, range(0, grid.height, BAND_ROWS)))
    if not r.any():  # name the culprit when one table alone zeroes the grid
        for name, term in model.terms.items():
            if not term(stack[name]).any():
                raise PriorError(f"[likelihood.{name}] is zero on every cell of the grid, so the prior would be zero everywhere")
    return calibrate(r, *learned_calibration(model))


def learned_calibration(model: LikelihoodModel) -> tuple[float, float]:
    """(τ, ε) of a learned model's ``[meta.learned]`` (``temper_exponent``, ``defensive_epsilon``;
    docs/learn.md): its prior is p ∝ r^τ, then (1 − ε)·p + ε·uniform over the support r > 0.
    (1, 0) for a model without them; PriorError naming a bad value."""
    learned = model.meta.get("learned", {})
    learned = learned if isinstance(learned, dict) else {}
    tau, eps = learned.get("temper_exponent", 1.0), learned.get("defensive_epsilon", 0.0)
    if not (isinstance(tau, int | float) and tau > 0):
        raise PriorError(f"[meta.learned] temper_exponent must be a number > 0, got {tau!r}")
    if not (isinstance(eps, int | float) and 0 <= eps < 1):
        raise PriorError(f"[meta.learned] defensive_epsilon must be a number in [0, 1), got {eps!r}")
    return float(tau), float(eps)


def temper_rows(r: np.ndarray, tau: float) -> None:
    """r ← r^τ in place (zeros stay zero); a band at a time in the tiled build."""
    if tau != 1.0:
        np.power(r, tau, out=r, where=r > 0)


def uniform_share(total: float, n_support: int, eps: float) -> float:
    """The constant c that, added to each of the ``n_support`` cells with r^τ > 0 (sum ``total``),
    makes the normalised array the defensive mixture (1 − ε)·r^τ/total + ε/n_support there:
    c = ε·total / ((1 − ε)·n_support) (equal cells, so uniform over the support is 1/n_support a cell)."""
    return eps * total / ((1.0 - eps) * n_support) if eps > 0 else 0.0


def calibrate(r: np.ndarray, tau: float = 1.0, eps: float = 0.0) -> np.ndarray:
    """Unnormalised r made a learned model's scored prior in place (τ, ε: :func:`learned_calibration`):
    normalising the result gives (1 − ε)·r^τ/Σr^τ + ε·u, u uniform over the support."""
    temper_rows(r, tau)
    if eps > 0:
        support = r > 0
        r += uniform_share(float(r.sum()), int(support.sum()), eps) * support
    return r


def _description(model: LikelihoodModel, provenance: dict | None) -> dict:
    description = model.to_dict()
    if provenance:
        description["provenance"] = provenance
    return description


def build_prior(stack: FeatureStack, model: LikelihoodModel, provenance: dict | None = None) -> TerrainPrior:
    """The normalised prior r(x) ∝ Π r_i(F_i(x)) of a feature stack; ``provenance`` is stored with the model."""
    return TerrainPrior.from_array(_likelihood(stack, model), stack.grid, _description(model, provenance))


def unused_features(config: RegionConfig, terms: set[str] | dict) -> list[str]:
    """Features of ``config`` that a prior with tables for ``terms`` would not use: no table of their own
    and not the source of a used ``classes`` feature."""
    used = set(terms)
    for name in terms:
        spec = config.features.get(name)
        if spec is not None and spec.type == "classes":
            used.add(spec.source)
    return [name for name in config.features if name not in used]


def region_model(config: RegionConfig, model: LikelihoodModel | None = None) -> LikelihoodModel:
    """``model``, else the config's ``[likelihood.*]`` tables; PriorError when there are neither.

    Every feature of the config must count: with the config's own tables a feature with no table (and
    not binned by a feature that has one) is a PriorError naming it; a ``model`` given apart from the
    config (``--model``) may use fewer features, and those it leaves out are named in a warning.
    """
    own = model is None
    model = model or config.model
    if model is None:
        raise PriorError(f"{config.path}: no [likelihood.<feature>] tables and no model given")
    unused = unused_features(config, model.terms)
    if unused and own:
        raise PriorError(
            f"{config.path}: [features.{unused[0]}] has no [likelihood.{unused[0]}] table"
            + (f" (nor do {unused[1:]})" if len(unused) > 1 else "")
            + ", so the prior would leave it out: add a table (a likelihood of 1 is neutral) or remove the feature"
        )
    if unused:
        warnings.warn(f"{config.path}: the model has no table for the features {unused}; they are left out of the prior",
                      UnusedFeatureWarning, stacklevel=2)
    return model


def region_provenance(config: RegionConfig, model_path: str | Path | None = None) -> dict:
    """What a prior records about its inputs: region name, config path and, when the tables came from
    a file other than the config, that file's absolute path."""
    provenance = {"region": config.name, "config": str(config.path)}
    if model_path is not None:
        provenance["model"] = str(Path(model_path).resolve())
    return provenance


def build_region_prior(
    config: RegionConfig, model: LikelihoodModel | None = None, progress: bool = True, provenance: dict | None = None
) -> TerrainPrior:
    """Features and prior of a region; ``model`` overrides the config's ``[likelihood.*]`` tables;
    ``provenance`` is stored with the model (default :func:`region_provenance`). BuildMemoryError
    before anything is allocated when the build would not fit in memory."""
    model = region_model(config, model)
    check_memory(config)
    stack = build_features(config, progress)
    if set(model.terms) <= set(stack.features):  # free features no table reads (a classes feature's source) first
        stack = FeatureStack(stack.grid, {name: stack[name] for name in model.terms})
    r = _likelihood(stack, model)
    # The features are done with once r is: free them (~20 bytes a cell) before the density and its
    # tables are made, and let the density take r's buffer (the same numbers, 8 bytes a cell less).
    del stack
    return TerrainPrior.from_array(r, config.grid, _description(model, region_provenance(config) if provenance is None else provenance),
                                   reuse=True)


def _feature_qml(f: Feature) -> str:
    """QGIS style of a feature: a palette of its categories (codes present or labelled), else a ramp over its finite range."""
    if f.kind == "categorical":
        return paletted_qml({int(c): f.label(c) for c in sorted(set(f.labels) | set(f.codes().tolist()))})
    finite = f.values[np.isfinite(f.values)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    return pseudocolor_qml(lo, hi, f.units)


def write_features(stack: FeatureStack, out_dir: str | Path) -> list[Path]:
    """One Cloud-Optimized GeoTIFF per feature in ``out_dir`` (``<name>.tif``) with its QGIS style
    (``<name>.qml``), all renamed into place together; returns the GeoTIFF paths.

    Categorical: int16 codes (int32 when a code needs it), nodata ``NODATA_CODE``, the labels as a JSON tag ``LABELS``,
    a paletted style with the labels; continuous: float32 in the tag ``UNITS``, nodata NaN, a pseudocolour style.
    """
    out_dir = Path(out_dir)
    finals = [out_dir / f"{f.name}.tif" for f in stack]
    with atomic_paths(*finals, *map(style_path, finals)) as temps:
        for f, tmp, tmp_qml in zip(stack, temps[: len(finals)], temps[len(finals) :], strict=True):
            if f.kind == "categorical":
                small = f.values.size == 0 or np.iinfo(np.int16).max >= f.values.max()
                dtype = "int16" if small else "int32"
                writer = cog_writer(tmp, stack.grid, dtype, "NEAREST", nodata=NODATA_CODE)
                tags = {"LABELS": json.dumps({str(k): v for k, v in f.labels.items()})}
                data = f.values.astype(dtype)
            else:
                writer = cog_writer(tmp, stack.grid, "float32", nodata=float("nan"))
                tags = {"UNITS": f.units}
                data = f.values.astype(np.float32)
            with writer as dst:
                dst.write(data, 1)
                dst.update_tags(FEATURE=f.name, KIND=f.kind, **tags)
            tmp_qml.write_text(_feature_qml(f), encoding="utf-8")
    return finals
