"""Reading layers onto a grid: reprojection vs closed forms, filters, repairs, rasters, and every bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import rasterio
import shapely
from affine import Affine
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyproj import Proj, Transformer

from pipeline.gis.grid import NODATA_CODE, Grid
from pipeline.gis.layers import (
    LayerError,
    LayerSpec,
    LayerWarning,
    read_dem,
    read_raster,
    read_vector,
    warp_scale,
)
from tests.pipeline.gis_helpers import tree_hashes, write_raster, write_vector

# 10 km x 8 km around lon 21 E (zone 34's central meridian), lat -34 S
GRID = Grid.from_bounds((495_000.0, 6_232_000.0, 505_000.0, 6_240_000.0), 100.0, "EPSG:32734")
TO_LONLAT = Transformer.from_crs("EPSG:32734", "EPSG:4326", always_xy=True)


def spec(path: Path, **kw) -> LayerSpec:
    return LayerSpec(name=kw.pop("name", "test"), path=path, kind=kw.pop("kind", "vector"), **kw)


def test_reprojects_lonlat_points_onto_the_central_meridian(tmp_path: Path) -> None:
    """On a zone's central meridian the UTM easting is 500 000 m exactly, whatever the latitude."""
    lats = np.array([-34.02, -33.99, -33.96])
    p = write_vector(tmp_path / "pts.geojson", list(shapely.points(np.full(3, 21.0), lats)), crs="EPSG:4326")
    layer = read_vector(spec(p), GRID)
    xy = shapely.get_coordinates(layer.geometries)
    np.testing.assert_allclose(xy[:, 0], 500_000.0, atol=1e-6)
    assert np.all(np.diff(xy[:, 1]) > 0)  # north stays north: axis order is lon, lat
    # northing closed form check for distances: 0.03 deg of latitude is about 3.33 km
    assert xy[1, 1] - xy[0, 1] == pytest.approx(0.03 * 110_900, rel=2e-3)


