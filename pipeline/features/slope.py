"""Slope in degrees from a DEM by Horn's method, as ``gdaldem slope -compute_edges`` computes it.

Horn (1981) weights the 3x3 window 1-2-1 across the derivative direction:
``dz/dx = ((c + 2f + i) - (a + 2d + g)) / (8 dx)``, ``dz/dy = ((g + 2h + i) - (a + 2b + c)) / (8 dy)``
and ``slope = atan(hypot(dz/dx, dz/dy))``. It is exact for planes and for quadratic surfaces.

Edges (gdaldem's ``-compute_edges``): a neighbour outside the raster is extrapolated linearly from
the two cells inward, ``2 z0 - z1``. At the four corner cells we extrapolate in both directions
(``4 z00 - 2 z01 - 2 z10 + z11``), so planes stay exact everywhere; gdaldem instead repeats the
corner column there, which halves the x-gradient of the corner cells on a plane.

No data (NaN, and +-inf): a no-data centre gives NaN; a no-data neighbour (or an extrapolated one
computed from no data) is replaced by the centre value, as gdaldem does with ``-compute_edges``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from pipeline.gis.grid import NODATA_CODE


@nb.njit(cache=True, inline="always")
def _at(row, c):
    """Value of a row at column c, extrapolated linearly one cell beyond either end."""
    w = row.shape[0]
    if c < 0:
        return 2.0 * row[0] - row[1]
    if c >= w:
        return 2.0 * row[w - 1] - row[w - 2]
    return row[c]


@nb.njit(cache=True)
def _horn(a, b, c, d, e, f, g, h, i, inv8dx, inv8dy):
    """Slope (degrees) of the 3x3 window a..i (row by row, e the centre); no-data neighbours take e."""
    # gdaldem -compute_edges: a missing neighbour takes the centre's value.
    a = a if np.isfinite(a) else e
    b = b if np.isfinite(b) else e
    c = c if np.isfinite(c) else e
    d = d if np.isfinite(d) else e
    f = f if np.isfinite(f) else e
    g = g if np.isfinite(g) else e
    h = h if np.isfinite(h) else e
    i = i if np.isfinite(i) else e
    gx = ((c + 2.0 * f + i) - (a + 2.0 * d + g)) * inv8dx
    gy = ((g + 2.0 * h + i) - (a + 2.0 * b + c)) * inv8dy
    return np.degrees(np.arctan(np.sqrt(gx * gx + gy * gy)))


@nb.njit(cache=True)
def _original_row(dem, r, out):
    """Row r of the DEM as float64 into ``out``; rows -1 and h extrapolated linearly from the two
    rows inward (so planes stay exact at the edges and corners)."""
    h = dem.shape[0]
    for c in range(dem.shape[1]):
        if r < 0:
            out[c] = 2.0 * np.float64(dem[0, c]) - np.float64(dem[1, c])
        elif r >= h:
            out[c] = 2.0 * np.float64(dem[h - 1, c]) - np.float64(dem[h - 2, c])
        else:
            out[c] = np.float64(dem[r, c])


@nb.njit(cache=True, parallel=True)
def _horn_slope(dem: np.ndarray, inv8dx: float, inv8dy: float, out: np.ndarray, chunks: int) -> int:
    """Fill ``out`` with Horn slopes (``out`` may be ``dem`` itself); returns the number of cells with
    data. Each of ``chunks`` bands of rows keeps float64 copies of the original rows above, at and
    below the row it writes, so no padded copy of the DEM exists and writing in place is safe: the
    rows just outside each band are copied before any band is written."""
    h, w = dem.shape
    bounds = np.linspace(0, h, chunks + 1).astype(np.int64)
    edges = np.empty((chunks, 2, w))  # original rows bounds[k] - 1 and bounds[k + 1] per band
    for k in range(chunks):
        _original_row(dem, bounds[k] - 1, edges[k, 0])
        _original_row(dem, bounds[k + 1], edges[k, 1])
    valid = np.zeros(chunks, dtype=np.int64)
    for k in nb.prange(chunks):
        s, e = bounds[k], bounds[k + 1]
        above, centre, below = edges[k, 0].copy(), np.empty(w), np.empty(w)
        if s < e:
            _original_row(dem, s, centre)
        for r in range(s, e):
            if r + 1 < e:
                _original_row(dem, r + 1, below)
            else:
                below[:] = edges[k, 1]
            for c in range(w):
                m = centre[c]
                if not np.isfinite(m):
                    out[r, c] = np.nan
                    continue
                valid[k] += 1
                out[r, c] = _horn(
                    _at(above, c - 1), _at(above, c), _at(above, c + 1),
                    _at(centre, c - 1), m, _at(centre, c + 1),
                    _at(below, c - 1), _at(below, c), _at(below, c + 1),
                    inv8dx, inv8dy,
                )
            above, centre, below = centre, below, above
    return valid.sum()


def slope_deg(dem: np.ndarray, dx: float, dy: float, in_place: bool = False) -> np.ndarray:
    """Slope in degrees (0..90) of a north-up DEM (metres) with cells ``dx`` by ``dy`` metres.

    NaN (and +-inf) mark no data. Returns float32 for float32 input, float64 otherwise; NaN where the DEM is NaN.
    ``in_place``: write the slopes over a float32/float64 C-contiguous ``dem`` (the same numbers, no
    second grid-size array). Raises ValueError for a DEM that is not 2-D, smaller than 2 x 2, or
    entirely no data.
    """
    dem = np.asarray(dem)
    if dem.ndim != 2:
        raise ValueError(f"slope_deg: DEM must be 2-D, got shape {dem.shape}")
    if dem.shape[0] < 2 or dem.shape[1] < 2:
        raise ValueError(f"slope_deg: DEM must be at least 2 x 2 cells, got {dem.shape}")
    for name, value in (("dx", dx), ("dy", dy)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"slope_deg: {name} must be a positive cell size in metres, got {value}")
    if in_place and not (dem.dtype in (np.float32, np.float64) and dem.flags.c_contiguous and dem.flags.writeable):
        raise ValueError(f"slope_deg: in_place needs a writeable C-contiguous float DEM, got {dem.dtype}")
    if dem.dtype not in (np.float32, np.float64):
        dem = dem.astype(np.float64)
    out = dem if in_place else np.empty(dem.shape, dtype=dem.dtype)
    chunks = min(dem.shape[0], 4 * nb.get_num_threads())
    if _horn_slope(dem, 1.0 / (8.0 * dx), 1.0 / (8.0 * dy), out, chunks) == 0:
        raise ValueError("slope_deg: the DEM is entirely no data (NaN)")
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
    slope = np.ascontiguousarray(slope)
    codes = np.empty(slope.shape, dtype=np.int16)
    _classes(slope.reshape(-1), breaks, NODATA_CODE, codes.reshape(-1))
    return codes


@nb.njit(cache=True, parallel=True)
def _classes(slope, breaks, nodata, codes):
    """codes[i] = how many breaks slope[i] is at or above (compared in float64), ``nodata`` for NaN:
    one pass with no grid-size temporaries (the comparison per break made a boolean grid each)."""
    for i in nb.prange(slope.shape[0]):
        x = slope[i]
        if np.isnan(x):
            codes[i] = nodata
            continue
        k = 0
        for b in breaks:
            k += np.float64(x) >= b
        codes[i] = k
