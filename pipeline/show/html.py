"""The prior as an interactive, self-contained HTML map (Leaflet via folium, :mod:`common.maps`), with the
region's roads, water and obstacles when its config is given."""

from __future__ import annotations

from pathlib import Path

from common.maps import LeafletMap, density_map
from pipeline.config.region import RegionConfig
from pipeline.gis import open_source
from pipeline.prior.terrain import TerrainPrior

LAYER_COLOURS = {"distance": "#222222", "water": "#1f78b4", "mask": "#8c564b"}
"""Line colour of a vector layer by the feature it feeds: roads (distance features), water, other masks."""


def add_region_layers(m: LeafletMap, config: RegionConfig) -> list[str]:
    """Draw each vector layer that feeds a distance feature (roads) or a mask feature (water, obstacles),
    named by its ``[layers.<name>]`` key and filtered by its ``where``; returns the layer names drawn."""
    drawn: list[str] = []
    for feature in config.features.values():
        if feature.type not in ("distance", "mask"):
            continue
        colour = LAYER_COLOURS["water" if "water" in feature.name else feature.type]
        for name in feature.layers:
            if name in drawn:
                continue
            spec = config.layers[name]
            with open_source(spec) as path:  # a restore_index shapefile is read from its repaired copy
                m.add_vector_file(path, spec.layer, name, colour, fill=0.35 if feature.type == "mask" else 0.0,
                                  where=spec.where)
            drawn.append(name)
    return drawn


def prior_map(prior: TerrainPrior, config: RegionConfig | None = None, basemap: str | None = None) -> LeafletMap:
    """The prior density (colour ramp and legend) and, with ``config``, its region's vector layers."""
    m = density_map(prior.density, prior.grid.transform, prior.grid.crs, basemap=basemap)
    if config is not None:
        add_region_layers(m, config)
    return m


def write_prior_html(prior: TerrainPrior, path: str | Path, config: RegionConfig | None = None,
                     basemap: str | None = None) -> Path:
    """Write :func:`prior_map` as one HTML file that opens with no network (unless ``basemap`` is given)."""
    return prior_map(prior, config, basemap).save(path, title=f"prior density, {prior.grid.crs.to_string()}")
