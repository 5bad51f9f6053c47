"""TerrainPrior: a normalised prior density on a grid, with summed-area tables for O(1) rectangle sums.

This is the only thing the tracker knows about terrain. It is read-only once built.

Files: ``prior.tif`` (float32 density per m^2, CRS, transform, the model and the build binding as tags)
and, beside it, ``prior.sat.npy`` / ``prior.sat2.npy``: the padded (H+1, W+1) float64 summed-area tables
of the per-cell mass of r (probability) and of r^2 (per m^2). They are memory-mapped on read, after
:meth:`TerrainPrior.read` has checked that the three files are one build (:mod:`pipeline.prior.write`).
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator
from pathlib import Path

import numba as nb
import numpy as np
import rasterio

from pipeline.gis.grid import Grid, GridError
from pipeline.prior.windowed import WINDOWED_CELLS, WindowedDensity
from pipeline.prior.write import (
    BLOCK,
    BUILD_TAG,
    TABLE_TAGS,
    UNITS,
    sat_paths,
    table_hash,
    write_prior,
)

DENSITY_TOL = 1e-5
"""How far a read prior's integral of r, and its tables' last row and column totals (relative to the
table's total), may be from what the density implies: the density is stored as float32 (~6e-8 relative
rounding per cell), the tables as float64."""
SCAN_ROWS_BYTES = 1 << 24
"""Bytes of table rows hashed and checked at a time on read (bounds the memory a check touches)."""


class PriorError(ValueError):
    """A prior that cannot be built or read."""


def _bad_cells(bad: np.ndarray) -> str:
    """'N bad cells, first at row r, col c' for a boolean mask with at least one True."""
    rows, cols = np.nonzero(bad)
    return f"{bad.sum()} bad cells, first at row {rows[0]}, col {cols[0]}"


def _rebuild_hint(path: Path, model: dict) -> str:
    """How to rebuild the prior at ``path``, naming the region config it records when it does."""
    provenance = model.get("provenance")
    config = provenance.get("config") if isinstance(provenance, dict) else None
    return f"rebuild it with `terrain-prior build {config or 'REGION.toml'} --out {path}`"


class _LayoutNote(logging.Filter):
    """Drops GDAL's note that an edited COG lost its optimised layout: the prior still reads exactly, and
    :func:`_read_geotiff` checks what it holds, so the note is no news to whoever reads a prior."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "used to have optimizations in its layout" not in record.getMessage()


@contextlib.contextmanager
def _without_layout_note() -> Iterator[None]:
    log, note = logging.getLogger("rasterio._env"), _LayoutNote()
    log.addFilter(note)
    try:
        yield
    finally:
        log.removeFilter(note)


def _read_geotiff(path: Path, windowed: bool | None) -> tuple[Grid, np.ndarray | WindowedDensity, dict, list[str], str, tuple]:
    """Grid, density (float64 array, or a :class:`WindowedDensity` when ``windowed``; None: above
    :data:`WINDOWED_CELLS` cells), model, table digests, rebuild hint and the density's row and column
    sums of r and r² mass (:func:`_density_sums`); PriorError unless it carries a prior's tags and a
    finite, non-negative density that integrates to 1 (within DENSITY_TOL)."""
    try:
        with _without_layout_note(), rasterio.open(path) as src:
            tags = src.tags()
            profile = (src.count, src.dtypes[0])
            crs, transform, shape = src.crs, src.transform, src.shape
            if windowed is None:
                windowed = shape[0] * shape[1] > WINDOWED_CELLS
            density = None
            if profile == (1, "float32"):
                density = WindowedDensity(path, shape, np.nan) if windowed else src.read(1).astype(np.float64)
    except rasterio.errors.RasterioError as exc:
        raise PriorError(f"{path}: cannot read prior GeoTIFF: {exc}") from exc
    hint = _rebuild_hint(path, {})
    missing = [t for t in ("MODEL", BUILD_TAG, *TABLE_TAGS) if t not in tags]
    if missing or tags.get("UNITS") != UNITS or density is None:
        why = f"no {', '.join(missing)} tag{'s' * (len(missing) > 1)}" if missing else (
            f"UNITS tag {tags.get('UNITS')!r}, not {UNITS!r}" if tags.get("UNITS") != UNITS
            else f"{profile[0]} band(s) of {profile[1]}, not one float32 band")
        raise PriorError(f"{path}: not a prior written by terrain-prior build ({why}); {hint}")
    try:
        model = json.loads(tags["MODEL"])
    except json.JSONDecodeError as exc:
        raise PriorError(f"{path}: MODEL tag is not valid JSON ({exc}); {hint}") from exc
    if not isinstance(model, dict):
        raise PriorError(f"{path}: MODEL tag is a JSON {type(model).__name__}, not an object; {hint}")
    hint = _rebuild_hint(path, model)
    try:
        grid = Grid(crs, transform, *shape)
    except GridError as exc:
        raise PriorError(f"{path}: {exc}; {hint}") from exc
    strips = density.strips() if isinstance(density, WindowedDensity) else [(0, density)]
    total, top, sums = _density_sums(strips, grid.cell_area, f"{path}: density must be finite and >= 0; {{}}; {hint}")
    if isinstance(density, WindowedDensity):
        density.max = top
    if not abs(total - 1.0) <= DENSITY_TOL:
        raise PriorError(f"{path}: density integrates to {total:.9g}, not 1 (tolerance {DENSITY_TOL:g}); {hint}")
    return grid, density, model, [tags[t] for t in TABLE_TAGS], hint, sums


