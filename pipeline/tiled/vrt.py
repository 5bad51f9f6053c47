"""GDAL / OGR VRTs that let a tile read only its part of an input layer: a raster window (with
its own transform) and a vector layer behind a spatial filter. Written as XML with ElementTree.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from pathlib import Path

import pyogrio
import pyogrio.errors
import rasterio
import rasterio.errors
from rasterio.crs import CRS
from rasterio.windows import Window

from pipeline.gis.grid import Grid
from pipeline.gis.layers import LayerSpec, covering_window

_GDAL_TYPES = {
    "uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16", "uint32": "UInt32",
    "int32": "Int32", "uint64": "UInt64", "int64": "Int64", "float32": "Float32", "float64": "Float64",
}


def _element(parent: ET.Element, tag: str, text: str | None = None, **attrib: str) -> ET.Element:
    e = ET.SubElement(parent, tag, attrib)
    e.text = text
    return e


def windowed_raster_layer(spec: LayerSpec, grid: Grid, folder: Path) -> LayerSpec:
    """A VRT in ``folder`` of the part of a raster layer that covers ``grid`` (plus the resampling
    kernel's reach, :func:`pipeline.gis.layers.covering_window`), so
    :func:`pipeline.gis.layers.read_raster` reads that part only, with its own transform and no data."""

    try:
        src = rasterio.open(spec.path)
    except rasterio.errors.RasterioIOError:
        return spec  # read_raster reports the missing or unreadable file, naming the layer
    with src:
        if src.crs is None or not 1 <= spec.band <= src.count:
            return spec  # likewise: read_raster's own messages
        win = covering_window(src, grid)
        if win is None:  # off the raster: read_raster then reports no data as it would
            return spec
        c0, r0, c1, r1 = win.col_off, win.row_off, win.col_off + win.width, win.row_off + win.height
        t = src.window_transform(Window(c0, r0, c1 - c0, r1 - r0))
        dtype = src.dtypes[spec.band - 1]
        nodata = src.nodata
        crs_wkt = src.crs.to_wkt()
    size = {"xSize": str(c1 - c0), "ySize": str(r1 - r0)}
    root = ET.Element("VRTDataset", rasterXSize=size["xSize"], rasterYSize=size["ySize"])
    _element(root, "SRS", crs_wkt)
    _element(root, "GeoTransform", ", ".join(repr(v) for v in (t.c, t.a, t.b, t.f, t.d, t.e)))
    band = _element(root, "VRTRasterBand", dataType=_GDAL_TYPES[dtype], band="1")
    if nodata is not None:
        _element(band, "NoDataValue", repr(nodata))
    source = _element(band, "SimpleSource")
    _element(source, "SourceFilename", str(spec.path.resolve()), relativeToVRT="0")
    _element(source, "SourceBand", str(spec.band))
    _element(source, "SrcRect", xOff=str(c0), yOff=str(r0), **size)
    _element(source, "DstRect", xOff="0", yOff="0", **size)
    path = folder / f"{spec.name}.vrt"
    ET.ElementTree(root).write(path, encoding="utf-8")
    return dataclasses.replace(spec, path=path, band=1)


def filtered_vector_layer(spec: LayerSpec, bounds: tuple[float, float, float, float], crs: CRS, folder: Path) -> LayerSpec:
    """An OGR VRT in ``folder`` of a vector layer that yields only the features touching ``bounds``
    (``crs``, metres), in source order, so a tile reads and burns its own roads instead of the whole
    layer. Layers in another CRS (or with a restored index) are returned as they are: their box would
    need reprojecting, and read_vector's own checks apply to the original file."""
    if spec.restore_index or spec.path.suffix.lower() == ".vrt":
        return spec
    try:
        info = pyogrio.read_info(spec.path, layer=spec.layer)
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError):
        return spec  # read_vector reports the missing or unreadable file or layer, naming it
    if info["crs"] is None or not CRS.from_user_input(info["crs"]) == crs:
        return spec
    layer = spec.layer if spec.layer is not None else str(pyogrio.list_layers(spec.path)[0, 0])
    x0, y0, x1, y1 = bounds
    ring = ",".join(f"{x!r} {y!r}" for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)))
    root = ET.Element("OGRVRTDataSource")
    vlayer = _element(root, "OGRVRTLayer", name=layer)
    _element(vlayer, "SrcDataSource", str(spec.path.resolve()), relativeToVRT="0")
    _element(vlayer, "SrcLayer", layer)
    _element(vlayer, "SrcRegion", f"POLYGON(({ring}))", clip="false")
    path = folder / f"{spec.name}.vrt"
    ET.ElementTree(root).write(path, encoding="utf-8")
    return dataclasses.replace(spec, path=path, layer=layer)