def test_where_filter_and_attributes(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    kinds = rng.choice(["primary", "secondary", "track"], 40)
    lines = [shapely.LineString([(496_000 + 100 * i, 6_233_000), (496_000 + 100 * i, 6_239_000)]) for i in range(40)]
    p = write_vector(tmp_path / "roads.gpkg", lines, {"highway": kinds}, layer="roads")
    layer = read_vector(spec(p, layer="roads", where="highway IN ('primary', 'secondary')"), GRID, ["highway"])
    expected = np.flatnonzero(np.isin(kinds, ["primary", "secondary"]))
    assert layer.geometries.size == expected.size
    np.testing.assert_array_equal(layer.attributes["highway"], kinds[expected])
    xs = shapely.get_coordinates(layer.geometries)[::2, 0]
    np.testing.assert_allclose(xs, 496_000 + 100 * expected)


def test_invalid_geometry_repaired_and_counted(tmp_path: Path, caplog) -> None:
    bowtie = shapely.Polygon([(496_000, 6_233_000), (497_000, 6_234_000), (497_000, 6_233_000), (496_000, 6_234_000)])
    square = shapely.box(498_000, 6_233_000, 499_000, 6_234_000)
    p = write_vector(tmp_path / "obst.gpkg", [bowtie, square])
    with caplog.at_level(logging.WARNING, logger="pipeline.gis.layers"):
        layer = read_vector(spec(p), GRID)
    assert layer.n_repaired == 1
    assert shapely.is_valid(layer.geometries).all()
    # the bow-tie's two triangles: 2 x (1000 x 500 / 2)
    assert shapely.area(layer.geometries[0]) == pytest.approx(500_000.0)
    assert "repaired 1 invalid geometries" in caplog.text and "obst.gpkg" in caplog.text


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(LayerError, match=r"nope\.gpkg.*\[layers\.test\].*file not found"):
        read_vector(spec(tmp_path / "nope.gpkg"), GRID)


def test_unknown_layer_lists_the_available_ones(tmp_path: Path) -> None:
    p = write_vector(tmp_path / "x.gpkg", [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], layer="lakes")
    with pytest.raises(LayerError, match=r"x\.gpkg, layer 'rivers'.*no layer 'rivers'; the file has \['lakes'\]"):
        read_vector(spec(p, layer="rivers"), GRID)


def test_several_layers_need_a_name(tmp_path: Path) -> None:
    p = write_vector(tmp_path / "x.gpkg", [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], layer="lakes")
    write_vector(p, [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], layer="ponds")
    with pytest.raises(LayerError, match=r"x\.gpkg.*several layers \['lakes', 'ponds'\]; set layer"):
        read_vector(spec(p), GRID)
    assert read_vector(spec(p, layer="ponds"), GRID).geometries.size == 1


def test_unknown_attribute(tmp_path: Path) -> None:
    p = write_vector(tmp_path / "x.gpkg", [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], {"kind": ["a"]})
    with pytest.raises(LayerError, match=r"x\.gpkg.*no attribute 'material'"):
        read_vector(spec(p), GRID, ["material"])


def test_bad_where_clause(tmp_path: Path) -> None:
    p = write_vector(tmp_path / "x.gpkg", [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], {"kind": ["a"]})
    with pytest.raises(LayerError, match=r"x\.gpkg.*where = \"colour = 'red'\""):
        read_vector(spec(p, where="colour = 'red'"), GRID)


def test_corrupt_vector_file(tmp_path: Path) -> None:
    p = tmp_path / "broken.gpkg"
    p.write_bytes(b"SQLite format 3\x00" + bytes(range(256)) * 4)
    with pytest.raises(LayerError, match=r"broken\.gpkg.*\[layers\.test\]"):
        read_vector(spec(p), GRID)


def test_layer_without_crs(tmp_path: Path) -> None:
    p = write_vector(tmp_path / "nocrs.shp", [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], crs=None)
    assert not p.with_suffix(".prj").exists()
    with pytest.raises(LayerError, match=r"nocrs\.shp.*no CRS"):
        read_vector(spec(p), GRID)


def test_empty_and_off_grid_layers_warn(tmp_path: Path) -> None:
    p = write_vector(tmp_path / "x.gpkg", [shapely.box(496_000, 6_233_000, 497_000, 6_234_000)], {"kind": ["a"]})
    with pytest.warns(LayerWarning, match=r"x\.gpkg.*empty after where"):
        layer = read_vector(spec(p, where="kind = 'b'"), GRID)
    assert layer.geometries.size == 0
    far = write_vector(tmp_path / "far.gpkg", [shapely.box(600_000, 6_000_000, 601_000, 6_001_000)])
    with pytest.warns(LayerWarning, match=r"far\.gpkg.*no geometry touches the grid"):
        read_vector(spec(far), GRID)


def _stale_shapefile(folder: Path) -> Path:
    """A shapefile whose .shx says record 2 is shorter than it is (as record 31 of Swellendam's water.shp)."""
    def poly(n: int, x0: float) -> shapely.Polygon:
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return shapely.Polygon(np.column_stack([x0 + 300 * np.cos(a), 6_236_000 + 300 * np.sin(a)]))

    path = write_vector(folder / "lakes.shp", [poly(5, 497_000), poly(40, 499_000), poly(7, 501_000)], {"n": [5, 40, 7]})
    shx = bytearray(path.with_suffix(".shx").read_bytes())
    record = 100 + 8  # 100-byte header, then (offset, content length) per record as big-endian 16-bit words
    length = int.from_bytes(shx[record + 4:record + 8], "big")
    shx[record + 4:record + 8] = (length - 40).to_bytes(4, "big")
    path.with_suffix(".shx").write_bytes(bytes(shx))
    return path


def test_stale_shapefile_index_is_an_error_then_restores_on_a_copy(tmp_path: Path) -> None:
    """GDAL reads this short record as a missing shape, silently (Swellendam's raises; see test_real_data):
    an error naming the layer and both ways out, unless the layer allows empty geometries (then a warning)."""
    p = _stale_shapefile(tmp_path)
    before = tree_hashes(tmp_path, "lakes.*")
    with pytest.raises(LayerError) as info:
        read_vector(spec(p, name="lakes"), GRID)
    msg = str(info.value)
    assert "lakes.shp" in msg and "1 of 3 features have no geometry (FIDs 1)" in msg and "restore_index = true" in msg
    assert "allow_empty_geometries = true in [layers.lakes]" in msg
    with pytest.warns(LayerWarning) as record:
        layer = read_vector(spec(p, name="lakes", allow_empty_geometries=True), GRID)
    msg = str(record[0].message)
    assert "lakes.shp" in msg and "1 of 3 features have no geometry" in msg and "skipped" in msg
    assert layer.geometries.size == 2
    layer = read_vector(spec(p, name="lakes", restore_index=True), GRID, ["n"])
    np.testing.assert_array_equal(layer.attributes["n"], [5, 40, 7])
    assert [len(shapely.get_coordinates(g)) for g in layer.geometries] == [6, 41, 8]  # rings closed
    assert tree_hashes(tmp_path, "lakes.*") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(before)


def test_unreadable_shapefile_names_the_restore_option() -> None:
    """The message for a shapefile GDAL refuses (the exception is GDAL's, as raised for Swellendam's water.shp)."""
    from pipeline.gis.layers import _stale_index_hint

    exc = RuntimeError("Corrupted .shp file : shape 30, nPoints=21, nParts=1, nEntitySize=216.")
    msg = _stale_index_hint(spec(Path("/data/water.shp"), name="water"), exc)
    assert "/data/water.shp" in msg and "SHAPE_RESTORE_SHX" in msg and "restore_index = true in [layers.water]" in msg


# ---- rasters ---------------------------------------------------------------------------------------

def _lonlat_raster(tmp_path: Path, fn, dtype, nodata=None, name="r.tif") -> Path:
    """A geographic raster of ``fn(lon, lat)`` sampled at pixel centres covering GRID generously."""
    res = 0.0005
    lon0, lat1 = 20.93, -33.90
    w, h = 400, 400
    lon = lon0 + (np.arange(w) + 0.5) * res
    lat = lat1 - (np.arange(h) + 0.5) * res
    lon2, lat2 = np.meshgrid(lon, lat)
    data = fn(lon2, lat2).astype(dtype)
    return write_raster(tmp_path / name, data, Affine(res, 0, lon0, 0, -res, lat1), "EPSG:4326", nodata)


def test_dem_reprojected_bilinear_reproduces_a_plane(tmp_path: Path) -> None:
    """Bilinear resampling is exact on a field linear in the source coordinates, up to GDAL's approximate
    transformer (error <= 0.125 source pixels by default: 0.25 m here, where the plane rises 2 m per pixel)."""
    def plane(lon, lat):
        return 500.0 + 4000.0 * (lon - 21.0) - 3000.0 * (lat + 34.0)

    dem = read_dem(spec(_lonlat_raster(tmp_path, plane, np.float32), kind="raster"), GRID)
    lon, lat = TO_LONLAT.transform(*GRID.cell_centres())
    np.testing.assert_allclose(dem, plane(lon, lat), atol=0.25)


def test_nodata_kept_as_nan(tmp_path: Path) -> None:
    hole_lon, hole_lat = (20.99, 21.01), (-34.03, -34.01)

    def field(lon, lat):
        z = 100.0 + 0 * lon
        z[(lon > hole_lon[0]) & (lon < hole_lon[1]) & (lat > hole_lat[0]) & (lat < hole_lat[1])] = -9999.0
        return z

    dem = read_dem(spec(_lonlat_raster(tmp_path, field, np.float32, nodata=-9999.0), kind="raster"), GRID)
    lon, lat = TO_LONLAT.transform(*GRID.cell_centres())
    margin = 0.0015  # three source pixels
    inside = (lon > hole_lon[0] + margin) & (lon < hole_lon[1] - margin) & (lat > hole_lat[0] + margin) & (lat < hole_lat[1] - margin)
    outside = (lon < hole_lon[0] - margin) | (lon > hole_lon[1] + margin) | (lat < hole_lat[0] - margin) | (lat > hole_lat[1] + margin)
    assert inside.sum() > 50
    assert np.isnan(dem[inside]).all()
    np.testing.assert_allclose(dem[outside], 100.0, atol=1e-4)


def test_categorical_raster_nearest(tmp_path: Path) -> None:
    def quadrants(lon, lat):
        return (1 + (lon > 21.0) + 2 * (lat > -34.0)).astype(np.uint8)

    codes = read_raster(spec(_lonlat_raster(tmp_path, quadrants, np.uint8, nodata=0), kind="raster"), GRID, categorical=True)
    assert codes.dtype == np.int32
    lon, lat = TO_LONLAT.transform(*GRID.cell_centres())
    away = (np.abs(lon - 21.0) > 0.001) & (np.abs(lat + 34.0) > 0.001)
    np.testing.assert_array_equal(codes[away], quadrants(lon, lat)[away])
    assert set(np.unique(codes)) <= {1, 2, 3, 4}


def test_categorical_raster_nodata_code(tmp_path: Path) -> None:
    def left_missing(lon, lat):
        return np.where(lon < 21.0, 0, 3).astype(np.uint8)

    codes = read_raster(spec(_lonlat_raster(tmp_path, left_missing, np.uint8, nodata=0), kind="raster"), GRID, categorical=True)
    lon, _ = TO_LONLAT.transform(*GRID.cell_centres())
    assert (codes[lon < 20.999] == NODATA_CODE).all() and (codes[lon > 21.001] == 3).all()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31), src_res=st.sampled_from([30.0, 40.0, 90.0]), holes=st.booleans(),
       categorical=st.booleans(), lonlat=st.booleans())
