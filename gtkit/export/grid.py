"""The raster grid of an export, in the project's world frame.

A :class:`Grid` is ``width`` x ``height`` square cells of ``res`` metres. Row 0 is the
northern edge (``ymax``), column 0 the western edge (``xmin``); cell (i, j) covers
x in [xmin + j*res, xmin + (j+1)*res] and y in [ymax - (i+1)*res, ymax - i*res], and its value
is the surface sampled at the cell centre. Grids made by :meth:`Grid.covering` have their edges
on whole multiples of ``res`` in the *CRS* (not the world frame), so exports of one site with
the same resolution line up cell for cell in a GIS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import GtkitError

MAX_CELLS = 400_000_000  # a hard stop against typos like --resolution 0.0001


@dataclass(frozen=True)
class Grid:
    xmin: float   # world x of the western edge
    ymax: float   # world y of the northern edge
    res: float    # metres per cell
    width: int
    height: int

    @property
    def xmax(self) -> float:
        return self.xmin + self.width * self.res

    @property
    def ymin(self) -> float:
        return self.ymax - self.height * self.res

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    @classmethod
    def covering(cls, xmin: float, ymin: float, xmax: float, ymax: float, res: float,
                 origin=(0.0, 0.0, 0.0)) -> "Grid":
        """The smallest grid of ``res`` cells that covers the world box, snapped in the CRS."""
        if not (res > 0 and math.isfinite(res)):
            raise GtkitError(f"resolution must be a positive number of metres, got {res!r}")
        ox, oy = float(origin[0]), float(origin[1])
        x0 = math.floor((xmin + ox) / res) * res - ox
        y1 = math.ceil((ymax + oy) / res) * res - oy
        w = max(1, int(math.ceil((xmax + ox - (x0 + ox)) / res - 1e-9)))
        h = max(1, int(math.ceil((y1 + oy - (ymin + oy)) / res - 1e-9)))
        if w * h > MAX_CELLS:
            raise GtkitError(f"a {w} x {h} raster at {res} m per cell is too large; choose a coarser --resolution")
        return cls(x0, y1, float(res), w, h)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """World x (columns) and y (rows) of the cell centres, as 1-D arrays."""
        x = self.xmin + (np.arange(self.width) + 0.5) * self.res
        y = self.ymax - (np.arange(self.height) + 0.5) * self.res
        return x, y

    def cell_of(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column and an inside-mask for world points (half-open cells)."""
        j = np.floor((np.asarray(x, float) - self.xmin) / self.res).astype(np.int64)
        i = np.floor((self.ymax - np.asarray(y, float)) / self.res).astype(np.int64)
        inside = (i >= 0) & (i < self.height) & (j >= 0) & (j < self.width)
        return i, j, inside

    def transform(self, origin=(0.0, 0.0, 0.0)):
        """The rasterio/GDAL affine transform from (col, row) to CRS coordinates."""
        from rasterio.transform import Affine

        # rounded to a micrometre so snapped edges read as the round numbers they are
        return Affine(self.res, 0.0, round(self.xmin + float(origin[0]), 6), 0.0, -self.res,
                      round(self.ymax + float(origin[1]), 6))

    @classmethod
    def from_transform(cls, transform, width: int, height: int, origin=(0.0, 0.0, 0.0)) -> "Grid":
        """The world grid of a north-up raster (square cells), given its CRS transform."""
        a, b, c, d, e, f = (transform.a, transform.b, transform.c, transform.d, transform.e, transform.f)
        if abs(b) > 1e-12 or abs(d) > 1e-12 or e >= 0 or abs(a + e) > 1e-9 * abs(a):
            raise GtkitError("raster is not north-up with square cells")
        return cls(c - float(origin[0]), f - float(origin[1]), float(a), int(width), int(height))


def nice_resolution(res: float) -> float:
    """The smallest of 1, 2, 2.5, 5 x 10^k that is >= ``res`` (easy numbers for a GIS user)."""
    if not (res > 0 and math.isfinite(res)):
        raise GtkitError(f"cannot choose a resolution from {res!r}")
    k = math.floor(math.log10(res))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        v = round(m * 10.0 ** k, 10)
        if v >= res * (1 - 1e-9):
            return v
    return 10.0 ** (k + 1)
