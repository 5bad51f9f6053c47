"""Region config (TOML) -> typed, validated objects: the grid, the input layers, the features, the model.

Validated once here, at the edge; errors name the config file and the offending key. Paths are
resolved relative to the config file. Example (``terrain_data/region.toml`` is a full one)::

    [region]
    name = "synthetic"
    crs = "EPSG:32734"                 # projected, metres; or "utm": zone picked from lon/lat bounds
    bounds = [300000, 6186000, 314000, 6200000]   # xmin, ymin, xmax, ymax in bounds_crs
    bounds_crs = "EPSG:32734"          # optional; default the grid CRS ("EPSG:4326" when crs = "utm")
    cell_size = 20.0                   # metres

    [layers.roads]                     # vector: GeoPackage / Shapefile / GeoJSON
    path = "roads.gpkg"
    layer = "roads"                    # optional when the file has one layer
    where = "highway IN ('primary', 'secondary')"   # optional OGR SQL attribute filter
    restore_index = false              # shapefiles: rebuild a stale .shx on a temporary copy
    allow_empty_geometries = false     # features with no geometry: an error unless true (then skipped, warned)

    [layers.dem]                       # raster (by suffix .tif/.tiff/.vrt/.img/.asc) or point cloud (.las/.laz/.ply/.pcd/.xyz)
    path = "dem.tif"                   # point clouds: optional crs (overrides the file's; needed by a LAS without one),
                                       # LAS/LAZ: classes = [2] (ground, default) or "all", returns = "all"|"first"|"last"|"single"|[1, 2]

    [features.water]                   # see FEATURE_TYPES for every type and its keys
    type = "mask"
    layers = ["lakes", "river"]
    buffer_m = 10.0
    labels = ["dry", "water"]

    [likelihood.water]                 # parsed by pipeline.prior.likelihood
    type = "categorical"
    values = { dry = 1.0, water = 0.0 }
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rasterio.crs import CRS

from pipeline.gis.crs import to_pyproj, transformer
from pipeline.gis.grid import Grid, GridError
from pipeline.gis.layers import LayerError, LayerSpec
from pipeline.gis.lidar import GROUND, LAS_SUFFIXES, LidarError, PointFilter
from pipeline.gis.lidar import SUFFIXES as POINTCLOUD_SUFFIXES
from pipeline.prior.likelihood import LikelihoodError, LikelihoodModel, read_toml


class ConfigError(ValueError):
    """A region config that is malformed; the message names the file and key."""


class ConfigWarning(UserWarning):
    """A region config that works but probably not as meant (e.g. a grid CRS whose metres are not ground metres)."""


SCALE_TOLERANCE = 0.01
"""Warn when the grid CRS's point scale at the grid's centre differs from 1 by more than this (UTM: < 0.001)."""


TOP_LEVEL_TABLES = {"region", "layers", "features", "likelihood", "meta", "learn"}
"""``[learn]`` is validated by pipeline.config.learn; the rest here."""
RASTER_SUFFIXES = {".tif", ".tiff", ".vrt", ".img", ".asc"}


@dataclass(frozen=True)
class FeatureSpec:
    """One feature grid to build.

    Types and their keys (``name`` is the feature's name, the key of its ``[features.<name>]`` table):

    - ``mask``: ``layers`` (vector), ``buffer_m`` (metres around lines/points, default 0),
      ``all_touched`` (default false), ``labels`` ([outside, inside], default ["no", "yes"]).
    - ``distance``: ``layers`` (vector) -> Euclidean distance in metres to the nearest cell they touch;
      optional ``max_distance_m``, ``margin_m`` (metres around the grid where the layers still count,
      so a road just outside the bounds is not ignored; default 0), ``to`` ("lines", default, or "ends":
      to the nearest end point of the layers' lines, e.g. where farm tracks end at a farmstead).
    - ``slope``: ``layer`` (a DEM raster or point cloud) -> slope in degrees.
    - ``elevation``: ``layer`` (a DEM raster or point cloud) -> ground elevation in metres.
    - ``classes``: ``source`` (a continuous feature), ``breaks`` (ascending, units of the source),
      optional ``labels`` (one more than breaks) -> categories [-inf, b0), [b0, b1), ..., [bn, inf).
    - ``categories``: ``layer`` (vector polygons) and ``attribute`` -> one category per attribute value,
      optional ``classes`` (the allowed values, in code order), ``background`` (label of uncovered cells;
      default no data).
    - ``raster``: ``layer`` (raster); ``categorical = true`` (nearest resampling, optional ``labels``
      table code -> name) or false (bilinear, continuous, optional ``units``).
    """

    name: str
    type: str
    layers: tuple[str, ...] = ()
    buffer_m: float = 0.0
    all_touched: bool = False
    labels: tuple[str, ...] = ()
    max_distance_m: float | None = None
    margin_m: float = 0.0
    to: str = "lines"
    source: str | None = None
    breaks: tuple[float, ...] = ()
    attribute: str | None = None
    classes: tuple[str, ...] = ()
    background: str | None = None
    categorical: bool = False
    code_labels: dict[int, str] = field(default_factory=dict)
    units: str = ""

    @property
    def layer(self) -> str:
        """The single input layer of slope / categories / raster features."""
        return self.layers[0]


DISTANCE_TO = ("lines", "ends")
"""What a distance feature measures to: the layers' geometries, or the end points of their lines."""

FEATURE_TYPES: dict[str, tuple[set[str], set[str]]] = {
    # type: (required keys, optional keys) besides "type"
    "mask": ({"layers"}, {"buffer_m", "all_touched", "labels"}),
    "distance": ({"layers"}, {"max_distance_m", "margin_m", "buffer_m", "all_touched", "to"}),
    "slope": ({"layer"}, set()),
    "elevation": ({"layer"}, set()),
    "classes": ({"source", "breaks"}, {"labels"}),
    "categories": ({"layer", "attribute"}, {"classes", "background"}),
    "raster": ({"layer"}, {"categorical", "labels", "units"}),
}


@dataclass(frozen=True)
class RegionConfig:
    """A validated region config."""

    path: Path
    name: str
    grid: Grid
    layers: dict[str, LayerSpec]
    features: dict[str, FeatureSpec]
    model: LikelihoodModel | None


def utm_crs(lon_min: float, lat_min: float, lon_max: float, lat_max: float) -> CRS:
    """The WGS 84 UTM zone CRS containing the centre of lon/lat bounds (degrees)."""
    lon = (lon_min + lon_max) / 2.0
    lat = (lat_min + lat_max) / 2.0
    zone = int(math.floor((lon + 180.0) / 6.0)) % 60 + 1
    return CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


class _Table:
    """A TOML table that remembers where it came from, for error messages."""

    def __init__(self, source: Path, key: str, d: Any) -> None:
        if not isinstance(d, dict):
            raise ConfigError(f"{source}: [{key}] must be a table, got {type(d).__name__}")
        self.source, self.key, self.d = source, key, d

    def err(self, sub: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.source}: {self.key}.{sub}: {msg}")

    def check_keys(self, allowed: set[str]) -> None:
        unknown = sorted(set(self.d) - allowed)
        if unknown:
            raise ConfigError(f"{self.source}: [{self.key}]: unknown keys {unknown}; allowed {sorted(allowed)}")

    def get(self, sub: str, types: type | tuple[type, ...], default: Any = ..., what: str = "") -> Any:
        if sub not in self.d:
            if default is ...:
                raise self.err(sub, "missing" + (f" ({what})" if what else ""))
            return default
        v = self.d[sub]
        if isinstance(v, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
            raise self.err(sub, f"expected {what or types}, got {v!r}")
        if not isinstance(v, types):
            raise self.err(sub, f"expected {what or types}, got {v!r}")
        return v

    def number(self, sub: str, default: Any = ..., positive: bool = False, nonneg: bool = False) -> float:
        v = self.get(sub, (int, float), default, "a number")
        if v is None:
            return v
        v = float(v)
        if not math.isfinite(v) or (positive and v <= 0) or (nonneg and v < 0):
            raise self.err(sub, f"must be a finite {'positive ' if positive else 'non-negative ' if nonneg else ''}number, got {v}")
        return v

    def str_list(self, sub: str, default: Any = ...) -> tuple[str, ...]:
        v = self.get(sub, (list, str), default, "a list of names")
        if isinstance(v, str):
            v = [v]
        if not all(isinstance(s, str) for s in v):
            raise self.err(sub, f"expected a list of strings, got {v!r}")
        return tuple(v)


def _parse_crs(t: _Table, key: str, value: Any) -> CRS:
    try:
        return CRS.from_user_input(value)
    except Exception as exc:  # rasterio raises CRSError; any failure here is a bad config value
        raise t.err(key, f"not a CRS: {value!r} ({exc})") from None


def _parse_grid(t: _Table) -> Grid:
    t.check_keys({"name", "crs", "bounds", "bounds_crs", "cell_size"})
    crs_value = t.get("crs", str, what="a CRS such as \"EPSG:32734\" or \"utm\"")
    bounds = t.get("bounds", list, what="[xmin, ymin, xmax, ymax]")
    if len(bounds) != 4 or not all(isinstance(b, int | float) and not isinstance(b, bool) for b in bounds):
        raise t.err("bounds", f"expected 4 numbers [xmin, ymin, xmax, ymax], got {bounds!r}")
    if not all(math.isfinite(b) for b in bounds):
        raise t.err("bounds", f"must be finite numbers, got {bounds!r}")
    cell = t.number("cell_size", 20.0, positive=True)
    if crs_value.lower() == "utm":
        bounds_crs = _parse_crs(t, "bounds_crs", t.get("bounds_crs", str, "EPSG:4326"))
        if not bounds_crs.is_geographic:
            raise t.err("bounds_crs", "crs = \"utm\" needs the bounds in longitude/latitude degrees")
        lon_min, lat_min, lon_max, lat_max = bounds
        if not (-180 <= lon_min < lon_max <= 180 and -90 <= lat_min < lat_max <= 90):
            raise t.err("bounds", f"with crs = \"utm\" bounds are [lon_min, lat_min, lon_max, lat_max] degrees, got {bounds}")
        grid_crs = utm_crs(*bounds)
    else:
        grid_crs = _parse_crs(t, "crs", crs_value)
        bounds_crs = _parse_crs(t, "bounds_crs", t.get("bounds_crs", str, crs_value))
    if bounds_crs != grid_crs:
        bounds = transformer(bounds_crs, grid_crs).transform_bounds(*bounds, densify_pts=21)
    try:
        grid = Grid.from_bounds(tuple(bounds), cell, grid_crs)
    except GridError as exc:
        raise t.err(exc.key, str(exc)) from None
    k = grid.scale_factor()
    if abs(k - 1.0) > SCALE_TOLERANCE:
        x, y = (grid.bounds[0] + grid.bounds[2]) / 2.0, (grid.bounds[1] + grid.bounds[3]) / 2.0
        _, lat = transformer(grid_crs, "EPSG:4326").transform(x, y)
        warnings.warn(
            f"{t.source}: {t.key}.crs: {to_pyproj(grid_crs).name} has a scale factor of {k:.4g} at the grid's "
            f"centre (latitude {lat:.2f}°; 1/cos φ = {1 / math.cos(math.radians(lat)):.4g} for Web Mercator): "
            f"its metres are {k:.4g} ground metres, so cell_size, buffers and distances are off by that factor; "
            "a local projected CRS (crs = \"utm\") has a scale factor of about 1",
            ConfigWarning, stacklevel=4,
        )
    return grid


def _layer_kind(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix in RASTER_SUFFIXES:
        return "raster"
    if suffix in POINTCLOUD_SUFFIXES:
        return "pointcloud"
    return "vector"


def _parse_layer(source: Path, name: str, d: Any) -> LayerSpec:
    t = _Table(source, f"layers.{name}", d)
    t.check_keys({"path", "layer", "where", "restore_index", "allow_empty_geometries", "band", "kind", "crs", "classes",
                  "returns"})
    path = Path(t.get("path", str, what="a file path"))
    if not path.is_absolute():
        path = source.parent / path
    kind = t.get("kind", str, _layer_kind(path))
    if kind not in ("vector", "raster", "pointcloud"):
        raise t.err("kind", f"must be vector, raster or pointcloud, got {kind!r}")
    restore_index = t.get("restore_index", bool, False, "true or false")
    if restore_index and path.suffix.lower() != ".shp":
        raise t.err("restore_index", f"only Shapefiles (.shp) have an index to restore, {path.name} is not one")
    band = t.get("band", int, 1, "a band number")
    if band < 1:
        raise t.err("band", f"bands count from 1, got {band}")
    for key in ("crs", "classes", "returns"):
        if key in t.d and (kind != "pointcloud" or (key != "crs" and path.suffix.lower() not in LAS_SUFFIXES)):
            raise t.err(key, f"only {'point clouds' if key == 'crs' else 'LAS/LAZ point clouds'} take {key}, {path.name} is a {kind} layer")
    crs = t.get("crs", str, None, 'a CRS such as "EPSG:2992"')
    points = None
    if "classes" in t.d or "returns" in t.d:
        classes = t.get("classes", (list, str), [GROUND], 'a list of class codes or "all"')
        returns = t.get("returns", (list, str), "all", 'a list of return numbers or "all", "first", "last", "single"')
        classes = None if classes == "all" else tuple(classes) if isinstance(classes, list) else classes
        returns = returns if isinstance(returns, str) else tuple(returns)
        for key, kw in (("classes", {"classes": classes}), ("returns", {"classes": classes, "returns": returns})):
            try:
                points = PointFilter(**kw)
            except LidarError as exc:
                raise t.err(key, str(exc)) from None
    try:
        return LayerSpec(
            name=name,
            path=path,
            kind=kind,
            layer=t.get("layer", str, None),
            where=t.get("where", str, None),
            restore_index=restore_index,
            band=band,
            allow_empty_geometries=t.get("allow_empty_geometries", bool, False, "true or false"),
            crs=None if crs is None else _parse_crs(t, "crs", crs),
            points=points,
        )
    except LayerError as exc:  # the where filter: the one check LayerSpec makes itself
        raise t.err("where", str(exc)) from None


def _parse_feature(source: Path, name: str, d: Any, layers: dict[str, LayerSpec]) -> FeatureSpec:
    t = _Table(source, f"features.{name}", d)
    ftype = t.get("type", str, what=f"one of {sorted(FEATURE_TYPES)}")
    if ftype not in FEATURE_TYPES:
        raise t.err("type", f"must be one of {sorted(FEATURE_TYPES)}, got {ftype!r}")
    required, optional = FEATURE_TYPES[ftype]
    t.check_keys(required | optional | {"type"})
    for k in sorted(required):
        if k not in t.d:
            raise t.err(k, "missing")

    def layer_refs(key: str, kinds: tuple[str, ...]) -> tuple[str, ...]:
        refs = t.str_list(key)
        if not refs:
            raise t.err(key, "needs at least one layer")
        for ref in refs:
            if ref not in layers:
                raise t.err(key, f"no layer {ref!r}; [layers] has {sorted(layers)}")
            if layers[ref].kind not in kinds:
                raise t.err(key, f"layer {ref!r} is a {layers[ref].kind} layer; {ftype} needs {' or '.join(kinds)}")
        return refs

    kw: dict[str, Any] = {"name": name, "type": ftype}
    if ftype in ("mask", "distance"):
        kw["layers"] = layer_refs("layers", ("vector",))
        kw["buffer_m"] = t.number("buffer_m", 0.0, nonneg=True)
        kw["all_touched"] = t.get("all_touched", bool, ftype == "distance", "true or false")
    if ftype == "mask":
        kw["labels"] = t.str_list("labels", ("no", "yes"))
        if len(kw["labels"]) != 2:
            raise t.err("labels", f"a mask needs two labels [outside, inside], got {list(kw['labels'])}")
    if ftype == "distance":
        kw["max_distance_m"] = t.number("max_distance_m", None, positive=True)
        kw["margin_m"] = t.number("margin_m", 0.0, nonneg=True)
        kw["to"] = t.get("to", str, "lines", '"lines" or "ends"')
        if kw["to"] not in DISTANCE_TO:
            raise t.err("to", f"must be one of {list(DISTANCE_TO)}, got {kw['to']!r}")
    if ftype in ("slope", "elevation"):
        kw["layers"] = layer_refs("layer", ("raster", "pointcloud"))
    if ftype == "classes":
        kw["source"] = t.get("source", str, what="a continuous feature name")
        breaks = t.get("breaks", list, what="a list of ascending numbers")
        if not breaks or not all(isinstance(b, int | float) and not isinstance(b, bool) for b in breaks):
            raise t.err("breaks", f"expected a non-empty list of numbers, got {breaks!r}")
        if any(b1 <= b0 for b0, b1 in zip(breaks, breaks[1:], strict=False)):
            raise t.err("breaks", f"must increase strictly, got {breaks}")
        kw["breaks"] = tuple(float(b) for b in breaks)
        default = _break_labels(kw["breaks"])
        kw["labels"] = t.str_list("labels", default)
        if len(kw["labels"]) != len(breaks) + 1:
            raise t.err("labels", f"{len(breaks)} breaks make {len(breaks) + 1} classes, got {len(kw['labels'])} labels")
    if ftype == "categories":
        kw["layers"] = layer_refs("layer", ("vector",))
        kw["attribute"] = t.get("attribute", str, what="an attribute (field) name")
        kw["classes"] = t.str_list("classes", ())
        kw["background"] = t.get("background", str, None)
    if ftype == "raster":
        kw["layers"] = layer_refs("layer", ("raster",))
        kw["categorical"] = t.get("categorical", bool, False, "true or false")
        kw["units"] = t.get("units", str, "")
        labels = t.get("labels", dict, {}, "a table code -> label")
        try:
            kw["code_labels"] = {int(k): str(v) for k, v in labels.items()}
        except ValueError:
            raise t.err("labels", f"keys must be integer codes, got {sorted(labels)}") from None
        if labels and not kw["categorical"]:
            raise t.err("labels", "labels only apply with categorical = true")
    if len(kw["labels"] if "labels" in kw else ()) != len(set(kw.get("labels", ()))):
        raise t.err("labels", f"labels must be distinct, got {list(kw['labels'])}")
    return FeatureSpec(**kw)


def _break_labels(breaks: tuple[float, ...]) -> tuple[str, ...]:
    """Default class labels from breaks: "<5", "5-15", ..., ">=30"."""
    fmt = [f"{b:g}" for b in breaks]
    return (f"<{fmt[0]}", *(f"{a}-{b}" for a, b in zip(fmt, fmt[1:], strict=False)), f">={fmt[-1]}")


def parse_config(d: dict, source: Path) -> RegionConfig:
    """Validate a parsed TOML document (``source`` is the config path, for messages and relative paths)."""
    unknown = sorted(set(d) - TOP_LEVEL_TABLES)
    if unknown:
        raise ConfigError(f"{source}: unknown top-level tables {unknown}; allowed {sorted(TOP_LEVEL_TABLES)}")
    if "region" not in d:
        raise ConfigError(f"{source}: missing [region] table (crs, bounds, cell_size)")
    region = _Table(source, "region", d["region"])
    grid = _parse_grid(region)
    name = region.get("name", str, source.stem)
    layers = {n: _parse_layer(source, n, v) for n, v in _Table(source, "layers", d.get("layers", {})).d.items()}
    features_t = _Table(source, "features", d.get("features", {}))
    if not features_t.d:
        raise ConfigError(f"{source}: no [features.<name>] tables")
    features = {n: _parse_feature(source, n, v, layers) for n, v in features_t.d.items()}
    for f in features.values():
        if f.type == "classes":
            src = features.get(f.source)
            if src is None or src.type not in ("slope", "elevation", "distance") and not (src.type == "raster" and not src.categorical):
                raise ConfigError(f"{source}: features.{f.name}.source: {f.source!r} is not a continuous feature of this config")
    model = None
    if "likelihood" in d:
        try:
            model = LikelihoodModel.from_dict({"likelihood": d["likelihood"], "meta": d.get("meta", {})}, str(source))
        except LikelihoodError as exc:  # names the file and table already
            raise ConfigError(str(exc)) from None
        missing = sorted(set(model.terms) - set(features))
        if missing:
            raise ConfigError(f"{source}: [likelihood.{missing[0]}] has no feature; features are {sorted(features)}")
    return RegionConfig(source, name, grid, layers, features, model)


def load_config(path: str | Path) -> RegionConfig:
    """Read and validate a region config TOML file."""
    path = Path(path).resolve()
    d = read_toml(path, "region config", ConfigError)
    return parse_config(d, path)
