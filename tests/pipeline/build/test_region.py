"""Config -> features -> prior on the bundled region and on small hand-made regions, vs independent oracles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyogrio.raw
import pytest
import rasterio
import shapely
from affine import Affine

from pipeline.build.region import build_features, build_prior, build_region_prior, write_features
from pipeline.config.region import load_config
from pipeline.features.stack import Feature, FeatureStack
from pipeline.gis.grid import NODATA_CODE, Grid
from pipeline.gis.layers import LayerError
from pipeline.prior.likelihood import LikelihoodError, LikelihoodModel
from pipeline.prior.terrain import PriorError, TerrainPrior
from tests.pipeline.gis_helpers import REGION_TOML, write_config, write_raster, write_vector


@pytest.fixture(scope="module")
def region():
    cfg = load_config(REGION_TOML)
    return cfg, build_features(cfg, progress=False)


def assert_float32_of(values: np.ndarray, exact: np.ndarray, atol: float = 0.0) -> None:
    """Distance features are float32: the rounding of the exact distance, within half a float32 ulp."""
    assert values.dtype == np.float32
    np.testing.assert_allclose(values, exact, rtol=2.0**-24 * (1 + 1e-9), atol=atol)


def layer_geoms(name: str) -> np.ndarray:
    _, _, wkb, _ = pyogrio.raw.read(REGION_TOML.parent / "region.gpkg", layer=name)
    return shapely.from_wkb(wkb)


def test_bundled_prior_is_the_normalised_product_of_hand_set_tables(region) -> None:
    cfg, stack = region
    prior = build_prior(stack, cfg.model)
    cell_area = 400.0
    assert prior.density.sum() * cell_area == pytest.approx(1.0, rel=1e-12)
    assert prior.rect_sum(*np.array(cfg.grid.bounds)[[0, 2, 1, 3]]) == pytest.approx(1.0, rel=1e-9)
    # independent product, written out from region.toml's tables
    slope = stack["slope"].values
    slope_r = np.select([slope < 4, slope < 8, slope < 12], [1.0, 0.7, 0.35], 0.1)
    d = stack["road_distance"].values.astype(np.float64)  # the tables evaluate in float64
    road_r = 0.9 * np.exp(-0.5 * ((d - 100.0) / 100.0) ** 2) + 0.1
    surface_r = np.array([1.0, 0.6, 0.4, 0.8])[stack["surface"].values]  # soil, sand, rock, clay
    veg = stack["vegetation"].values
    veg_r = np.where(veg == NODATA_CODE, 1.0, np.array([0.0, 1.0, 0.7, 0.5, 0.8])[np.clip(veg, 0, 4)])
    r = (stack["water"].values == 0) * (stack["obstacles"].values == 0) * slope_r * road_r * surface_r * veg_r
    np.testing.assert_allclose(prior.density, r / (r.sum() * cell_area), rtol=1e-12)
    assert prior.model["likelihood"]["road_distance"] == {"type": "road", "rmd": 100.0, "mv": 0.1, "nodata": 1.0}


def test_region_prior_is_the_plain_product_bit_for_bit(region) -> None:
    """build_region_prior (slope written over its DEM, features no table reads freed, r evaluated in
    bands, the density in r's buffer) against the plain path: the model evaluated over the whole
    stack, normalised into new arrays."""
    cfg, stack = region
    got = build_region_prior(cfg, progress=False)
    want = TerrainPrior.from_array(cfg.model.evaluate(stack), cfg.grid)
    for a, b in ((got.density, want.density), (got.sat, want.sat), (got.sat2, want.sat2)):
        np.testing.assert_array_equal(a, b)


def sample_cells(n: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 700, n), rng.integers(0, 700, n)


def test_water_mask_holds_buffered_lakes_and_river(region) -> None:
    cfg, stack = region
    water = shapely.union_all(shapely.buffer(np.concatenate([layer_geoms("lakes"), layer_geoms("rivers")]), 15.0))
    xc, yc = cfg.grid.cell_centres()
    rows, cols = sample_cells()
    wet_rows, wet_cols = np.nonzero(stack["water"].values)  # every water cell, plus the random sample
    rows, cols = np.concatenate([rows, wet_rows]), np.concatenate([cols, wet_cols])
    pts = shapely.points(xc[rows, cols], yc[rows, cols])
    expected = shapely.contains(water, pts)
    tie = shapely.distance(shapely.boundary(water), pts) < 0.5
    np.testing.assert_array_equal(stack["water"].values[rows, cols][~tie] == 1, expected[~tie])
    assert stack["water"].labels == {0: "dry", 1: "water"}


def test_road_distance_vs_brute_force(region) -> None:
    cfg, stack = region
    d = stack["road_distance"].values.astype(np.float64)  # the tables evaluate in float64
    roads = layer_geoms("roads")
    kept = [g for g, h in zip(roads, _highways(), strict=True) if h != "track"]
    xc, yc = cfg.grid.cell_centres()
    on_road = d == 0
    # every cell a kept road crosses is a road cell; no cell is more than half a diagonal from a road line
    dist_to_line = shapely.distance(shapely.union_all(kept), shapely.points(xc[on_road], yc[on_road]))
    assert dist_to_line.max() <= np.hypot(10, 10) + 1e-6
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, 700, 300), rng.integers(0, 700, 300)
    ry, rx = yc[on_road], xc[on_road]
    brute = np.sqrt((xc[rows, cols, None] - rx) ** 2 + (yc[rows, cols, None] - ry) ** 2).min(axis=1)
    assert_float32_of(stack["road_distance"].values[rows, cols], brute, atol=1e-9)


def _highways() -> np.ndarray:
    _, _, _, (highway,) = pyogrio.raw.read(REGION_TOML.parent / "region.gpkg", layer="roads", columns=["highway"])
    return highway


def test_slope_classes_follow_breaks(region) -> None:
    _, stack = region
    slope, cls = stack["slope"].values, stack["slope_class"].values
    np.testing.assert_array_equal(cls, (slope >= 4).astype(int) + (slope >= 8) + (slope >= 12))
    assert stack["slope_class"].labels == {0: "<4", 1: "4-8", 2: "8-12", 3: ">=12"}


def test_surface_categories_from_polygon_attribute(region) -> None:
    cfg, stack = region
    _, _, wkb, (material,) = pyogrio.raw.read(REGION_TOML.parent / "region.gpkg", layer="surface", columns=["material"])
    geoms = shapely.from_wkb(wkb)
    xc, yc = cfg.grid.cell_centres()
    rows, cols = sample_cells(seed=1)
    pts = shapely.points(xc[rows, cols], yc[rows, cols])
    got = stack["surface"]
    for geom, mat in zip(geoms, material, strict=True):
        inside = shapely.contains(geom, pts) & (shapely.distance(shapely.boundary(geom), pts) > 0.5)
        assert {got.label(c) for c in np.unique(got.values[rows, cols][inside])} <= {mat}
    covered = shapely.contains(shapely.union_all(geoms), pts)
    assert covered.mean() > 0.99 and (got.values[rows, cols][covered] != NODATA_CODE).all()


def test_vegetation_raster_labels(region) -> None:
    _, stack = region
    with rasterio.open(REGION_TOML.parent / "vegetation.tif") as src:
        raw = src.read(1)  # same grid: nearest resampling is the identity
    np.testing.assert_array_equal(stack["vegetation"].values, raw)
    assert stack["vegetation"].label(3) == "forest"


# ---- small hand-made regions --------------------------------------------------------------------

GRID_BOUNDS = [500_000, 6_200_000, 501_000, 6_200_800]  # 50 x 40 cells of 20 m


def small_region(tmp_path: Path, features: dict, likelihood: dict | None = None, **layers) -> Path:
    doc = {
        "region": {"crs": "EPSG:32734", "bounds": GRID_BOUNDS, "cell_size": 20.0},
        "layers": {name: {"path": str(path)} for name, path in layers.items()},
        "features": features,
    }
    if likelihood:
        doc["likelihood"] = likelihood
    return write_config(tmp_path / "small.toml", doc)


def patches(tmp_path: Path) -> Path:
    polys = [shapely.box(500_100, 6_200_100, 500_400, 6_200_400), shapely.box(500_500, 6_200_300, 500_900, 6_200_700)]
    return write_vector(tmp_path / "patches.gpkg", polys, {"material": ["sand", "rock"]})


def test_categories_unknown_value_names_it(tmp_path: Path) -> None:
    cfg = load_config(small_region(
        tmp_path, {"surface": {"type": "categories", "layer": "p", "attribute": "material", "classes": ["sand", "soil"]}},
        p=patches(tmp_path)))
    with pytest.raises(LayerError, match=r"patches\.gpkg.*\[layers\.p\].*'material' has value 'rock'.*\[features\.surface\]"):
        build_features(cfg, progress=False)


def test_categories_background_label(tmp_path: Path) -> None:
    cfg = load_config(small_region(
        tmp_path, {"surface": {"type": "categories", "layer": "p", "attribute": "material", "background": "soil"}},
        p=patches(tmp_path)))
    f = build_features(cfg, progress=False)["surface"]
    xc, yc = cfg.grid.cell_centres()
    in_sand = (xc > 500_100) & (xc < 500_400) & (yc > 6_200_100) & (yc < 6_200_400)
    in_rock = (xc > 500_500) & (xc < 500_900) & (yc > 6_200_300) & (yc < 6_200_700)
    labels = np.vectorize(f.label)(f.values)
    assert (labels[in_sand] == "sand").all() and (labels[in_rock] == "rock").all()
    assert (labels[~in_sand & ~in_rock] == "soil").all()


def test_category_without_likelihood_is_named(tmp_path: Path) -> None:
    cfg = load_config(small_region(
        tmp_path, {"surface": {"type": "categories", "layer": "p", "attribute": "material"}},
        {"surface": {"type": "categorical", "values": {"sand": 1.0}}}, p=patches(tmp_path)))
    with pytest.raises(LikelihoodError, match=r"'surface'.*category 'rock'.*no likelihood"):
        build_prior(build_features(cfg, progress=False), cfg.model)


def test_table_zero_everywhere_is_named(tmp_path: Path) -> None:
    cfg = load_config(small_region(
        tmp_path, {"patch": {"type": "mask", "layers": ["p"]}},
        {"patch": {"type": "categorical", "values": {"no": 0.0, "yes": 0.0}}}, p=patches(tmp_path)))
    with pytest.raises(PriorError, match=r"\[likelihood\.patch\] is zero on every cell"):
        build_prior(build_features(cfg, progress=False), cfg.model)


def test_tables_whose_zeros_cover_the_grid_together(tmp_path: Path) -> None:
    p = patches(tmp_path)
    cfg = load_config(small_region(
        tmp_path, {"a": {"type": "mask", "layers": ["p"]}, "b": {"type": "mask", "layers": ["p"]}},
        {"a": {"type": "categorical", "values": {"no": 0.0, "yes": 1.0}},
         "b": {"type": "categorical", "values": {"no": 1.0, "yes": 0.0}}}, p=p))
    with pytest.raises(PriorError, match="zero everywhere"):
        build_prior(build_features(cfg, progress=False), cfg.model)


def test_distance_to_any_layer_with_cap(tmp_path: Path) -> None:
    cfg = load_config(small_region(
        tmp_path, {"to_patch": {"type": "distance", "layers": ["p"], "max_distance_m": 150.0}}, p=patches(tmp_path)))
    d = build_features(cfg, progress=False)["to_patch"]
    assert d.kind == "continuous" and d.units == "m"
    xc, yc = cfg.grid.cell_centres()
    inside = d.values == 0
    brute = np.sqrt((xc[..., None] - xc[inside]) ** 2 + (yc[..., None] - yc[inside]) ** 2).min(axis=-1)
    assert_float32_of(d.values, np.minimum(brute, 150.0))


def test_slope_from_dem_in_another_crs_is_the_plane_angle(tmp_path: Path) -> None:
    """A plane rising 0.1 m per metre eastward, stored in UTM 35S: slope atan(0.1) everywhere, edges included."""
    from pyproj import Transformer

    to35 = Transformer.from_crs("EPSG:32734", "EPSG:32735", always_xy=True)
    x0, y0 = to35.transform(499_000, 6_201_800)
    res = 10.0
    cols, rows = np.meshgrid(np.arange(500) + 0.5, np.arange(400) + 0.5)
    x35, y35 = x0 + cols * res, y0 - rows * res
    x34, _ = Transformer.from_crs("EPSG:32735", "EPSG:32734", always_xy=True).transform(x35, y35)
    dem = write_raster(tmp_path / "dem.tif", (0.1 * (x34 - 500_000)).astype(np.float64),
                       Affine(res, 0, x0, 0, -res, y0), "EPSG:32735")
    cfg = load_config(small_region(tmp_path, {"slope": {"type": "slope", "layer": "dem"}}, dem=dem))
    slope = build_features(cfg, progress=False)["slope"].values
    np.testing.assert_allclose(slope, np.degrees(np.arctan(0.1)), atol=0.05)


def test_features_sharing_a_dem_get_their_own_grids(tmp_path: Path) -> None:
    """The DEM is read ahead of the features (on a thread) once per layer; a second feature of the same
    layer reads its own grid, so the first one's slope, computed in place, is not its elevation."""
    from pipeline.features.slope import slope_deg
    from pipeline.gis.layers import read_dem

    cols, rows = np.meshgrid(np.arange(60) + 0.5, np.arange(50) + 0.5)
    dem = write_raster(tmp_path / "dem.tif", (100 + 0.3 * cols ** 1.5 + 0.2 * rows).astype(np.float32),
                       Affine(20.0, 0, GRID_BOUNDS[0], 0, -20.0, GRID_BOUNDS[3]), "EPSG:32734")
    cfg = load_config(small_region(tmp_path, {"slope": {"type": "slope", "layer": "dem"},
                                              "height": {"type": "elevation", "layer": "dem"},
                                              "slope_again": {"type": "slope", "layer": "dem"}}, dem=dem))
    stack = build_features(cfg, progress=False)
    z = read_dem(cfg.layers["dem"], cfg.grid)
    np.testing.assert_array_equal(stack["height"].values, z)
    expected = slope_deg(z, cfg.grid.dx, cfg.grid.dy)
    np.testing.assert_array_equal(stack["slope"].values, expected)
    np.testing.assert_array_equal(stack["slope_again"].values, expected)


def test_slope_from_point_cloud(tmp_path: Path) -> None:
    pytest.importorskip("open3d")
    rng = np.random.default_rng(3)
    n = 40_000
    x, y = rng.uniform(499_900, 501_100, n), rng.uniform(6_199_900, 6_200_900, n)
    z = 0.2 * (y - 6_200_000)  # rises northward, 0.2 m per metre
    cloud = tmp_path / "ground.xyz"
    np.savetxt(cloud, np.column_stack([x, y, z]), fmt="%.3f")
    cfg = load_config(small_region(tmp_path, {"slope": {"type": "slope", "layer": "lidar"}}, lidar=cloud))
    assert cfg.layers["lidar"].kind == "pointcloud"
    slope = build_features(cfg, progress=False)["slope"].values
    np.testing.assert_allclose(slope, np.degrees(np.arctan(0.2)), atol=0.1)


# ---- writing feature GeoTIFFs -------------------------------------------------------------------

def tiny_stack() -> FeatureStack:
    grid = Grid.from_bounds((0, 0, 100, 60), 20.0, "EPSG:32634")
    stack = FeatureStack(grid)
    stack.add(Feature("water", np.array([[0, 1, 0, 0, 1]] * 3, dtype=np.int16), "categorical", labels={0: "dry", 1: "water"}))
    stack.add(Feature("road_distance", np.arange(15, dtype=float).reshape(3, 5) * 20.0, "continuous", units="m"))
    return stack


def test_write_features_round_trip(tmp_path: Path) -> None:
    stack = tiny_stack()
    paths = write_features(stack, tmp_path / "out")
    assert [p.name for p in paths] == ["water.tif", "road_distance.tif"]
    with rasterio.open(paths[0]) as src:
        np.testing.assert_array_equal(src.read(1), stack["water"].values)
        assert src.nodata == NODATA_CODE and src.tags()["LABELS"] == '{"0": "dry", "1": "water"}'
        assert src.crs.to_epsg() == 32634 and src.transform == stack.grid.transform
    with rasterio.open(paths[1]) as src:
        np.testing.assert_array_equal(src.read(1), stack["road_distance"].values.astype(np.float32))
        assert src.tags()["UNITS"] == "m"


def test_write_features_keeps_large_codes(tmp_path: Path) -> None:
    grid = Grid.from_bounds((0, 0, 40, 20), 20.0, "EPSG:32634")
    stack = FeatureStack(grid)
    stack.add(Feature("landcover", np.array([[7, 70_000]], dtype=np.int32), "categorical"))
    (path,) = write_features(stack, tmp_path)
    with rasterio.open(path) as src:
        np.testing.assert_array_equal(src.read(1), [[7, 70_000]])


def test_failed_feature_write_leaves_nothing(tmp_path: Path, monkeypatch) -> None:
    real_open = rasterio.open
    calls = []

    def failing_open(path, mode="r", **kw):
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        return real_open(path, mode, **kw)

    monkeypatch.setattr(rasterio, "open", failing_open)
    out = tmp_path / "out"
    with pytest.raises(OSError, match="disk full"):
        write_features(tiny_stack(), out)
    assert list(out.iterdir()) == []


def test_model_override_and_provenance(region) -> None:
    cfg, stack = region
    model = LikelihoodModel.from_dict({"likelihood": {"water": {"type": "categorical", "values": {"dry": 1.0, "water": 0.0}}}})
    prior = build_prior(stack, model, {"config": "x.toml"})
    expected = (stack["water"].values == 0) / ((stack["water"].values == 0).sum() * 400.0)
    np.testing.assert_allclose(prior.density, expected)
    assert prior.model["provenance"] == {"config": "x.toml"}


def test_bundled_data_is_what_generate_py_makes(tmp_path: Path) -> None:
    """The committed terrain_data files are reproduced by the committed generator (fixed seed)."""
    from terrain_data.generate import main as generate

    generate(tmp_path)
    for name in ("dem.tif", "vegetation.tif"):
        with rasterio.open(tmp_path / name) as new, rasterio.open(REGION_TOML.parent / name) as old:
            np.testing.assert_array_equal(new.read(1), old.read(1))
            assert new.transform == old.transform and new.crs == old.crs and new.nodata == old.nodata
    for layer in ("roads", "rivers", "lakes", "obstacles", "surface"):
        new = pyogrio.raw.read(tmp_path / "region.gpkg", layer=layer)
        old = pyogrio.raw.read(REGION_TOML.parent / "region.gpkg", layer=layer)
        assert list(new[2]) == list(old[2])
        for a, b in zip(new[3], old[3], strict=True):
            np.testing.assert_array_equal(a, b)


def test_distance_margin_sees_roads_outside_the_grid(tmp_path: Path) -> None:
    """A road 105 m north of the grid: without a margin it is invisible, with one the distance is exact."""
    road = write_vector(tmp_path / "road.gpkg", [shapely.LineString([(499_000, 6_200_905), (502_000, 6_200_905)])])
    feats = {"near": {"type": "distance", "layers": ["r"], "margin_m": 200.0},
             "blind": {"type": "distance", "layers": ["r"]}}
    cfg = load_config(small_region(tmp_path, feats, r=road))
    with pytest.warns(UserWarning, match="no geometry touches the grid"):
        stack = build_features(cfg, progress=False)
    assert np.isinf(stack["blind"].values).all()
    _, yc = cfg.grid.cell_centres()
    # the road burns the padded row of cells 6_200_900..6_200_920 m, centre 6_200_910 m
    np.testing.assert_allclose(stack["near"].values, 6_200_910.0 - yc, rtol=1e-12)


def test_distance_to_line_ends_is_the_brute_force_distance_to_their_cells(tmp_path: Path) -> None:
    """to = "ends": distance from every cell centre to the nearest centre of a cell holding a line's end
    point (the distance transform's rule), brute force over the ends; a point layer is a named error."""
    rng = np.random.default_rng(3)
    lines = [shapely.LineString(rng.uniform([500_010, 6_200_010], [500_990, 6_200_790], (k, 2))) for k in (2, 3, 5, 4)]
    path = write_vector(tmp_path / "tracks.gpkg", lines)
    pts = write_vector(tmp_path / "pts.gpkg", [shapely.Point(500_500, 6_200_400)])
    cfg = load_config(small_region(tmp_path, {"ends": {"type": "distance", "layers": ["t"], "to": "ends"},
                                              "lines": {"type": "distance", "layers": ["t"]}}, t=path))
    stack = build_features(cfg, progress=False)
    xc, yc = cfg.grid.cell_centres()
    ends = np.array([c for g in lines for c in (g.coords[0], g.coords[-1])])
    r, c, _ = cfg.grid.cell_index(ends[:, 0], ends[:, 1])
    ex, ey = xc[r, c], yc[r, c]
    brute = np.min(np.hypot(xc[..., None] - ex, yc[..., None] - ey), axis=-1)
    assert_float32_of(stack["ends"].values, brute, atol=1e-9)
    assert (stack["ends"].values >= stack["lines"].values).all()
    bad = load_config(small_region(tmp_path, {"ends": {"type": "distance", "layers": ["p"], "to": "ends"}}, p=pts))
    with pytest.raises(LayerError, match=r"\[features\.ends\] \(to = \"ends\"\).*'p'.*need lines.*Point"):
        build_features(bad, progress=False)
