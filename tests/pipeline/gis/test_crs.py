"""The one CRS helper: rasterio CRS -> pyproj CRS and transformers in (x, y) order."""

import numpy as np
from pyproj import CRS as ProjCRS
from rasterio.crs import CRS

from pipeline.gis.crs import to_pyproj, transformer


def test_to_pyproj_accepts_rasterio_pyproj_and_strings():
    utm = ProjCRS.from_epsg(32734)
    assert to_pyproj(CRS.from_epsg(32734)).equals(utm)
    assert to_pyproj("EPSG:32734").equals(utm)
    assert to_pyproj(utm) == utm


def test_transformer_is_xy_ordered_and_mixes_crs_kinds():
    tr = transformer("EPSG:4326", CRS.from_epsg(32734))
    x, y = tr.transform(21.0, -34.0)  # lon, lat on zone 34's central meridian
    assert np.isclose(x, 500000.0)
    assert 6.2e6 < y < 6.3e6
    back = transformer(CRS.from_epsg(32734), "EPSG:4326").transform(x, y)
    assert np.allclose(back, (21.0, -34.0))
