"""TerrainPrior.read accepts only a prior set of one build: every damaged, foreign or mixed file is a
PriorError naming the file and how to rebuild, through the API and both command-line tools."""

from __future__ import annotations

import pickle
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from pipeline.cli import main as prior_main
from pipeline.gis.grid import Grid
from pipeline.prior.terrain import DENSITY_TOL, PriorError, TerrainPrior
from pipeline.prior.write import BUILD_TAG, TABLE_TAGS, sat_paths, table_hash
from tracker.cli import main as track_main

REBUILD = "rebuild it with `terrain-prior build"


def _grid() -> Grid:
    return Grid("EPSG:32734", Affine(20.0, 0.0, 300_000.0, 0.0, -20.0, 6_200_000.0), 12, 9)


def _prior(seed: int = 0) -> TerrainPrior:
    r = np.random.default_rng(seed).random((12, 9)) + 0.1
    return TerrainPrior.from_array(r, _grid(), {"provenance": {"config": "/data/region.toml"}, "seed": seed})


@pytest.fixture
def prior_path(tmp_path: Path) -> Path:
    return _prior().write(tmp_path / "prior.tif")


def _retag(path: Path, **tags: str) -> None:
    with rasterio.open(path, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:  # tampering with a COG on purpose
        dst.update_tags(**tags)


def _rewrite_density(path: Path, change: Callable[[np.ndarray], np.ndarray]) -> None:
    """Replace the density of a prior GeoTIFF, keeping all its tags."""
    with rasterio.open(path, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:  # tampering with a COG on purpose
        dst.write(change(dst.read(1)).astype(np.float32), 1)


def _rehash(path: Path) -> None:
    """Record the tables' current checksums in the GeoTIFF, as if its build had written them."""
    digests = []
    for p in sat_paths(path):
        h = table_hash()
        h.update(np.load(p))
        digests.append(h.hexdigest())
    _retag(path, **dict(zip(TABLE_TAGS, digests, strict=True)))


def test_round_trip_reads_the_build(prior_path: Path) -> None:
    back = TerrainPrior.read(prior_path)
    ref = _prior()
    np.testing.assert_array_equal(back.sat, ref.sat)
    with rasterio.open(prior_path) as src:
        tags = src.tags()
    assert len(tags[BUILD_TAG]) == 32 and int(tags[BUILD_TAG], 16) >= 0
    for p, t, table in zip(sat_paths(prior_path), TABLE_TAGS, (ref.sat, ref.sat2), strict=True):
        h = table_hash()
        h.update(np.ascontiguousarray(table))
        assert tags[t] == h.hexdigest()
        assert isinstance(np.load(p, mmap_mode="r"), np.ndarray)


def test_each_build_has_its_own_id(tmp_path: Path) -> None:
    a, b = (_prior().write(tmp_path / n / "prior.tif") for n in "ab")
    with rasterio.open(a) as sa, rasterio.open(b) as sb:
        assert sa.tags()[BUILD_TAG] != sb.tags()[BUILD_TAG]


@pytest.mark.parametrize("windowed", [False, True])
@pytest.mark.parametrize("swapped", ["prior.tif", "prior.sat.npy", "prior.sat2.npy"])
def test_mixed_set_is_refused(tmp_path: Path, swapped: str, windowed: bool) -> None:
    """The reported case (a new .sat.npy beside the old .tif and .sat2.npy) and its siblings: any one
    file of another build beside the other two."""
    old = _prior(0).write(tmp_path / "old" / "prior.tif")
    new = _prior(1).write(tmp_path / "new" / "prior.tif")
    shutil.copy(new.parent / swapped, old.parent / swapped)
    with pytest.raises(PriorError, match=r"prior\.sat2?\.npy: not the table of the build prior\.tif records.*mixed from two builds") as err:
        TerrainPrior.read(old, windowed=windowed)
    assert f"rebuild it with `terrain-prior build /data/region.toml --out {old}`" in str(err.value)


def test_rebuild_with_equal_tables_is_one_build(tmp_path: Path) -> None:
    """The binding is by content: the tables of an identical rebuild match either GeoTIFF."""
    a = _prior(0).write(tmp_path / "a" / "prior.tif")
    b = _prior(0).write(tmp_path / "b" / "prior.tif")
    shutil.copy(b, a)
    np.testing.assert_array_equal(TerrainPrior.read(a).sat, _prior(0).sat)


def test_plain_geotiff_with_tables_beside_it_is_not_a_prior(tmp_path: Path, prior_path: Path) -> None:
    """A DEM with summed-area tables copied beside it."""
    dem = tmp_path / "dem" / "prior.tif"
    dem.parent.mkdir()
    g = _grid()
    profile = {"driver": "GTiff", "height": g.height, "width": g.width, "count": 1, "dtype": "float32",
               "crs": g.crs, "transform": g.transform}
    with rasterio.open(dem, "w", **profile) as dst:
        dst.write(np.full(g.shape, 412.0, dtype=np.float32), 1)
    for src, dst in zip(sat_paths(prior_path), sat_paths(dem), strict=True):
        shutil.copy(src, dst)
    with pytest.raises(PriorError, match=r"dem/prior\.tif: not a prior written by terrain-prior build \(no MODEL, PRIOR_BUILD"):
        TerrainPrior.read(dem)


@pytest.mark.parametrize(
    ("tag", "value", "match"),
    [
        ("MODEL", "{not json", "MODEL tag is not valid JSON"),
        ("MODEL", "[1, 2]", "MODEL tag is a JSON list, not an object"),
        ("UNITS", "m", "UNITS tag 'm'"),
    ],
)
def test_bad_tags(prior_path: Path, tag: str, value: str, match: str) -> None:
    _retag(prior_path, **{tag: value})
    with pytest.raises(PriorError, match=match) as err:
        TerrainPrior.read(prior_path)
    assert str(prior_path) in str(err.value) and REBUILD in str(err.value)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda d: d * 2.0, "density integrates to 2, not 1"),
        (lambda d: d * (1 + 3 * DENSITY_TOL), r"density integrates to 1\.0000[0-9]+, not 1"),
        (lambda d: np.where(np.arange(d.size).reshape(d.shape) == 10, -d, d), "finite and >= 0; 1 bad cells, first at row 1, col 1"),
        (lambda d: np.where(np.arange(d.size).reshape(d.shape) == 20, np.nan, d), "finite and >= 0; 1 bad cells, first at row 2, col 2"),
    ],
)
@pytest.mark.parametrize("windowed", [False, True])
def test_bad_density(prior_path: Path, change, match: str, windowed: bool) -> None:
    _rewrite_density(prior_path, change)
    with pytest.raises(PriorError, match=match) as err:
        TerrainPrior.read(prior_path, windowed=windowed)
    assert f"{prior_path}: density" in str(err.value) and "build /data/region.toml --out" in str(err.value)


