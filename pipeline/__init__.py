"""GIS layers to a terrain prior, in subpackages that follow the data flow: gis → features → prior →
config → build → learn → tiled → show, with the command line in :mod:`pipeline.cli`."""
