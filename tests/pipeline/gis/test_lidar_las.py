"""LAS/LAZ input: class and return filters, CRS from WKT / GeoTIFF keys / compound CRS / the config,
units to metres, reprojection to the grid, and the named errors. Clouds are sampled from a known
plane in UTM metres and written in other CRSs and units, so the oracle is the plane itself."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import CRS, Transformer

from pipeline import cli
from pipeline.config.region import ConfigError, load_config
from pipeline.gis.grid import Grid
from pipeline.gis.lidar import LidarError, PointFilter, _parts, lidar_surface, read_point_cloud

laspy = pytest.importorskip("laspy")
pytest.importorskip("open3d")

UTM = "EPSG:32610"
GRID = Grid.from_bounds((494100.0, 4877400.0, 494180.0, 4877460.0), 2.0, UTM)  # 30 x 40 cells
SLOPE = np.degrees(np.arctan(np.hypot(0.1, 0.05)))


def plane(x, y):
    return 130.0 + 0.1 * (x - 494100.0) - 0.05 * (y - 4877400.0)


def cloud(n: int = 30000, seed: int = 0) -> dict[str, np.ndarray]:
    """Ground (class 2) on the plane, vegetation (class 1) 8 m above it as first of two returns."""
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = GRID.bounds
    x, y = rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)
    veg = rng.random(n) < 0.4
    z = plane(x, y) + np.where(veg, 8.0, 0.0)
    returns = np.where(veg, 2, rng.integers(1, 3, n))
    return {
        "xyz": np.c_[x, y, z],
        "classification": np.where(veg, 1, 2).astype(np.uint8),
        "return_number": np.where(veg, 1, rng.integers(1, returns + 1)).astype(np.uint8),
        "number_of_returns": returns.astype(np.uint8),
    }


def write_las(path, c: dict, crs: str | None = None, h_unit: float = 1.0, z_unit: float = 1.0,
              geokeys: dict[int, int] | None = None, version: str = "1.2") -> None:
    """Write ``c`` (UTM metres) as LAS/LAZ in ``crs`` (x, y transformed there, z divided by ``z_unit``)."""
    xyz = c["xyz"].copy()
    if crs is not None:
        xyz[:, 0], xyz[:, 1] = Transformer.from_crs(UTM, crs, always_xy=True).transform(xyz[:, 0], xyz[:, 1])
    xyz[:, 2] /= z_unit
    header = laspy.LasHeader(point_format=3 if version == "1.2" else 6, version=version)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    if crs is not None and geokeys is None:
        header.add_crs(CRS(crs))
    if geokeys is not None:
        vlr = laspy.vlrs.known.GeoKeyDirectoryVlr()
        vlr.geo_keys_header.key_directory_version, vlr.geo_keys_header.key_revision = 1, 1
        vlr.geo_keys_header.number_of_keys = len(geokeys)
        vlr.geo_keys = []
        for key, value in geokeys.items():
            entry = laspy.vlrs.geotiff.GeoKeyEntryStruct()
            entry.id, entry.tiff_tag_location, entry.count, entry.value_offset = key, 0, 1, value
            vlr.geo_keys.append(entry)
        header.vlrs.append(vlr)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    for k in ("classification", "return_number", "number_of_returns"):
        setattr(las, k, c[k])
    las.write(str(path))


@pytest.mark.parametrize(
    ("crs", "suffix"),
    [(UTM, ".las"), ("EPSG:2992", ".laz"), ("EPSG:2227", ".laz")],  # metres; international feet; US survey feet
)
def test_ground_plane_in_other_crs_and_units(tmp_path, crs, suffix):
    c = cloud()
    z_unit = _parts(CRS(crs))[1]
    path = tmp_path / f"cloud{suffix}"
    write_las(path, c, crs, z_unit=z_unit)
    s = lidar_surface(path, GRID)
    xc, yc = GRID.cell_centres()
    assert (s.count > 0).all()
    # the vegetation 8 m above is filtered out: the ground plane is reproduced to the mm of the LAS scale
    np.testing.assert_allclose(s.elevation, plane(xc, yc), atol=0.01)
    np.testing.assert_allclose(s.slope, SLOPE, atol=0.05)


def test_unit_factors():
    assert _parts(CRS("EPSG:2992"))[1] == 0.3048
    assert _parts(CRS("EPSG:2227"))[1] == pytest.approx(1200 / 3937, rel=1e-12)
    assert _parts(CRS("EPSG:32610+6360"))[1] == pytest.approx(1200 / 3937, rel=1e-12)  # metres + NAVD88 ftUS
    assert _parts(CRS("EPSG:32610+8228"))[1] == 0.3048
    assert _parts(CRS("EPSG:4326"))[1] == 1.0
    assert _parts(CRS("EPSG:32610+6360"))[0] == CRS(UTM)


def test_compound_crs_vertical_feet_horizontal_metres(tmp_path):
    c = cloud(3000)
    path = tmp_path / "compound.laz"
    write_las(path, c, "EPSG:32610+6360", z_unit=1200 / 3937, version="1.4")  # WKT: LAS 1.4
    got = read_point_cloud(path, UTM)
    want = c["xyz"][c["classification"] == 2]
    np.testing.assert_allclose(got, want, atol=2e-3)


@pytest.mark.parametrize(("code", "factor"), [(9001, 1.0), (9002, 0.3048), (9003, 1200 / 3937)])
def test_geotiff_keys(tmp_path, code, factor):
    """No WKT: the CRS from ProjectedCSTypeGeoKey, z units from VerticalUnitsGeoKey (here apart from x, y's feet)."""
    c = cloud(3000)
    path = tmp_path / "keys.las"
    write_las(path, c, "EPSG:2992", z_unit=factor, geokeys={1024: 1, 3072: 2992, 4099: code})
    got = read_point_cloud(path, UTM)
    np.testing.assert_allclose(got, c["xyz"][c["classification"] == 2], atol=2e-3)


def test_filters_select_exactly(tmp_path):
    c = cloud(5000)
    path = tmp_path / "f.las"
    write_las(path, c, UTM)
    cls, rn, nr, xyz = c["classification"], c["return_number"], c["number_of_returns"], c["xyz"]
    cases = {
        PointFilter(): cls == 2,
        PointFilter(None): np.ones(cls.size, bool),
        PointFilter((1,)): cls == 1,
        PointFilter((2,), "first"): (cls == 2) & (rn == 1),
        PointFilter((2,), "last"): (cls == 2) & (rn == nr),
        PointFilter(None, "single"): nr == 1,
        PointFilter(None, (2,)): rn == 2,
    }
    for keep, mask in cases.items():
        got = read_point_cloud(path, keep=keep)
        np.testing.assert_allclose(got, xyz[mask], atol=6e-4, err_msg=keep.describe())
    write_las(path, cloud(), UTM)  # dense enough that every cell has vegetation points
    vegetation = lidar_surface(path, GRID, keep=PointFilter((1,)))
    np.testing.assert_allclose(vegetation.elevation, plane(*GRID.cell_centres()) + 8.0, atol=0.01)


def test_filter_errors(tmp_path):
    with pytest.raises(LidarError, match="classes"):
        PointFilter((2, 300))
    with pytest.raises(LidarError, match="classes"):
        PointFilter(())
    with pytest.raises(LidarError, match="returns"):
        PointFilter((2,), "middle")
    with pytest.raises(LidarError, match="returns"):
        PointFilter((2,), (0,))
    c = cloud(500)
    c["classification"][:] = 1
    path = tmp_path / "noground.laz"
    write_las(path, c, UTM)
    with pytest.raises(LidarError, match=r"noground.laz: none of its 500 points is of classes \[2\], all returns.*\{1: 500\}"):
        read_point_cloud(path, UTM)


def test_no_crs_needs_one_in_the_config(tmp_path, capsys):
    c = cloud()
    path = tmp_path / "nocrs.laz"
    write_las(path, c)  # x, y in UTM metres, no CRS VLR
    with pytest.raises(LidarError, match="nocrs.laz: the file has no CRS"):
        lidar_surface(path, GRID)
    xmin, ymin, xmax, ymax = GRID.bounds
    toml = f"""
[region]
crs = "{UTM}"
bounds = [{xmin}, {ymin}, {xmax}, {ymax}]
cell_size = 2.0

[layers.lidar]
path = "nocrs.laz"
{{crs}}

[features.elevation]
type = "elevation"
layer = "lidar"
"""
    cfg = tmp_path / "r.toml"
    cfg.write_text(toml.format(crs=""))
    assert cli.main(["-q", "features", str(cfg), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "error: [layers.lidar]:" in err and "nocrs.laz: the file has no CRS" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "elevation.tif").exists()
    cfg.write_text(toml.format(crs=f'crs = "{UTM}"'))
    assert cli.main(["-q", "features", str(cfg), "--out", str(tmp_path / "out")]) == 0
    import rasterio

    with rasterio.open(tmp_path / "out" / "elevation.tif") as src:
        np.testing.assert_allclose(src.read(1), plane(*GRID.cell_centres()), atol=0.01)


@pytest.mark.parametrize(
    ("layer", "match"),
    [
        ('path = "c.ply"\nclasses = [2]', "layers.d.classes: only LAS/LAZ point clouds"),
        ('path = "d.tif"\ncrs = "EPSG:32610"', "layers.d.crs: only point clouds"),
        ('path = "c.laz"\nclasses = [2, 999]', "layers.d.classes: classes must be"),
        ('path = "c.laz"\nclasses = "ground"', "layers.d.classes: classes must be"),
        ('path = "c.laz"\nreturns = "middle"', "layers.d.returns: returns must be"),
        ('path = "c.laz"\ncrs = "EPSG:nope"', "layers.d.crs: not a CRS"),
    ],
)
def test_config_errors(tmp_path, layer, match):
    cfg = tmp_path / "r.toml"
    cfg.write_text(
        f'[region]\ncrs = "{UTM}"\nbounds = [0, 0, 100, 100]\n\n[layers.d]\n{layer}\n\n'
        '[features.z]\ntype = "elevation"\nlayer = "d"\n'
    )
    with pytest.raises(ConfigError, match=match):
        load_config(cfg)


def test_config_filter_reaches_the_reader(tmp_path):
    cfg = tmp_path / "r.toml"
    cfg.write_text(
        f'[region]\ncrs = "{UTM}"\nbounds = [0, 0, 100, 100]\n\n[layers.d]\npath = "c.laz"\nclasses = "all"\nreturns = [1]\n\n'
        '[features.z]\ntype = "elevation"\nlayer = "d"\n'
    )
    assert load_config(cfg).layers["d"].points == PointFilter(None, (1,))


def test_corrupt_laz(tmp_path):
    path = tmp_path / "bad.laz"
    path.write_bytes(b"LASF" + b"\x00" * 50)
    with pytest.raises(LidarError, match="bad.laz: not a readable LAS/LAZ file"):
        read_point_cloud(path)
