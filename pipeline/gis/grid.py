"""The raster grid every feature and the prior live on: projected CRS, metres, north-up."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from affine import Affine
from pyproj import Proj
from rasterio.crs import CRS

from pipeline.gis.crs import to_pyproj, transformer

NODATA_CODE = -1
"""Code of a categorical cell with no data (continuous features use NaN)."""


class GridError(ValueError):
    """A grid that cannot carry metric features (geographic CRS, bad bounds or cell size); ``key`` is the
    ``[region]`` key at fault ("crs", "bounds" or "cell_size")."""

    def __init__(self, msg: str, key: str) -> None:
        super().__init__(msg)
        self.key = key


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid in a projected CRS whose units are metres.

    Row 0 is the northern edge; column 0 the western edge. ``transform`` maps
    (col, row) pixel coordinates to (x, y) map coordinates in metres.
    """

    crs: CRS
    transform: Affine
    height: int
    width: int

    def __post_init__(self) -> None:
        crs = CRS.from_user_input(self.crs)
        object.__setattr__(self, "crs", crs)
        if crs.is_geographic:
            raise GridError(
                f"grid CRS {crs.to_string()} is geographic (degrees); features need metres: "
                "choose a projected CRS or set crs = \"utm\" in the region config", "crs"
            )
        pcrs = to_pyproj(crs)
        units = {(a.unit_name, a.unit_conversion_factor) for a in pcrs.axis_info[:2]}
        if units != {("metre", 1.0)}:
            names = ", ".join(sorted({name for name, _ in units}))
            code = f" ({crs.to_string()})" if crs.to_epsg() else ""
            raise GridError(
                f"grid CRS {pcrs.name!r}{code} has units of {names}, not metres; cell_size, buffers and distances "
                "are metres: choose a CRS in metres (e.g. the UTM zone in metres, or crs = \"utm\")", "crs"
            )
        t = self.transform
        if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            raise GridError(f"grid transform must be north-up with positive cell sizes, got {t!r}", "cell_size")
        if self.height <= 0 or self.width <= 0:
            raise GridError(f"grid shape must be positive, got {self.height} x {self.width}", "bounds")

    @classmethod
    def from_bounds(
        cls, bounds: tuple[float, float, float, float], cell_size: float, crs: CRS | str
    ) -> Grid:
        """Grid covering ``bounds`` = (xmin, ymin, xmax, ymax) in metres with square cells.

        The extent is rounded up to whole cells from the north-west corner.
        """
        xmin, ymin, xmax, ymax = map(float, bounds)
        if not all(np.isfinite((xmin, ymin, xmax, ymax, cell_size))):
            raise GridError(f"grid bounds and cell_size must be finite, got bounds {bounds}, cell_size {cell_size}", "bounds")
        if not (xmax > xmin and ymax > ymin):
            raise GridError(f"grid bounds must have xmax > xmin and ymax > ymin, got {bounds}", "bounds")
        if not cell_size > 0:
            raise GridError(f"cell_size must be positive metres, got {cell_size}", "cell_size")
        width = int(np.ceil((xmax - xmin) / cell_size - 1e-9))
        height = int(np.ceil((ymax - ymin) / cell_size - 1e-9))
        return cls(crs, Affine(cell_size, 0.0, xmin, 0.0, -cell_size, ymax), height, width)

    def scale_factor(self) -> float:
        """Point scale factor of the CRS at the grid's centre: grid metres per ground metre (1/cos φ for
        Web Mercator, 0.9996..1.001 in a UTM zone)."""
        x, y = (self.bounds[0] + self.bounds[2]) / 2.0, (self.bounds[1] + self.bounds[3]) / 2.0
        geo = to_pyproj(self.crs).geodetic_crs
        lon, lat = transformer(self.crs, geo).transform(x, y)
        f = Proj(to_pyproj(self.crs)).get_factors(lon, lat)
        return float(np.sqrt(f.meridional_scale * f.parallel_scale))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def dx(self) -> float:
        """Cell width in metres."""
        return float(self.transform.a)

    @property
    def dy(self) -> float:
        """Cell height in metres (positive)."""
        return float(-self.transform.e)

    @property
    def cell_area(self) -> float:
        """Cell area in square metres."""
        return self.dx * self.dy

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in metres."""
        left, top = self.transform.c, self.transform.f
        return (left, top - self.height * self.dy, left + self.width * self.dx, top)

    def to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional pixel coordinates (u = column, v = row) of map points; cell (r, c) spans [c, c+1) x [r, r+1)."""
        u = (np.asarray(x, dtype=np.float64) - self.transform.c) / self.dx
        v = (self.transform.f - np.asarray(y, dtype=np.float64)) / self.dy
        return u, v

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True where map points (metres) fall in a cell of the grid (half-open cells, as :meth:`to_pixel`)."""
        return self.cell_index(x, y)[2]

    def cell_index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of map points (metres): integer cell indices, 0 where a point is off the grid."""
        u, v = self.to_pixel(x, y)
        inside = (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        return np.where(inside, v, 0).astype(np.intp), np.where(inside, u, 0).astype(np.intp), inside

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre x of each column (west to east) and y of each row (north to south), metres."""
        xs = self.transform.c + (np.arange(self.width) + 0.5) * self.dx
        ys = self.transform.f - (np.arange(self.height) + 0.5) * self.dy
        return xs, ys

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinates (x, y) of cell centres as two (height, width) arrays."""
        return np.meshgrid(*self.axes())

    def to_xarray(self, values: np.ndarray, name: str, attrs: dict | None = None, nodata: float | None = None):
        """An (H, W) array on this grid as an xarray DataArray: dims (y, x), cell-centre coordinates
        in metres, the CRS, transform and ``nodata`` attached the rioxarray way (``.rio``)."""
        import rioxarray  # noqa: F401  (registers the .rio accessor; imported here to keep grids light)
        import xarray as xr

        xs, ys = self.axes()
        da = xr.DataArray(values, dims=("y", "x"), coords={"x": xs, "y": ys}, name=name, attrs=dict(attrs or {}))
        da = da.rio.write_crs(self.crs.to_wkt()).rio.write_transform(self.transform)
        return da if nodata is None else da.rio.write_nodata(nodata, encoded=False)

    def window_grid(self, row_off: int, col_off: int, height: int, width: int) -> Grid:
        """The sub-grid of a window (rasterio's row/col offsets), same CRS and cell size."""
        t = self.transform * Affine.translation(col_off, row_off)
        return Grid(self.crs, t, height, width)