def test_raster_read_is_gdals_masked_warp(tmp_path: Path, seed, src_res, holes, categorical, lonlat) -> None:
    """read_raster equals GDAL's warp with no-data masks bit for bit, whether the source has no-data
    cells (the masked warp itself) or none (the unmasked warp, which must give the same numbers and
    leave the cells it does not reach as no data); rasters offset to cover the grid partly."""
    from rasterio.warp import Resampling, reproject

    rng = np.random.default_rng(seed)
    h, w = rng.integers(20, 90, 2)
    # the raster's north-west corner anywhere over the grid, so it covers part of it
    x0, y1 = rng.uniform(495_000.0, 505_000.0) - w * src_res / 2, rng.uniform(6_232_000.0, 6_240_000.0) + h * src_res / 2
    crs = "EPSG:32733" if lonlat else "EPSG:32734"  # the neighbouring zone: a real reprojection
    if lonlat:
        x0, y1 = Transformer.from_crs("EPSG:32734", crs, always_xy=True).transform(x0, y1)
    values = (rng.integers(1, 9, (h, w)) if categorical else rng.normal(300.0, 40.0, (h, w))).astype(np.int16 if categorical else np.float32)
    nodata = -1 if categorical else -9999.0
    if holes:
        values[rng.random((h, w)) < 0.1] = nodata
    path = write_raster(tmp_path / f"r{seed}.tif", values, Affine(src_res, 0, x0, 0, -src_res, y1), crs, nodata)
    got = read_raster(spec(path, kind="raster"), GRID, categorical=categorical)
    fill, dtype = (NODATA_CODE, np.int32) if categorical else (np.nan, np.float32)
    src = np.where(values == nodata, fill, values).astype(dtype)
    expected = np.full(GRID.shape, fill, dtype=dtype)
    with rasterio.open(path) as raster:  # the whole raster, at the kernel width warp_scale fixes
        xscale, yscale = warp_scale(raster, GRID)
    reproject(src, expected, src_transform=Affine(src_res, 0, x0, 0, -src_res, y1), src_crs=crs, src_nodata=fill,
              dst_transform=GRID.transform, dst_crs=GRID.crs, dst_nodata=fill,
              resampling=Resampling.nearest if categorical else Resampling.bilinear, XSCALE=repr(xscale), YSCALE=repr(yscale))
    np.testing.assert_array_equal(got, expected)
    assert (got != fill).any() if categorical else np.isfinite(got).any()


