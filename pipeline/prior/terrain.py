"""TerrainPrior: a normalised prior density on a grid, with summed-area tables for O(1) rectangle sums.

This is the only thing the tracker knows about terrain. It is read-only once built.

Files: ``prior.tif`` (float32 density per m^2, CRS, transform, the model as tags) and, beside it,
``prior.sat.npy`` / ``prior.sat2.npy``: the padded (H+1, W+1) float64 summed-area tables of the per-cell
mass of r (probability) and of r^2 (per m^2). They are memory-mapped on read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numba as nb
import numpy as np
import rasterio

from pipeline.gis.grid import Grid
from pipeline.prior.write import BLOCK, sat_paths, write_prior


class PriorError(ValueError):
    """A prior that cannot be built or read."""


@nb.njit(cache=True, inline="always")
def sat_integral(sat: np.ndarray, u: float, v: float) -> float:
    """Integral of the cell values from the grid origin to fractional pixel point (u = column, v = row).

    ``sat`` is a padded summed-area table (H+1, W+1) with ``sat[0, :] = sat[:, 0] = 0``. Because the
    field is constant inside a cell, this integral is bilinear in (u, v) within each cell, so the
    bilinear interpolation of the table is exact. Points outside the grid clamp to its edge,
    which makes the field zero outside.
    """
    h = sat.shape[0] - 1
    w = sat.shape[1] - 1
    u = min(max(u, 0.0), float(w))
    v = min(max(v, 0.0), float(h))
    i = min(int(u), w - 1)
    j = min(int(v), h - 1)
    fu = u - i
    fv = v - j
    s00 = sat[j, i]
    s01 = sat[j, i + 1]
    s10 = sat[j + 1, i]
    s11 = sat[j + 1, i + 1]
    return (s00 * (1.0 - fu) + s01 * fu) * (1.0 - fv) + (s10 * (1.0 - fu) + s11 * fu) * fv


@nb.njit(cache=True, inline="always")
def sat_rect(sat: np.ndarray, u0: float, u1: float, v0: float, v1: float) -> float:
    """Sum over the fractional pixel rectangle [u0, u1] x [v0, v1] (u0 <= u1, v0 <= v1)."""
    return (
        sat_integral(sat, u1, v1)
        - sat_integral(sat, u0, v1)
        - sat_integral(sat, u1, v0)
        + sat_integral(sat, u0, v0)
    )


@nb.njit(cache=True, parallel=True)
def _rect_sums(sat, u0, u1, v0, v1, out):
    for k in nb.prange(u0.shape[0]):
        out[k] = sat_rect(sat, u0[k], u1[k], v0[k], v1[k])


@nb.njit(cache=True)
def density_table_rows(r, total, cell_area, above, above2, density, sat, sat2):
    """density = r / total for a band of rows, and the matching rows of the padded summed-area tables of
    density*cell_area and density^2*cell_area (``sat``/``sat2`` are (rows, W+1), column 0 zero) under the
    table rows ``above``/``above2`` (zeros for the first band).

    One fused pass, so a 10,000 x 10,000 grid is read once and written once per output with no
    temporaries; the tiled build calls it band by band with the previous band's last rows, which gives
    tables bit-identical to one call over the whole grid.
    """
    h, w = r.shape
    for i in range(h):
        sat[i, 0] = 0.0
        sat2[i, 0] = 0.0
        row = 0.0
        row2 = 0.0
        for j in range(w):
            d = r[i, j] / total
            density[i, j] = d
            row += d * cell_area
            row2 += d * d * cell_area
            if i == 0:
                sat[i, j + 1] = above[j + 1] + row
                sat2[i, j + 1] = above2[j + 1] + row2
            else:
                sat[i, j + 1] = sat[i - 1, j + 1] + row
                sat2[i, j + 1] = sat2[i - 1, j + 1] + row2


class TerrainPrior:
    """A prior density r(x) per m^2 on a grid, zero outside it, integrating to 1 over the grid.

    Attributes: ``grid`` (Grid), ``density`` ((H, W) per m^2), ``sat`` and ``sat2`` (padded
    summed-area tables of the per-cell mass of r and of r^2), ``model`` (dict describing how it was built).
    """

    def __init__(
        self,
        grid: Grid,
        density: np.ndarray,
        sat: np.ndarray,
        sat2: np.ndarray,
        model: dict | None = None,
    ) -> None:
        if density.shape != grid.shape:
            raise PriorError(f"density shape {density.shape} does not match grid {grid.shape}")
        expected = (grid.height + 1, grid.width + 1)
        if sat.shape != expected or sat2.shape != expected:
            raise PriorError(f"summed-area tables must be {expected}, got {sat.shape}, {sat2.shape}")
        self.grid = grid
        self.density = density
        self.sat = sat
        self.sat2 = sat2
        self.model = dict(model or {})

    @classmethod
    def from_array(cls, r: np.ndarray, grid: Grid, model: dict | None = None) -> TerrainPrior:
        """Normalise a non-negative (H, W) array of relative likelihoods into a density per m^2."""
        r = np.asarray(r, dtype=np.float64)
        if r.shape != grid.shape:
            raise PriorError(f"likelihood array shape {r.shape} does not match grid {grid.shape}")
        # min/max first (NaN propagates): no full-size temporaries unless something is wrong
        if not (r.min() >= 0 and np.isfinite(r.max())):
            bad = ~np.isfinite(r) | (r < 0)
            rows, cols = np.nonzero(bad)
            raise PriorError(
                f"likelihood must be finite and >= 0; {bad.sum()} bad cells, first at row {rows[0]}, col {cols[0]}"
            )
        total = float(r.sum()) * grid.cell_area
        if not total > 0:
            raise PriorError(
                "the likelihood table makes r zero everywhere on the grid; check for structural zeros covering the region"
            )
        density = np.empty(grid.shape, dtype=np.float64)
        sat = np.empty((grid.height + 1, grid.width + 1), dtype=np.float64)
        sat2 = np.empty_like(sat)
        zeros = np.zeros(grid.width + 1)
        sat[0], sat2[0] = zeros, zeros
        density_table_rows(np.ascontiguousarray(r), total, grid.cell_area, zeros, zeros, density, sat[1:], sat2[1:])
        return cls(grid, density, sat, sat2, model)

    @classmethod
    def uniform(cls, grid: Grid) -> TerrainPrior:
        """The uniform density over the grid (1 / grid area)."""
        return cls.from_array(np.ones(grid.shape), grid, {"uniform": True})

    def write(self, path: str | Path) -> Path:
        """Write the GeoTIFF and its summed-area tables atomically (:func:`pipeline.prior.write.write_prior`);
        returns the GeoTIFF path."""
        rows = range(0, self.grid.height, BLOCK)
        strips = ((self.density[r : r + BLOCK], self.sat[r + 1 : r + 1 + BLOCK], self.sat2[r + 1 : r + 1 + BLOCK]) for r in rows)
        return write_prior(path, self.grid, self.model, strips)

    @classmethod
    def read(cls, path: str | Path) -> TerrainPrior:
        """Load a prior written by :meth:`write` (tables memory-mapped)."""
        path = Path(path)
        sat_p, sat2_p = sat_paths(path)
        for p in (path, sat_p, sat2_p):
            if not p.exists():
                raise PriorError(f"{p}: missing; a prior is prior.tif plus prior.sat.npy and prior.sat2.npy beside it")
        try:
            with rasterio.open(path) as src:
                density = src.read(1).astype(np.float64)
                grid = Grid(src.crs, src.transform, src.height, src.width)
                model = json.loads(src.tags().get("MODEL", "{}"))
        except rasterio.errors.RasterioIOError as exc:
            raise PriorError(f"{path}: cannot read prior GeoTIFF: {exc}") from exc
        return cls(grid, density, np.load(sat_p, mmap_mode="r"), np.load(sat2_p, mmap_mode="r"), model)

    def sample(
        self, n: int, rng: np.random.Generator, region: tuple[float, float, float, float] | None = None
    ) -> np.ndarray:
        """``n`` i.i.d. points (n, 2) in metres (grid CRS) from r restricted to ``region`` ((xmin, ymin,
        xmax, ymax) metres, cell-aligned; the whole grid when None): a cell by inverse CDF of the per-cell
        masses, then a uniform point inside it. Draws ``rng.random(n)`` three times (cells, x, y)."""
        grid = self.grid
        c0, r0, c1, r1 = 0, 0, grid.width, grid.height
        if region is not None:
            u0, v1 = grid.to_pixel(region[0], region[1])
            u1, v0 = grid.to_pixel(region[2], region[3])
            px = np.array([u0, u1, v0, v1], dtype=np.float64)
            c0, c1, r0, r1 = (int(k) for k in np.rint(px))
            aligned = np.allclose(px, np.rint(px), atol=1e-6)
            if not (aligned and 0 <= c0 < c1 <= grid.width and 0 <= r0 < r1 <= grid.height):
                raise ValueError(f"TerrainPrior.sample: region {region} is not a cell-aligned window of the grid {grid.bounds}")
        mass = np.asarray(self.density[r0:r1, c0:c1], dtype=np.float64).ravel()
        cdf = np.cumsum(mass)
        if not cdf.size or not cdf[-1] > 0:
            raise ValueError(f"TerrainPrior.sample: the prior has no mass in region {region}")
        cells = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right")
        # Guard the u == total edge case (and zero-mass trailing cells) against float rounding.
        cells = np.minimum(cells, np.flatnonzero(mass > 0)[-1])
        w = c1 - c0
        rows = r0 + cells // w
        cols = c0 + cells % w
        x = grid.transform.c + (cols + rng.random(n)) * grid.dx
        y = grid.transform.f - (rows + rng.random(n)) * grid.dy
        return np.stack([x, y], axis=1)

    def to_xarray(self):
        """The density as an ``xarray.DataArray`` named "density" (per m^2), dims (y, x) with cell-centre
        coordinates in metres and the CRS and transform attached with rioxarray, so ``.plot()``,
        ``.sel(x=, y=, method="nearest")`` and ``.rio.to_raster()`` work; the model is the JSON attr "model"."""
        attrs = {"units": "1/m^2", "model": json.dumps(self.model)}
        return self.grid.to_xarray(np.asarray(self.density), "density", attrs)

    def density_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Density per m^2 at map points (metres, grid CRS); zero off the grid."""
        r, c, inside = self.grid.cell_index(x, y)
        out = np.zeros(np.shape(inside), dtype=np.float64)
        out[inside] = self.density[r[inside], c[inside]]
        return out

    def rect_sum(
        self,
        x0: np.ndarray,
        x1: np.ndarray,
        y0: np.ndarray,
        y1: np.ndarray,
        squared: bool = False,
    ) -> np.ndarray:
        """Integral of r (probability mass) or r^2 (per m^2) over map rectangles [x0,x1] x [y0,y1].

        Vectorised over arrays of equal shape; corners may fall anywhere inside or outside a cell
        (the prior is zero off the grid). Requires x0 <= x1 and y0 <= y1.
        """
        x0, x1, y0, y1 = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x0, x1, y0, y1)))
        if np.any(x1 < x0) or np.any(y1 < y0):
            raise ValueError("rect_sum needs x0 <= x1 and y0 <= y1")
        u0, v1 = self.grid.to_pixel(x0, y0)
        u1, v0 = self.grid.to_pixel(x1, y1)
        return self.rect_sum_px(u0, u1, v0, v1, squared)

    def rect_sum_px(
        self, u0: np.ndarray, u1: np.ndarray, v0: np.ndarray, v1: np.ndarray, squared: bool = False
    ) -> np.ndarray:
        """As :meth:`rect_sum` in fractional pixel coordinates (u columns, v rows from the north-west corner)."""
        shape = np.shape(u0)
        flat = [np.ascontiguousarray(a, dtype=np.float64).ravel() for a in (u0, u1, v0, v1)]
        out = np.empty(flat[0].shape[0], dtype=np.float64)
        _rect_sums(np.asarray(self.sat2 if squared else self.sat), *flat, out)
        return out.reshape(shape)
