"""Feature grids (the paper's Features(x)): named 2-D arrays on one Grid."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Literal

import numba as nb
import numpy as np

from pipeline.gis.grid import NODATA_CODE, Grid

_DENSE_CODE_RANGE = 1 << 20
"""Code ranges narrower than this are handled with dense look-up tables instead of sorting."""


@nb.njit(cache=True)
def _mark(codes: np.ndarray, lo: int, seen: np.ndarray) -> None:
    """seen[c - lo] = True for every code c (all within lo .. lo + len(seen) - 1)."""
    for c in codes:
        seen[c - lo] = True


@dataclass(frozen=True)
class Feature:
    """One feature grid.

    ``categorical``: integer codes (int16/int32), ``NODATA_CODE`` for no data; ``labels`` maps
    code -> name (e.g. ``{0: "dry", 1: "water"}``). ``continuous``: float values in ``units``
    (``"m"`` for distances, ``"deg"`` for slope), NaN for no data.
    """

    name: str
    values: np.ndarray
    kind: Literal["categorical", "continuous"]
    units: str = ""
    labels: dict[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.values.ndim != 2:
            raise ValueError(f"feature {self.name!r}: values must be 2-D, got shape {self.values.shape}")
        if self.kind == "categorical" and not np.issubdtype(self.values.dtype, np.integer):
            raise ValueError(f"categorical feature {self.name!r} needs integer codes, got {self.values.dtype}")
        if self.kind not in ("categorical", "continuous"):
            raise ValueError(f"feature {self.name!r}: kind must be categorical or continuous, got {self.kind!r}")

    def label(self, code: int) -> str:
        """Name of a category code (its number as text when unlabelled)."""
        return self.labels.get(int(code), str(int(code)))

    def codes(self) -> np.ndarray:
        """Category codes present (excluding no data), ascending."""
        if self.values.size == 0:
            return np.empty(0, dtype=self.values.dtype)
        lo, hi = int(self.values.min()), int(self.values.max())
        if hi - lo < _DENSE_CODE_RANGE:
            # A pass marking the code range is linear time; np.unique sorts all cells.
            seen = np.zeros(hi - lo + 1, dtype=np.bool_)
            _mark(self.values.reshape(-1), lo, seen)
            present = np.flatnonzero(seen) + lo
        else:
            present = np.unique(self.values)
        return present[present != NODATA_CODE]


@dataclass
class FeatureStack:
    """Feature grids sharing one Grid, keyed by feature name."""

    grid: Grid
    features: dict[str, Feature] = field(default_factory=dict)

    def add(self, feature: Feature) -> None:
        if feature.values.shape != self.grid.shape:
            raise ValueError(
                f"feature {feature.name!r} has shape {feature.values.shape}, grid is {self.grid.shape}"
            )
        self.features[feature.name] = feature

    def __getitem__(self, name: str) -> Feature:
        try:
            return self.features[name]
        except KeyError:
            raise KeyError(f"no feature {name!r}; have {sorted(self.features)}") from None

    def __contains__(self, name: str) -> bool:
        return name in self.features

    def __iter__(self):
        return iter(self.features.values())

    def to_xarray(self):
        """The features as an ``xarray.Dataset``, one variable per feature on dims (y, x) with
        cell-centre coordinates in metres and the CRS attached with rioxarray. Variable attrs: "kind",
        "units" and, for categorical features, "labels" (JSON code -> name); nodata is
        ``NODATA_CODE`` (categorical) or NaN (continuous)."""
        import xarray as xr

        arrays = {}
        for f in self:
            attrs = {"kind": f.kind, "units": f.units}
            if f.kind == "categorical":
                attrs["labels"] = json.dumps({str(k): v for k, v in f.labels.items()})
            nodata = NODATA_CODE if f.kind == "categorical" else np.nan
            arrays[f.name] = self.grid.to_xarray(f.values, f.name, attrs, nodata)
        return xr.Dataset(arrays).rio.write_crs(self.grid.crs.to_wkt()).rio.write_transform(self.grid.transform)

    def sample(self, x: np.ndarray, y: np.ndarray) -> dict[str, np.ndarray]:
        """Feature values at map points (metres); points off the grid get no data."""
        r, c, inside = self.grid.cell_index(x, y)
        out = {}
        for f in self:
            vals = f.values[r, c]
            if f.kind == "categorical":
                out[f.name] = np.where(inside, vals, NODATA_CODE)
            else:
                out[f.name] = np.where(inside, vals.astype(np.float64), np.nan)
        return out