@pytest.mark.parametrize("crs", ["EPSG:32734", "EPSG:32733", "EPSG:4326"])
@pytest.mark.parametrize("src_res", [30.0, 250.0])
def test_warp_scale_is_grid_cells_per_source_pixel(tmp_path: Path, crs, src_res) -> None:
    """The same CRS: the ratio of pixel sizes. Another UTM zone: a pixel's ground length is res / k_src,
    which measures res k_grid / k_src on the grid (pyproj's point scale factors). Degrees: a pixel of
    1/3600 degree is R dlat along a meridian (the meridional radius) and N cos(lat) dlon along a parallel."""
    lon, lat = 21.3, -34.0
    if crs == "EPSG:4326":
        deg = src_res / 30.0 / 3600.0
        t = Affine(deg, 0, lon - 10 * deg, 0, -deg, lat + 10 * deg)
    else:
        x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)  # the raster's centre
        t = Affine(src_res, 0, x - 10 * src_res, 0, -src_res, y + 10 * src_res)
    path = write_raster(tmp_path / "r.tif", np.zeros((20, 20), np.float32), t, crs)
    with rasterio.open(path) as src:
        xscale, yscale = warp_scale(src, GRID)
    k_grid = Proj("EPSG:32734").get_factors(lon, lat).meridional_scale
    if crs == "EPSG:4326":
        a, f = 6_378_137.0, 1 / 298.257223563
        e2 = f * (2 - f)
        s2 = np.sin(np.radians(lat)) ** 2
        n_radius, m_radius = a / np.sqrt(1 - e2 * s2), a * (1 - e2) / (1 - e2 * s2) ** 1.5
        expected = (k_grid * n_radius * np.cos(np.radians(lat)) * np.radians(deg) / 100.0, k_grid * m_radius * np.radians(deg) / 100.0)
    else:
        k_src = Proj(crs).get_factors(lon, lat).meridional_scale
        expected = (src_res * k_grid / k_src / 100.0,) * 2
    np.testing.assert_allclose((xscale, yscale), expected, rtol=1e-5)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31), src_res=st.sampled_from([5.0, 10.0, 20.0, 30.0, 45.0, 90.0, 150.0]), holes=st.booleans())