def _density_sums(strips, cell_area: float, bad_message: str) -> tuple[float, float, tuple]:
    """One pass over (first row, values) bands of a density: its integral, its largest value and, for the
    tables' check, ((column sums, row sums) of the cell mass of r, the same of r²). PriorError
    (``bad_message`` with the bad cells) at a negative or non-finite cell."""
    total, top, cols, cols2, rows, rows2 = 0.0, 0.0, 0.0, 0.0, [], []
    for r0, d in strips:
        # min/max first (NaN propagates): no full-size temporaries unless something is wrong
        if not (d.min() >= 0 and np.isfinite(d.max())):
            bad = ~(d >= 0) | ~np.isfinite(d)
            rows_bad, cols_bad = np.nonzero(bad)
            where = f"{bad.sum()} bad cells, first at row {r0 + rows_bad[0]}, col {cols_bad[0]}"
            # a windowed read stops at the first band that has any: the count is that band's
            raise PriorError(bad_message.format(where if r0 == 0 else f"{where} (in rows {r0}-{r0 + d.shape[0] - 1})"))
        mass = d * cell_area
        total += float(d.sum()) * cell_area
        top = max(top, float(d.max()))
        cols = cols + mass.sum(axis=0)
        rows.append(mass.sum(axis=1))
        mass *= d
        cols2 = cols2 + mass.sum(axis=0)
        rows2.append(mass.sum(axis=1))
    return total, top, ((cols, np.concatenate(rows)), (cols2, np.concatenate(rows2)))


def _read_table(path: Path, shape: tuple[int, int], hint: str) -> np.memmap:
    """Memory-map a summed-area table, refusing by name anything but a complete C-order float64 .npy of
    ``shape`` (never unpickling)."""
    fmt = np.lib.format
    try:
        size = path.stat().st_size
        if size == 0:
            raise PriorError(f"{path}: empty (0 bytes), not a summed-area table; {hint}")
        with open(path, "rb") as f:
            try:
                version = fmt.read_magic(f)
                read_header = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
                if read_header is None:
                    raise ValueError(f".npy format version {version} is not one np.save writes for tables")
                file_shape, fortran, dtype = read_header(f)
            except (ValueError, EOFError, SyntaxError) as exc:
                raise PriorError(f"{path}: not a .npy summed-area table ({exc}); {hint}") from exc
            offset = f.tell()
    except OSError as exc:
        raise PriorError(f"{path}: cannot read summed-area table: {exc.strerror or exc}; {hint}") from exc
    if dtype.hasobject:
        raise PriorError(f"{path}: holds pickled Python objects, not a float64 table (never unpickled); {hint}")
    if dtype != np.float64 or fortran:
        raise PriorError(f"{path}: table is {dtype.str}{' Fortran-order' if fortran else ''}, must be C-order float64 (<f8); {hint}")
    if file_shape != shape:
        raise PriorError(f"{path}: table shape {file_shape} does not match the prior's grid: expected {shape}; {hint}")
    want = offset + dtype.itemsize * shape[0] * shape[1]
    if size != want:
        state = "truncated" if size < want else "longer than its header says"
        raise PriorError(f"{path}: {state}: {size} bytes, expected {want}; {hint}")
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)


