"""One self-contained interactive map (Leaflet through folium) that both the pipeline and the tracker draw on.

Inputs are plain arrays and shapely geometries in a projected CRS (metres); the map reprojects them for
Leaflet (rasters to EPSG:3857, vectors to EPSG:4326). Leaflet's JavaScript and CSS (``common/assets``,
Leaflet 1.9.4, BSD-2-Clause) are inlined, and no tile server is used unless a basemap URL is given, so
the file opens with no network.
"""

from __future__ import annotations

import base64
import html
import json
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import branca.colormap
import folium
import numpy as np
import pyogrio
import pyogrio.errors
import pyogrio.raw
import shapely
from affine import Affine
from branca.element import Element, MacroElement
from jinja2 import Template
from pyproj import Transformer
from rasterio.crs import CRS
from rasterio.warp import Resampling, calculate_default_transform, reproject, transform_bounds

from common.atomic import atomic_paths

log = logging.getLogger(__name__)

ASSETS = Path(__file__).with_name("assets")
MAX_IMAGE_PX = 2048
"""Longest side (pixels) of a raster overlay; larger rasters are resampled coarser (the file stays small)."""
RAMP = tuple(branca.colormap.linear.viridis.colors)
"""Colour ramp of raster overlays (viridis, RGBA in 0..1)."""
VECTOR_COLOURS = {"water": "#1f78b4", "other": "#222222"}
"""Line colour of a vector file's overlay: water (its name mentions water, a lake, river or sea) or other."""
WATER_WORDS = ("water", "lake", "river", "sea")


@dataclass(frozen=True)
class VectorSource:
    """A layer of a vector file to draw: ``path``, ``layer`` (None: the file's only layer) and the
    overlay's ``name`` (None: the layer's name, else the file's stem)."""

    path: Path
    layer: str | None = None
    name: str | None = None

    @classmethod
    def parse(cls, text: str) -> VectorSource:
        """``PATH[:LAYER][=NAME]``, e.g. ``region.gpkg:lakes=water`` (ValueError naming ``text`` if a part is empty)."""
        rest, eq, name = text.rpartition("=") if "=" in text else (text, "", "")
        path, colon, layer = rest.rpartition(":") if ":" in rest else (rest, "", "")
        if not path or (colon and not layer) or (eq and not name):
            raise ValueError(f"{text!r}: expected PATH[:LAYER][=NAME] with no empty part")
        return cls(Path(path), layer or None, name or None)

    @property
    def label(self) -> str:
        """The overlay's name."""
        return self.name or self.layer or self.path.stem


def _leaflet_assets() -> tuple[str, str]:
    """Leaflet's JavaScript and its CSS with the control images inlined as data URIs."""
    js = (ASSETS / "leaflet.js").read_text(encoding="utf-8")
    js = re.sub(r"//# sourceMappingURL=\S+\s*$", "", js)  # devtools would request the .map file

    def data_uri(match: re.Match) -> str:
        png = (ASSETS / match.group(1)).read_bytes()
        return f"url(data:image/png;base64,{base64.b64encode(png).decode()})"

    css = re.sub(r"url\((images/[\w.-]+\.png)\)", data_uri, (ASSETS / "leaflet.css").read_text(encoding="utf-8"))
    return js, css


class _Legend(MacroElement):
    """A Leaflet control (bottom right) holding the SVG of a branca colormap (no d3 needed)."""

    _template = Template("""
        {% macro script(this, kwargs) %}
        var {{ this.get_name() }} = L.control({position: "bottomright"});
        {{ this.get_name() }}.onAdd = function () {
            let div = L.DomUtil.create("div", "map-legend");
            div.style.background = "rgba(255, 255, 255, 0.85)";
            div.style.padding = "4px 8px";
            div.innerHTML = {{ this.svg|tojson }};
            return div;
        };
        {{ this.get_name() }}.addTo({{ this._parent.get_name() }});
        {% endmacro %}
    """)

    def __init__(self, svg: str):
        super().__init__()
        self._name = "Legend"
        self.svg = svg


