"""Where an automatic tie point lies on the reference model: kept only on smooth surface.

The query sequences are flown at another hour than the reference block, under another sun. Where
the surface bends (building edges, roofs' ridges, tree canopies) the shading moves with the sun, and
so does the spot SIFT finds: a match between a query and a reference photo there is off by a
fraction of a pixel, always the same way, and thousands of them pull a whole sequence towards the
query sun (medium sample: every sequence 4-12 cm west). On smooth ground the texture is the
surface's own and does not move with the light.

So an automatic tie is kept only where the model's height grid (the DSM the surveyor exports:
the highest surface per cell) fits a plane within ``max_rms_m`` over a disk of ``radius_m``
around it and the tie lies on that plane (within ``max_off_m``). Measured on medium seed 6 (truth
read only by the report): 10,854 of 15,851 automatic ties kept, median query camera error 0.091 ->
0.039 m (README, issue 17).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError

log = logging.getLogger(__name__)


@dataclass
class SmoothSurfaceSettings:
    enabled: bool = True
    radius_m: float = 2.0          # the disk around a tie over which the model must be a plane
    max_rms_m: float = 0.10        # the model's heights about that plane
    max_off_m: float = 0.30        # the tie's own height off that plane (in the air: a canopy or an edge)
    resolution_m: float = 0.5      # height grid cell (coarsened on large sites, see MAX_GRID_CELLS)
    # "test": per sequence, the ties off smooth surface are dropped only where they are biased: the
    # joint adjustment with all ties and with the smooth ones only differ by more than test_factor x
    # the spread their difference would have if both were unbiased (gtkit.sfm.register.choose_smooth).
    # Measured against truth: on small seeds, dropping them everywhere cost up to 25 mm (the error
    # grows with the sigma), on medium keeping them cost 46-52 mm. "smooth": always drop them.
    choose: str = "test"
    test_factor: float = 2.0
    # what the test compares: "both" (the smooth-only solution is kept only where the two solutions'
    # camera centres AND footprints, the ground point each camera looks at in its frame, moved by
    # more than the limit), "footprint" or "centre" alone (before stop 40: a camera swinging about the
    # ground it sees, a mode the smooth ties alone hold weakly, moves its centre but not its view, and
    # read as bias: small seed 19 seq3 0.025 -> 0.153 m)
    test_on: str = "both"


MAX_GRID_CELLS = 64_000_000       # 8,000 x 8,000 cells: 256 MB of float32 heights


@dataclass
class HeightGrid:
    height: np.ndarray     # (rows, cols) float32 world z, NaN = no surface
    xmin: float
    ymax: float
    res: float


def model_heights(model: Path, frame, settings: SmoothSurfaceSettings) -> HeightGrid:
    """The model's highest surface per cell, drawn top-down (the DSM's rasteriser)."""
    from ..export.dsm import plan_grid
    from ..export.sources import load_surface
    from ..export.surface import rasterize_surface

    src, _ = load_surface(model, frame, textures=False)
    b = src.bounds()
    area = max((b[1, 0] - b[0, 0]) * (b[1, 1] - b[0, 1]), 1.0)
    res = max(settings.resolution_m, math.sqrt(area / MAX_GRID_CELLS))
    plan = plan_grid(src, frame, max(res, src.detail()))
    surf = rasterize_surface(src, plan.grid)
    return HeightGrid(surf.height, plan.grid.xmin, plan.grid.ymax, plan.grid.res)


def on_smooth_surface(xyz: np.ndarray, grid: HeightGrid, settings: SmoothSurfaceSettings) -> np.ndarray:
    """(N,) bool: each point lies on a stretch of model that is a plane over the disk around it."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    H, res = grid.height, grid.res
    k = max(1, int(math.ceil(settings.radius_m / res)))
    oy, ox = np.mgrid[-k:k + 1, -k:k + 1]
    inside = (ox ** 2 + oy ** 2) * res ** 2 <= settings.radius_m ** 2
    ox, oy = ox[inside], oy[inside]
    A = np.c_[ox * res, -oy * res, np.ones(len(ox))]   # plane z = a dx + b dy + c about the cell centre
    col = np.floor((xyz[:, 0] - grid.xmin) / res).astype(np.int64)
    row = np.floor((grid.ymax - xyz[:, 1]) / res).astype(np.int64)
    rr, cc = row[:, None] + oy[None], col[:, None] + ox[None]
    ok = (rr >= 0) & (rr < H.shape[0]) & (cc >= 0) & (cc < H.shape[1])
    z = np.full(rr.shape, np.nan, np.float64)
    z[ok] = H[rr[ok], cc[ok]]
    full = np.isfinite(z).mean(axis=1) >= 0.8     # the disk mostly on the model
    keep = np.zeros(len(xyz), bool)
    idx = np.flatnonzero(full)
    for s in range(0, len(idx), 65_536):             # every point's plane at once, in bounded chunks
        i = idx[s:s + 65_536]
        f = np.isfinite(z[i])
        zi = np.where(f, z[i], 0.0)
        w = f.astype(np.float64)
        M = np.einsum("nj,ja,jb->nab", w, A, A)      # least squares over each disk's finite cells
        coef = np.einsum("nab,nb->na", np.linalg.pinv(M), np.einsum("nj,ja->na", w * zi, A))
        res_z = (coef @ A.T - zi) * w
        rms = np.sqrt((res_z ** 2).sum(axis=1) / w.sum(axis=1))
        cx = grid.xmin + (col[i] + 0.5) * res
        cy = grid.ymax - (row[i] + 0.5) * res
        off = np.abs(xyz[i, 2] - (coef[:, 0] * (xyz[i, 0] - cx) + coef[:, 1] * (xyz[i, 1] - cy) + coef[:, 2]))
        keep[i] = (rms <= settings.max_rms_m) & (off <= settings.max_off_m)
    return keep


def smooth_surface_filter(model: Path | None, frame, settings: SmoothSurfaceSettings):
    """A function ``xyz -> keep mask`` for the project's model, or None (with the reason logged)
    when the filter is off or there is no model yet."""
    if not settings.enabled:
        return None
    if model is None:
        log.info("automatic tie points: no reference model yet, kept wherever they lie (build or import "
                 "one first for ties on smooth surface only)")
        return None
    try:
        grid = model_heights(model, frame, settings)
    except GtkitError as e:
        log.warning("automatic tie points kept wherever they lie: the model's heights could not be drawn (%s)", e)
        return None
    return lambda xyz: on_smooth_surface(xyz, grid, settings)