def test_constructor_refuses_float32_tables() -> None:
    p = _prior()
    with pytest.raises(PriorError, match="summed-area tables must be float64, got float32, float64"):
        TerrainPrior(p.grid, p.density, p.sat.astype(np.float32), p.sat2)


def test_density_within_tolerance_is_accepted(prior_path: Path) -> None:
    _rewrite_density(prior_path, lambda d: d * (1 + DENSITY_TOL / 4))
    TerrainPrior.read(prior_path)  # float32 rounding of a real build is far below the tolerance


def _npy_header(shape: tuple[int, int], dtype: str = "<f8") -> bytes:
    body = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
    pad = 64 - (10 + len(body) + 1) % 64
    return b"\x93NUMPY\x01\x00" + (len(body) + pad + 1).to_bytes(2, "little") + body + b" " * pad + b"\n"


def _damage(kind: str, table: Path) -> None:
    good = table.read_bytes()
    shape = np.load(table).shape
    if kind == "zero-byte":
        table.write_bytes(b"")
    elif kind == "truncated":
        table.write_bytes(good[: len(good) - 100])
    elif kind == "header-only":
        table.write_bytes(_npy_header(shape))
    elif kind == "garbage":
        table.write_bytes(np.random.default_rng(0).bytes(len(good)))
    elif kind == "pickled":
        np.save(table, np.array([{"__reduce__": "os.system"}] * 3, dtype=object), allow_pickle=True)
    elif kind == "raw pickle":
        table.write_bytes(pickle.dumps(np.load(table)))
    elif kind == "float32":
        np.save(table, np.load(table).astype(np.float32))
    elif kind == "fortran":
        np.save(table, np.asfortranarray(np.load(table)))
    elif kind == "shape":
        np.save(table, np.load(table)[:-1])
    elif kind == "longer":
        table.write_bytes(good + b"\0" * 8)
    elif kind == "directory":
        table.unlink()
        table.mkdir()


DAMAGE = {
    "zero-byte": r"empty \(0 bytes\), not a summed-area table",
    "truncated": r"truncated: \d+ bytes, expected \d+",
    "header-only": r"truncated: 128 bytes, expected \d+",
    "garbage": r"not a \.npy summed-area table \(the magic string is not correct",
    "pickled": r"holds pickled Python objects, not a float64 table \(never unpickled\)",
    "raw pickle": r"not a \.npy summed-area table",
    "float32": r"table is <f4, must be C-order float64",
    "fortran": r"table is <f8 Fortran-order, must be C-order float64",
    "shape": r"table shape \(12, 10\) does not match the prior's grid: expected \(13, 10\)",
    "longer": r"longer than its header says",
    "directory": r"cannot read summed-area table",
}


