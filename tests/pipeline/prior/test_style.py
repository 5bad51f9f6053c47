"""QGIS raster styles: the QML parses, with the renderer, ramp and palette QGIS reads."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline.prior.style import (
    PALETTE,
    VIRIDIS,
    paletted_qml,
    prior_qml,
    pseudocolor_qml,
    style_path,
)


def _renderer(qml: str) -> ET.Element:
    assert qml.startswith("<!DOCTYPE qgis ")
    root = ET.fromstring(qml.split("\n", 1)[1])
    assert root.tag == "qgis" and root.get("version", "").startswith("3.")
    return root.find("pipe/rasterrenderer")


@given(st.floats(-1e6, 1e6), st.floats(1e-9, 1e6))
def test_ramp_items_span_the_range_in_viridis_order(vmin, span):
    r = _renderer(pseudocolor_qml(vmin, vmin + span, "m"))
    assert r.get("type") == "singlebandpseudocolor" and r.get("band") == "1"
    shader = r.find("rastershader/colorrampshader")
    assert shader.get("colorRampType") == "INTERPOLATED"
    items = shader.findall("item")
    assert [i.get("color") for i in items] == list(VIRIDIS)
    values = [float(i.get("value")) for i in items]
    assert values[0] == vmin and values[-1] == pytest.approx(vmin + span) and np.all(np.diff(values) > 0)
    assert float(shader.get("minimumValue")) == vmin and float(shader.get("maximumValue")) == vmin + span
    assert r.find("rasterTransparency/singleValuePixelList") is None  # zeros drawn unless asked


def test_constant_and_non_finite_ranges():
    r = _renderer(pseudocolor_qml(5.0, 5.0))
    assert float(r.get("classificationMax")) > float(r.get("classificationMin")) == 5.0
    with pytest.raises(ValueError, match="finite range"):
        pseudocolor_qml(0.0, float("nan"))


@given(st.dictionaries(st.integers(-32767, 32767), st.text(min_size=1, max_size=20).filter(str.isprintable), max_size=12))
def test_palette_has_one_entry_per_code_with_its_label(labels):
    r = _renderer(paletted_qml(labels))
    assert r.get("type") == "paletted"
    entries = r.findall("colorPalette/paletteEntry")
    assert [(int(e.get("value")), e.get("label")) for e in entries] == sorted(labels.items())
    assert [e.get("color") for e in entries] == [PALETTE[i % len(PALETTE)] for i in range(len(labels))]


def test_prior_style_zeros_transparent_and_top_quantile():
    density = np.concatenate([np.zeros(50), np.linspace(1e-6, 1e-4, 101)])
    r = _renderer(prior_qml(density))
    entry = r.find("rasterTransparency/singleValuePixelList/pixelListEntry")
    assert (float(entry.get("min")), float(entry.get("max")), entry.get("percentTransparent")) == (0.0, 0.0, "100")
    # 98 % of the positive cells lie at or below the ramp's top (the zeros do not pull it down)
    assert float(r.get("classificationMax")) == pytest.approx(1e-6 + 0.98 * (1e-4 - 1e-6))
    assert float(_renderer(prior_qml(np.zeros(4))).get("classificationMax")) > 0  # an all-zero prior still styles


def test_style_path_is_the_sidecar_qgis_reads():
    assert style_path("out/prior.tif").as_posix() == "out/prior.qml"