class LeafletMap:
    """A Leaflet map of data in the projected CRS ``crs``, framed on ``bounds`` (xmin, ymin, xmax, ymax, m).

    ``basemap``: an optional XYZ tile URL template (``https://.../{z}/{x}/{y}.png``) drawn under the layers;
    without one the map needs no network at all.
    """

    def __init__(self, crs: CRS | str, bounds: Sequence[float], basemap: str | None = None,
                 attribution: str = "basemap"):
        self.crs = CRS.from_user_input(crs)
        west, south, east, north = transform_bounds(self.crs, "EPSG:4326", *bounds)
        self.map = folium.Map(tiles=None, control_scale=True, zoom_snap=0.25)
        # folium links Leaflet, jQuery and Bootstrap from CDNs; the map uses Leaflet only, inlined below
        self.map.default_js, self.map.default_css = [], []
        js, css = _leaflet_assets()
        header = self.map.get_root().header
        header.add_child(Element(f"<style>{css}</style>"), name="leaflet_css")
        header.add_child(Element(f"<script>{js}</script>"), name="leaflet_js")
        if basemap:
            folium.TileLayer(tiles=basemap, attr=attribution, name="basemap", overlay=False).add_to(self.map)
        self.map.fit_bounds([[south, west], [north, east]])

    def add_raster(self, name: str, values: np.ndarray, transform: Affine, caption: str,
                   opacity: float = 0.75, sqrt_ramp: bool = True) -> None:
        """A raster (H, W) on the grid ``transform`` (map CRS) as an image overlay with a legend; zeros and
        NaN transparent. ``sqrt_ramp`` spreads the colours evenly in √value, so small densities stay
        visible; the legend shows value ÷ maximum, with the maximum in its caption."""
        values = np.asarray(values, dtype=np.float64)
        h, w = values.shape
        left, top = transform @ (0, 0)
        right, bottom = transform @ (w, h)
        dst_transform, dst_w, dst_h = calculate_default_transform(self.crs, "EPSG:3857", w, h, left, bottom, right, top)
        scale = max(dst_w, dst_h) / MAX_IMAGE_PX
        if scale > 1:
            dst_transform, dst_w, dst_h = calculate_default_transform(
                self.crs, "EPSG:3857", w, h, left, bottom, right, top, dst_width=round(dst_w / scale),
                dst_height=round(dst_h / scale))
        warped = np.full((dst_h, dst_w), np.nan)
        # nearest keeps structural zeros exact (bilinear would smear density into water)
        reproject(values, warped, src_transform=transform, src_crs=self.crs, dst_transform=dst_transform,
                  dst_crs="EPSG:3857", resampling=Resampling.nearest, src_nodata=np.nan, dst_nodata=np.nan)
        finite = np.isfinite(warped) & (warped > 0)
        vmax = float(warped[finite].max()) if finite.any() else 1.0
        shown = warped[finite] / vmax  # the legend reads 0..1; its caption gives the maximum
        stops = np.linspace(0.0, 1.0, len(RAMP))
        index = stops**2 if sqrt_ramp else stops
        colormap = branca.colormap.LinearColormap(RAMP, index=index.tolist(), vmin=0.0, vmax=1.0,
                                                  caption=f"{caption} ÷ its maximum {vmax:.3g}",
                                                  tick_labels=[0.0, 0.1, 0.25, 0.5, 0.75, 1.0])
        rgba = np.zeros((dst_h, dst_w, 4), dtype=np.uint8)
        ramp = np.asarray(RAMP)
        for band in range(4):
            rgba[..., band][finite] = np.round(255 * np.interp(shown, index, ramp[:, band])).astype(np.uint8)
        west, north = dst_transform @ (0, 0)
        east, south = dst_transform @ (dst_w, dst_h)
        lon0, lat0, lon1, lat1 = transform_bounds("EPSG:3857", "EPSG:4326", west, south, east, north)
        folium.raster_layers.ImageOverlay(rgba, bounds=[[lat0, lon0], [lat1, lon1]], name=name, opacity=opacity,
                                          mercator_project=False, overlay=True).add_to(self.map)
        _Legend(colormap._repr_html_()).add_to(self.map)

    def _geojson(self, geometries: Sequence[shapely.Geometry], properties: Sequence[Mapping[str, str]],
                 crs: CRS) -> dict:
        """A GeoJSON FeatureCollection (lon/lat) of ``crs`` geometries with one properties dict each."""
        geoms = np.asarray(geometries, dtype=object)
        if crs != CRS.from_epsg(4326) and len(geoms):
            t = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
            geoms = shapely.transform(geoms, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1])))
        features = [{"type": "Feature", "geometry": json.loads(shapely.to_geojson(g)), "properties": dict(p)}
                    for g, p in zip(geoms, properties, strict=True)]
        return {"type": "FeatureCollection", "features": features}

    def _layer(self, name: str, geometries: Sequence[shapely.Geometry],
               popups: Sequence[Mapping[str, str]] | None, crs: CRS | str | None = None, **options) -> None:
        """One folium GeoJson layer of ``geometries`` (in ``crs``, default the map's) with an optional popup
        table per feature."""
        props = list(popups) if popups is not None else [{} for _ in range(len(geometries))]
        src = self.crs if crs is None else CRS.from_user_input(crs)
        layer = folium.GeoJson(self._geojson(geometries, props, src), name=name, **options)
        if props and props[0]:
            layer.add_child(folium.GeoJsonPopup(fields=list(props[0])))
        layer.add_to(self.map)

    def add_shapes(self, name: str, geometries: Sequence[shapely.Geometry], colour: str,
                   popups: Sequence[Mapping[str, str]] | None = None, fill: float = 0.0, weight: float = 1.5,
                   show: bool = True, crs: CRS | str | None = None) -> None:
        """Lines or polygons (in ``crs``, default the map's) as one switchable layer; ``popups``: per
        geometry a table {label: text} shown on click (all with the same labels)."""
        style = {"color": colour, "weight": weight, "fillColor": colour, "fillOpacity": fill}
        self._layer(name, geometries, popups, crs, show=show, style_function=lambda _feature: style)

    def add_vector_file(self, path: str | Path, layer: str | None = None, name: str | None = None,
                        colour: str | None = None, fill: float = 0.35, where: str | None = None) -> int:
        """Draw one layer of a vector file (any CRS GDAL reads, reprojected to lon/lat) as one switchable
        overlay: the one reader of vector layers for both maps. ``layer``: None for a file's only layer;
        ``name``: the overlay's (default as :attr:`VectorSource.label`); ``colour``: default by the name
        (:data:`VECTOR_COLOURS`); ``fill``: polygon fill opacity (lines are never filled); ``where``: an
        SQL attribute filter. Features without geometry are skipped (logged). Returns the features drawn;
        a missing file, unknown layer or bad filter is a ValueError naming it."""
        path = Path(path)
        where_text = f"{path}" + (f" layer {layer!r}" if layer else "")
        if not path.exists():
            raise ValueError(f"{path}: vector file not found")
        try:
            available = [str(n) for n in pyogrio.list_layers(path)[:, 0]]
        except pyogrio.errors.DataSourceError as exc:
            raise ValueError(f"{path}: not a readable vector file: {exc}") from None
        if layer is None and len(available) != 1:
            raise ValueError(f"{path}: the file has layers {available}; name one (PATH:LAYER)")
        if layer is not None and layer not in available:
            raise ValueError(f"{path}: no layer {layer!r}; the file has {available}")
        layer = layer if layer is not None else available[0]
        try:
            meta, _, wkb, _ = pyogrio.raw.read(path, layer=layer, where=where, columns=[])
        except (pyogrio.errors.DataLayerError, pyogrio.errors.FieldError) as exc:
            raise ValueError(f"{where_text}: cannot read" + (f" with where = {where!r}" if where else "")
                             + f": {exc}") from None
        if meta["crs"] is None:
            raise ValueError(f"{where_text}: the layer has no CRS; cannot place it on the map")
        geoms = shapely.from_wkb(wkb) if wkb is not None else np.empty(0, dtype=object)
        keep = ~shapely.is_missing(geoms) & ~shapely.is_empty(geoms)
        if not keep.all():
            log.warning("%s: %d of %d features have no geometry; not drawn", where_text, int((~keep).sum()), keep.size)
        name = name or VectorSource(path, layer).label
        if colour is None:
            colour = VECTOR_COLOURS["water" if any(w in name.lower() for w in WATER_WORDS) else "other"]
        self.add_shapes(name, geoms[keep], colour, fill=fill, crs=meta["crs"])
        return int(keep.sum())

    def add_points(self, name: str, xy: np.ndarray, colour: str,
                   popups: Sequence[Mapping[str, str]] | None = None, radius: float = 4.0) -> None:
        """Points (N, 2) in the map CRS as circle markers (vector, no icon images) in one switchable layer."""
        xy = np.reshape(np.asarray(xy, dtype=np.float64), (-1, 2))
        marker = folium.CircleMarker(radius=radius, color=colour, fill=True, fill_color=colour, fill_opacity=0.9, weight=1)
        self._layer(name, shapely.points(xy), popups, marker=marker)

    def save(self, path: str | Path, title: str = "map") -> Path:
        """Write the map as one HTML file (atomically), with a layer switcher."""
        folium.LayerControl(collapsed=False).add_to(self.map)
        root = self.map.get_root()
        root.header.add_child(Element(f"<title>{html.escape(title)}</title>"), name="title")
        with atomic_paths(path) as (tmp,):
            root.save(str(tmp))
        return Path(path)


def covariance_popup(cov: np.ndarray) -> str:
    """A 2×2 covariance (m²) as text: the entries and the 1-σ semi-axes (m)."""
    axes = np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0.0, None))[::-1]
    return (f"[[{cov[0, 0]:.4g}, {cov[0, 1]:.4g}], [{cov[1, 0]:.4g}, {cov[1, 1]:.4g}]] m² "
            f"(σ axes {axes[0]:.3g} m, {axes[1]:.3g} m)")


def density_map(density: np.ndarray, transform: Affine, crs: CRS | str, basemap: str | None = None,
                name: str = "prior density") -> LeafletMap:
    """A map framed on a density grid (per m², ``transform`` and ``crs`` of the grid) with it as the
    first overlay: the one starting point of the prior's map and the tracker's."""
    h, w = np.shape(density)
    left, top = transform @ (0, 0)
    right, bottom = transform @ (w, h)
    m = LeafletMap(crs, (left, bottom, right, top), basemap=basemap)
    m.add_raster(name, density, transform, caption=f"{name} (per m²)")
    return m