@pytest.mark.parametrize("which", [0, 1])
@pytest.mark.parametrize("kind", sorted(DAMAGE))
def test_damaged_tables_are_named(prior_path: Path, kind: str, which: int) -> None:
    table = sat_paths(prior_path)[which]
    _damage(kind, table)
    with pytest.raises(PriorError, match=DAMAGE[kind]) as err:
        TerrainPrior.read(prior_path)
    assert str(err.value).startswith(f"{table}: ") and "build /data/region.toml --out" in str(err.value)


@pytest.mark.parametrize("which", [0, 1])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_table_entry(prior_path: Path, which: int, value: float) -> None:
    table = sat_paths(prior_path)[which]
    t = np.load(table, mmap_mode="r+")
    t[5, 3] = value
    t.flush()
    del t
    with pytest.raises(PriorError, match=rf"{table.name}: NaN or infinite table entry at row 5, col 3"):
        TerrainPrior.read(prior_path)


@pytest.mark.parametrize("windowed", [False, True])
def test_tables_must_total_up_to_the_density(prior_path: Path, windowed: bool) -> None:
    """Tables whose checksum the GeoTIFF records, but which are not this density's tables."""
    sat = sat_paths(prior_path)[0]
    t = np.load(sat)
    t[1:, 1:] += 1e-4  # still finite and zero-padded
    np.save(sat, t)
    _rehash(prior_path)
    with pytest.raises(PriorError, match=r"prior\.sat\.npy: table totals differ from the density's by 0\.0001"):
        TerrainPrior.read(prior_path, windowed=windowed)
    np.save(sat, np.pad(t[1:, 1:], ((1, 0), (1, 0)))[:, ::-1].copy())  # not zero-padded
    _rehash(prior_path)
    with pytest.raises(PriorError, match="first row and column of a padded summed-area table must be zero"):
        TerrainPrior.read(prior_path, windowed=windowed)


@pytest.mark.parametrize("windowed", [False, True])
def test_sat2_must_total_up_to_the_squared_density(prior_path: Path, windowed: bool) -> None:
    sat, sat2 = sat_paths(prior_path)
    shutil.copy(sat, sat2)  # r's table where r^2's belongs
    _rehash(prior_path)
    with pytest.raises(PriorError, match=r"prior\.sat2\.npy: table totals differ"):
        TerrainPrior.read(prior_path, windowed=windowed)


def _bad_priors(tmp_path: Path) -> dict[str, Path]:
    """One broken prior per class of damage, each in its own folder."""
    out = {}
    for kind in ("zero-byte", "pickled", "garbage", "mixed", "plain", "model", "negative"):
        path = _prior().write(tmp_path / kind / "prior.tif")
        if kind in DAMAGE:
            _damage(kind, sat_paths(path)[0])
        elif kind == "mixed":
            shutil.copy(sat_paths(_prior(1).write(tmp_path / "other" / "prior.tif"))[0], sat_paths(path)[0])
        elif kind == "plain":
            with rasterio.open(path, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as dst:  # tampering with a COG on purpose
                dst.update_tags(MODEL="{}")
            with rasterio.open(path) as src:
                data, profile = src.read(1), src.profile
            with rasterio.open(path, "w", **profile) as dst:  # same pixels, no prior tags
                dst.write(data, 1)
        elif kind == "model":
            _retag(path, MODEL="garbage")
        elif kind == "negative":
            _rewrite_density(path, lambda d: -d)
        out[kind] = path
    return out


def test_cli_errors_name_the_file(tmp_path: Path, capsys) -> None:
    """`terrain-prior show BAD` and `terrain-track run --prior BAD` print one error line, no traceback."""
    reports = tmp_path / "reports.csv"
    reports.write_text("x,y,time,cov_xx,cov_xy,cov_yy\n300050,6199950,0,100,0,100\n")
    for kind, bad in _bad_priors(tmp_path).items():
        for tool, argv in (
            ("terrain-prior", lambda p: prior_main(["-q", "show", str(p), "--png", str(tmp_path / "p.png")])),
            ("terrain-track", lambda p: track_main(["run", "--prior", str(p), "--reports", str(reports), "--out", str(tmp_path / "t.gpkg")])),
        ):
            assert argv(bad) == 1, (tool, kind)
            out, err = capsys.readouterr()
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith(f"{tool}: error: {bad.parent}"), (tool, kind, err)
            assert "Traceback" not in err and "terrain-prior build" in err, (tool, kind, err)
    assert not (tmp_path / "p.png").exists() and not (tmp_path / "t.gpkg").exists()
