"""The one prior writer: tables byte-identical to np.save, strips of any height, a COG with its style beside it."""

import json

import numpy as np
import pytest
import rasterio

from pipeline.gis.grid import Grid
from pipeline.prior.terrain import TerrainPrior
from pipeline.prior.write import UNITS, geotiff_profile, prior_tags, sat_paths, write_prior


def _prior(h: int = 300, w: int = 70) -> TerrainPrior:
    grid = Grid.from_bounds((0.0, 0.0, w * 10.0, h * 10.0), 10.0, "EPSG:32734")
    r = np.random.default_rng(1).random((h, w))
    return TerrainPrior.from_array(r, grid, {"test": [1, 2]})


def test_tables_are_the_bytes_np_save_writes(tmp_path):
    prior = _prior()
    path = prior.write(tmp_path / "prior.tif")
    for table, written in zip((prior.sat, prior.sat2), sat_paths(path), strict=True):
        np.save(tmp_path / "ref.npy", table)
        assert written.read_bytes() == (tmp_path / "ref.npy").read_bytes()
    with rasterio.open(path) as src:
        np.testing.assert_array_equal(src.read(1), prior.density.astype(np.float32))
        assert src.tags()["UNITS"] == UNITS
        assert json.loads(src.tags()["MODEL"]) == {"test": [1, 2]}
        assert src.profile["compress"] == "deflate" and src.profile["blockxsize"] == 256


@pytest.mark.parametrize("direct", ["yes", "refused at open", "refused at write"])
@pytest.mark.parametrize("shape", [(1, 1), (3, 511), (40, 205), (64, 64)])
def test_table_file_writes_what_np_save_writes(tmp_path, monkeypatch, direct, shape):
    """TableFile's bytes and digest, written in uneven pieces across direct-I/O chunks (shrunk to 8 KiB)
    or through the page cache (O_DIRECT refused by the open, or by the first write), are np.save's file
    and the SHA-1 of its data."""
    import hashlib
    import os

    import pipeline.prior.write as write

    monkeypatch.setattr(write, "DIRECT_CHUNK", 8192)
    if direct == "refused at open":
        real_open = os.open
        def no_direct(path, flags, *args):
            if flags & getattr(os, "O_DIRECT", 0):
                raise OSError(22, "Invalid argument")
            return real_open(path, flags, *args)
        monkeypatch.setattr(os, "open", no_direct)
    elif direct == "refused at write":
        def no_pwrite(fd, data, offset):
            raise OSError(22, "Invalid argument")
        monkeypatch.setattr(os, "pwrite", no_pwrite)
    table = np.random.default_rng(shape[1]).random(shape)
    out = write.TableFile(tmp_path / "t.npy", write._npy_header(shape))
    assert out.direct == (direct == "yes" and hasattr(os, "O_DIRECT"))
    for r0 in range(0, shape[0], 3):
        out.write(table[r0 : r0 + 3])
    out.close()
    np.save(tmp_path / "ref.npy", table)
    data = (tmp_path / "ref.npy").read_bytes()
    assert (tmp_path / "t.npy").read_bytes() == data
    assert out.digest.hexdigest() == hashlib.sha1(table.tobytes()).hexdigest()


@pytest.mark.parametrize("rows", [1, 7, 300])
def test_cog_from_uneven_strips_reads_back_equal(tmp_path, rows):
    prior = _prior()
    strips = ((prior.density[r : r + rows], prior.sat[r + 1 : r + 1 + rows], prior.sat2[r + 1 : r + 1 + rows])
              for r in range(0, prior.grid.height, rows))
    path = write_prior(tmp_path / "prior.tif", prior.grid, prior.model, strips)
    back = TerrainPrior.read(path)
    np.testing.assert_array_equal(back.density, prior.density.astype(np.float32))
    np.testing.assert_array_equal(back.sat, prior.sat)
    np.testing.assert_array_equal(back.sat2, prior.sat2)
    assert back.model == prior.model
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prior.qml", "prior.sat.npy", "prior.sat2.npy", "prior.tif"]


def test_missing_rows_fail_and_write_nothing(tmp_path):
    prior = _prior()
    with pytest.raises(ValueError, match="strips cover 256 rows of a 300-row grid"):
        write_prior(tmp_path / "prior.tif", prior.grid, prior.model, [(prior.density[:256], prior.sat[1:257], prior.sat2[1:257])])
    assert list(tmp_path.iterdir()) == []


def test_profile_and_tags():
    grid = Grid.from_bounds((0.0, 0.0, 100.0, 50.0), 10.0, "EPSG:32734")
    p = geotiff_profile(grid, "int16", nodata=-1)
    assert (p["height"], p["width"], p["dtype"], p["nodata"], p["compress"]) == (5, 10, "int16", -1, "deflate")
    assert "compress" not in geotiff_profile(grid, "float32", None)
    assert prior_tags({"a": 1}) == {"MODEL": '{"a": 1}', "UNITS": UNITS}
