"""QGIS layer styles (QML) for the project's GeoTIFFs: a pseudocolour ramp for continuous rasters
(the prior density, distances, slopes) and a palette with labels for categorical ones.

QGIS loads ``name.qml`` beside ``name.tif`` as the layer's default style when the raster is added.
The tracker's vector styles reuse :func:`qml_document`.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path

import numpy as np

QGIS_VERSION = "3.28.0-Firenze"
"""The QGIS release whose QML layout these styles follow (read by every QGIS 3.x)."""
VIRIDIS = ("#440154", "#3b528b", "#21918c", "#5ec962", "#fde725")
"""Stops of the continuous ramp, low to high (matplotlib's viridis at 0, 1/4, ..., 1)."""
PALETTE = ("#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666")
"""Category colours in code order (ColorBrewer Dark2), cycled past eight categories."""
RAMP_QUANTILE = 0.98
"""The ramp of the prior ends at this quantile of its positive densities, as QGIS's cumulative cut."""


def style_path(path: str | Path) -> Path:
    """The QML sidecar QGIS reads beside a raster: ``prior.tif`` -> ``prior.qml``."""
    return Path(path).with_suffix(".qml")


def qml_document(root: ET.Element) -> str:
    """A QML file's text: the QGIS doctype and ``root`` (a ``<qgis>`` element)."""
    ET.indent(root)
    return "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + ET.tostring(root, encoding="unicode") + "\n"


def _rgba(hex_colour: str, alpha: int = 255) -> str:
    """QGIS's ``r,g,b,a`` colour string of ``#rrggbb``."""
    r, g, b = (int(hex_colour[i : i + 2], 16) for i in (1, 3, 5))
    return f"{r},{g},{b},{alpha}"


def _raster_qml(renderer: ET.Element) -> str:
    """A raster QML with ``renderer`` as its pipe's renderer (nearest-neighbour, no colour filters)."""
    root = ET.Element("qgis", version=QGIS_VERSION, styleCategories="AllStyleCategories")
    pipe = ET.SubElement(root, "pipe")
    provider = ET.SubElement(pipe, "provider")
    ET.SubElement(provider, "resampling", enabled="false", maxOversampling="2",
                  zoomedInResamplingMethod="nearestNeighbour", zoomedOutResamplingMethod="nearestNeighbour")
    pipe.append(renderer)
    ET.SubElement(pipe, "brightnesscontrast", brightness="0", contrast="0", gamma="1")
    ET.SubElement(pipe, "huesaturation", saturation="0", grayscaleMode="0", colorizeOn="0",
                  colorizeRed="255", colorizeGreen="128", colorizeBlue="128", colorizeStrength="100")
    ET.SubElement(pipe, "rasterresampler", maxOversampling="2")
    ET.SubElement(root, "blendMode").text = "0"
    return qml_document(root)


def _renderer(kind: str, **attrs: str) -> ET.Element:
    """A band-1 ``<rasterrenderer>`` of ``kind``."""
    return ET.Element("rasterrenderer", type=kind, band="1", opacity="1", alphaBand="-1", nodataColor="", **attrs)


def _min_max_origin(parent: ET.Element) -> None:
    """Fixed limits: QGIS keeps the style's range instead of restretching to its own statistics."""
    origin = ET.SubElement(parent, "minMaxOrigin")
    for tag, text in (("limits", "None"), ("extent", "WholeRaster"), ("statAccuracy", "Estimated"),
                      ("cumulativeCutLower", "0.02"), ("cumulativeCutUpper", "0.98"), ("stdDevFactor", "2")):
        ET.SubElement(origin, tag).text = text


def pseudocolor_qml(vmin: float, vmax: float, label: str = "", zero_transparent: bool = False) -> str:
    """QML of a single-band pseudocolour renderer: viridis interpolated from ``vmin`` to ``vmax`` (the
    raster's units, labelled ``label``); ``zero_transparent``: cells equal to 0 are not drawn."""
    if not (math.isfinite(vmin) and math.isfinite(vmax)):
        raise ValueError(f"a colour ramp needs a finite range, got [{vmin}, {vmax}]")
    if vmax <= vmin:  # a constant raster: any non-empty range draws it in the low colour
        vmax = vmin + (abs(vmin) or 1.0)
    renderer = _renderer("singlebandpseudocolor", classificationMin=repr(vmin), classificationMax=repr(vmax))
    transparency = ET.SubElement(renderer, "rasterTransparency")
    if zero_transparent:
        pixels = ET.SubElement(transparency, "singleValuePixelList")
        ET.SubElement(pixels, "pixelListEntry", min="0", max="0", percentTransparent="100")
    _min_max_origin(renderer)
    shader = ET.SubElement(ET.SubElement(renderer, "rastershader"), "colorrampshader", colorRampType="INTERPOLATED",
                           classificationMode="1", clip="0", minimumValue=repr(vmin), maximumValue=repr(vmax),
                           labelPrecision="4")
    ramp = ET.SubElement(shader, "colorramp", type="gradient", name="[source]")
    options = ET.SubElement(ramp, "Option", type="Map")
    inner = ";".join(f"{i / (len(VIRIDIS) - 1):g};{_rgba(c)}" for i, c in enumerate(VIRIDIS[1:-1], start=1))
    for name, value in (("color1", _rgba(VIRIDIS[0])), ("color2", _rgba(VIRIDIS[-1])), ("discrete", "0"),
                        ("rampType", "gradient"), ("stops", inner)):
        ET.SubElement(options, "Option", type="QString", name=name, value=value)
    for i, colour in enumerate(VIRIDIS):
        value = vmin + (vmax - vmin) * i / (len(VIRIDIS) - 1)
        ET.SubElement(shader, "item", value=repr(value), color=colour, alpha="255",
                      label=f"{value:.4g} {label}".rstrip())
    return _raster_qml(renderer)


def paletted_qml(labels: Mapping[int, str]) -> str:
    """QML of a paletted renderer: one colour and legend entry per category code (``labels``: code -> name)."""
    renderer = _renderer("paletted")
    ET.SubElement(renderer, "rasterTransparency")
    _min_max_origin(renderer)
    palette = ET.SubElement(renderer, "colorPalette")
    for i, code in enumerate(sorted(labels)):
        ET.SubElement(palette, "paletteEntry", value=str(int(code)), color=PALETTE[i % len(PALETTE)], alpha="255",
                      label=str(labels[code]))
    ET.SubElement(renderer, "colorramp", type="randomcolors", name="[source]")
    return _raster_qml(renderer)


def prior_qml(density: np.ndarray) -> str:
    """QML of a prior density (per m²): the ramp from 0 to the RAMP_QUANTILE of its positive cells,
    zeros (structural zeros, no-go terrain) transparent."""
    positive = density[density > 0]
    top = float(np.quantile(positive, RAMP_QUANTILE)) if positive.size else 1.0
    return pseudocolor_qml(0.0, top, "per m²", zero_transparent=True)