def _check_table(table: np.ndarray, path: Path, tif: Path, digest: str, sums: tuple[np.ndarray, np.ndarray], hint: str) -> None:
    """PriorError unless ``table`` is finite, zero-padded, hashes to ``digest`` (what GeoTIFF ``tif``
    records of its build) and its last row and column are the running totals of ``sums`` (the column and row
    sums of the cell mass of r or r^2)."""
    h = table_hash()
    step = max(1, SCAN_ROWS_BYTES // table[0].nbytes)
    for r in range(0, table.shape[0], step):
        chunk = np.ascontiguousarray(table[r : r + step])
        if not np.isfinite(chunk).all():
            bad = np.argwhere(~np.isfinite(chunk))[0]
            raise PriorError(f"{path}: NaN or infinite table entry at row {r + bad[0]}, col {bad[1]}; {hint}")
        h.update(chunk)
    if table[0].any() or table[:, 0].any():
        raise PriorError(f"{path}: first row and column of a padded summed-area table must be zero; {hint}")
    if h.hexdigest() != digest:
        raise PriorError(
            f"{path}: not the table of the build {tif.name} records (checksum differs): the prior set is "
            f"mixed from two builds or damaged; {hint}"
        )
    scale = DENSITY_TOL * max(float(table[-1, -1]), np.finfo(float).tiny)
    for line, totals in zip(sums, (table[-1, 1:], table[1:, -1]), strict=True):
        off = float(np.abs(np.cumsum(line) - totals).max())
        if not off <= scale:
            raise PriorError(f"{path}: table totals differ from the density's by {off:.3g} (tolerance {scale:.3g}); {hint}")


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
def table_rows(density, cell_area, above, above2, sat, sat2):
    """Rows of the padded summed-area tables of density*cell_area and density^2*cell_area for a float64
    band of ``density`` rows (``sat``/``sat2`` are (rows, W+1), column 0 zero) under the table rows
    ``above``/``above2`` (zeros for the first band): one pass, no temporaries. Bands with the previous
    band's last rows give tables bit-identical to one call over the whole grid."""
    h, w = density.shape
    for i in range(h):
        sat[i, 0] = 0.0
        sat2[i, 0] = 0.0
        row = 0.0
        row2 = 0.0
        for j in range(w):
            d = density[i, j]
            row += d * cell_area
            row2 += d * d * cell_area
            if i == 0:
                sat[i, j + 1] = above[j + 1] + row
                sat2[i, j + 1] = above2[j + 1] + row2
            else:
                sat[i, j + 1] = sat[i - 1, j + 1] + row
                sat2[i, j + 1] = sat2[i - 1, j + 1] + row2


@nb.njit(cache=True)
def density_table_rows(r, total, cell_area, above, above2, density, sat, sat2):
    """density = r / total for a band of rows, and the matching rows of the tables (:func:`table_rows`) of
    that float64 quotient, also when ``density`` is float32 (it rounds as ``astype`` does): the tables
    of an in-memory prior, whose float64 density is this quotient, are the same numbers."""
    h, w = r.shape
    d = np.empty((1, w))
    for i in range(h):
        for j in range(w):
            d[0, j] = r[i, j] / total
            density[i, j] = d[0, j]
        if i == 0:
            table_rows(d, cell_area, above, above2, sat[0:1], sat2[0:1])
        else:
            table_rows(d, cell_area, sat[i - 1], sat2[i - 1], sat[i : i + 1], sat2[i : i + 1])


class TerrainPrior:
    """A prior density r(x) per m^2 on a grid, zero outside it, integrating to 1 over the grid.

    Attributes: ``grid`` (Grid), ``density`` ((H, W) per m^2), ``sat`` and ``sat2`` (padded
    summed-area tables of the per-cell mass of r and of r^2), ``model`` (dict describing how it was built).
    Without tables (``sat`` and ``sat2`` None: a float64 density, as :meth:`from_array` makes), they are
    made on first use, and :meth:`write` streams them strip by strip instead: a prior built to be written
    never holds its two grid-size float64 tables.
    """

    def __init__(
        self,
        grid: Grid,
        density: np.ndarray,
        sat: np.ndarray | None,
        sat2: np.ndarray | None,
        model: dict | None = None,
    ) -> None:
        if density.shape != grid.shape:
            raise PriorError(f"density shape {density.shape} does not match grid {grid.shape}")
        if (sat is None) != (sat2 is None):
            raise PriorError("summed-area tables: give both sat and sat2, or neither (made from the density)")
        if sat is None and density.dtype != np.float64:  # tables from a rounded density would not be the build's
            raise PriorError(f"a prior without tables needs a float64 density, got {density.dtype}")
        if sat is not None:
            expected = (grid.height + 1, grid.width + 1)
            if sat.shape != expected or sat2.shape != expected:
                raise PriorError(f"summed-area tables must be {expected}, got {sat.shape}, {sat2.shape}")
            if sat.dtype != np.float64 or sat2.dtype != np.float64:  # float32 sums lose small rectangles' mass
                raise PriorError(f"summed-area tables must be float64, got {sat.dtype}, {sat2.dtype}")
        self.grid = grid
        self.density = density
        self._tables = None if sat is None else (sat, sat2)
        self.model = dict(model or {})

    @property
    def sat(self) -> np.ndarray:
        """Padded (H+1, W+1) float64 summed-area table of the per-cell mass of r (probability)."""
        return self._made_tables()[0]

    @property
    def sat2(self) -> np.ndarray:
        """Padded (H+1, W+1) float64 summed-area table of the per-cell mass of r^2 (per m^2)."""
        return self._made_tables()[1]

    def _made_tables(self) -> tuple[np.ndarray, np.ndarray]:
        if self._tables is None:
            sat = np.empty((self.grid.height + 1, self.grid.width + 1))
            sat2 = np.empty_like(sat)
            sat[0], sat2[0] = 0.0, 0.0
            table_rows(self.density, self.grid.cell_area, sat[0], sat2[0], sat[1:], sat2[1:])
            self._tables = (sat, sat2)
        return self._tables

    def _table_strips(self, rows: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(density, sat, sat2) bands of ``rows`` rows from the top (tables without the zero top row);
        tables not made yet are made band by band into two reused buffers."""
        h, w = self.grid.shape
        if self._tables is not None:
            sat, sat2 = self._tables
            for r in range(0, h, rows):
                yield self.density[r : r + rows], sat[r + 1 : r + 1 + rows], sat2[r + 1 : r + 1 + rows]
            return
        block, block2 = np.zeros((rows + 1, w + 1)), np.zeros((rows + 1, w + 1))  # row 0: the table row above
        for r in range(0, h, rows):
            n = min(rows, h - r)
            table_rows(self.density[r : r + n], self.grid.cell_area, block[0], block2[0], block[1 : n + 1], block2[1 : n + 1])
            yield self.density[r : r + n], block[1 : n + 1], block2[1 : n + 1]
            block[0], block2[0] = block[n], block2[n]

    @property
    def max_density(self) -> float:
        """The largest cell value of r, per m² (a windowed density knows it from its reading pass)."""
        top = getattr(self.density, "max", None)
        if isinstance(top, float):
            return top
        if not hasattr(self, "_max_density"):
            self._max_density = float(np.max(self.density))
        return self._max_density

    @classmethod
    def from_array(cls, r: np.ndarray, grid: Grid, model: dict | None = None, reuse: bool = False) -> TerrainPrior:
        """Normalise a non-negative (H, W) array of relative likelihoods into a density per m^2; with
        ``reuse`` a C-contiguous float64 ``r`` is overwritten by the density (no second grid-size array)."""
        r = np.asarray(r, dtype=np.float64)
        if r.shape != grid.shape:
            raise PriorError(f"likelihood array shape {r.shape} does not match grid {grid.shape}")
        # min/max first (NaN propagates): no full-size temporaries unless something is wrong
        if not (r.min() >= 0 and np.isfinite(r.max())):
            raise PriorError(f"likelihood must be finite and >= 0; {_bad_cells(~np.isfinite(r) | (r < 0))}")
        total = float(r.sum()) * grid.cell_area
        if not total > 0:
            raise PriorError(
                "the likelihood table makes r zero everywhere on the grid; check for structural zeros covering the region"
            )
        r = np.ascontiguousarray(r)
        density = np.divide(r, total, out=r if reuse else None)  # the quotient density_table_rows takes
        return cls(grid, density, None, None, model)

    @classmethod
    def uniform(cls, grid: Grid) -> TerrainPrior:
        """The uniform density over the grid (1 / grid area)."""
        return cls.from_array(np.ones(grid.shape), grid, {"uniform": True})

    def write(self, path: str | Path) -> Path:
        """Write the GeoTIFF and its summed-area tables atomically (:func:`pipeline.prior.write.write_prior`);
        returns the GeoTIFF path."""
        return write_prior(path, self.grid, self.model, self._table_strips(BLOCK))

    @classmethod
    def read(cls, path: str | Path, windowed: bool | None = None) -> TerrainPrior:
        """Load a prior written by :meth:`write` (tables memory-mapped; the density in memory, or read
        window by window (:class:`~pipeline.prior.windowed.WindowedDensity`) when ``windowed``, by default
        for grids above :data:`~pipeline.prior.windowed.WINDOWED_CELLS` cells), after checking it is one: the
        GeoTIFF's prior tags, a finite non-negative density integrating to 1, and two complete float64
        tables that hash to the checksums its build recorded and total up to its density. Anything else
        (a plain GeoTIFF, a set mixed from two builds, a damaged or foreign table) is a PriorError naming
        the file and how to rebuild."""
        path = Path(path)
        sat_p, sat2_p = sat_paths(path)
        for p in (path, sat_p, sat2_p):
            if not p.exists():
                raise PriorError(
                    f"{p}: missing; a prior is prior.tif plus prior.sat.npy and prior.sat2.npy beside it; "
                    f"{_rebuild_hint(path, {})}"
                )
        grid, density, model, digests, hint, sums = _read_geotiff(path, windowed)
        shape = (grid.height + 1, grid.width + 1)
        tables = [_read_table(p, shape, hint) for p in (sat_p, sat2_p)]
        for table, p, digest, line_sums in zip(tables, (sat_p, sat2_p), digests, sums, strict=True):
            _check_table(table, p, path, digest, line_sums, hint)
        return cls(grid, density, *tables, model)

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
