"""Coordinate reference systems: rasterio's CRS (grids, rasters) as pyproj's (vectors, transforms)."""

from __future__ import annotations

from typing import Any

from pyproj import CRS as ProjCRS
from pyproj import Transformer
from rasterio.crs import CRS


def to_pyproj(crs: CRS | ProjCRS | str | Any) -> ProjCRS:
    """A pyproj CRS of a rasterio CRS (through its WKT, which both read the same way) or of any
    input pyproj accepts ("EPSG:4326", WKT, a pyproj CRS)."""
    return ProjCRS.from_user_input(crs.to_wkt() if isinstance(crs, CRS) else crs)


def transformer(src: CRS | ProjCRS | str, dst: CRS | ProjCRS | str) -> Transformer:
    """Transformer from ``src`` to ``dst`` taking and giving (x, y) = (easting or lon, northing or lat)."""
    return Transformer.from_crs(to_pyproj(src), to_pyproj(dst), always_xy=True)