def test_a_window_of_the_grid_reads_what_the_whole_grid_reads(tmp_path: Path, seed, src_res, holes) -> None:
    """A tile's read is the whole grid's, cropped, bit for bit, when GDAL downsamples too: the kernel
    width is the raster's (warp_scale), not one GDAL derives from the part of the raster under the tile."""
    rng = np.random.default_rng(seed)
    h, w = (rng.integers(2_000, 12_000, 2) / src_res).astype(int) + 4
    x0, y1 = rng.uniform(495_000.0, 500_000.0), rng.uniform(6_236_000.0, 6_240_000.0)
    values = rng.normal(300.0, 40.0, (h, w)).astype(np.float32)
    if holes:
        values[rng.random((h, w)) < 0.1] = -9999.0
    path = write_raster(tmp_path / f"r{seed}.tif", values, Affine(src_res, 0, x0, 0, -src_res, y1), "EPSG:32734", -9999.0)
    r0, c0 = rng.integers(0, 60), rng.integers(0, 80)
    hh, ww = rng.integers(5, 80 - r0 + 1), rng.integers(5, 100 - c0 + 1)
    whole = read_raster(spec(path, kind="raster"), GRID, warn_empty=False)
    tile = read_raster(spec(path, kind="raster"), GRID.window_grid(r0, c0, hh, ww), warn_empty=False)
    np.testing.assert_array_equal(tile, whole[r0 : r0 + hh, c0 : c0 + ww])


def test_all_nodata_dem_is_an_error(tmp_path: Path) -> None:
    p = _lonlat_raster(tmp_path, lambda lon, lat: np.full(lon.shape, -9999.0), np.float32, nodata=-9999.0, name="dem.tif")
    with pytest.raises(LayerError, match=r"dem\.tif.*no data on the grid"):
        read_dem(spec(p, kind="raster"), GRID)


def test_off_grid_dem_is_an_error(tmp_path: Path) -> None:
    p = write_raster(tmp_path / "far.tif", np.ones((10, 10), np.float32), Affine(0.01, 0, 10.0, 0, -0.01, 50.0), "EPSG:4326")
    with pytest.raises(LayerError, match=r"far\.tif.*no data on the grid"):
        read_dem(spec(p, kind="raster"), GRID)


def test_raster_without_crs(tmp_path: Path) -> None:
    p = write_raster(tmp_path / "nocrs.tif", np.ones((10, 10), np.float32), Affine(100, 0, 495_000, 0, -100, 6_240_000), None)
    with pytest.raises(LayerError, match=r"nocrs\.tif.*no CRS"):
        read_dem(spec(p, kind="raster"), GRID)


def test_corrupt_and_missing_raster(tmp_path: Path) -> None:
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00" + b"\x13" * 500)
    with pytest.raises(LayerError, match=r"bad\.tif.*not a readable raster"):
        read_dem(spec(bad, kind="raster"), GRID)
    with pytest.raises(LayerError, match=r"gone\.tif.*file not found"):
        read_dem(spec(tmp_path / "gone.tif", kind="raster"), GRID)


def test_categorical_raster_must_hold_integers(tmp_path: Path) -> None:
    p = _lonlat_raster(tmp_path, lambda lon, lat: lon * 0 + 1.5, np.float32)
    with pytest.raises(LayerError, match=r"r\.tif.*integer codes"):
        read_raster(spec(p, kind="raster"), GRID, categorical=True)


def test_band_out_of_range(tmp_path: Path) -> None:
    p = _lonlat_raster(tmp_path, lambda lon, lat: lon * 0 + 1.0, np.float32)
    with pytest.raises(LayerError, match=r"r\.tif.*band 3 requested, the raster has 1"):
        read_dem(spec(p, kind="raster", band=3), GRID)
