"""Gaps of a DSM filled inside the photos' ground footprint, and the areas the fill is judged on.

Where the model has no surface (plain grass, water, shadows: dense matching found nothing there),
the DSM has empty cells. :func:`fill_gaps` fills them from the gap's border (:func:`laplace_fill`):
the plane of the measured cells around the gap plus the harmonic (Laplace) interpolation of their
deviations from it (every filled cell the mean of its four neighbours, the border held fixed). Cells outside the **footprint** (:func:`footprint`, ground that at least
``min_views`` reference photos saw) are never filled and never used: a gap that touches the
footprint's edge or the DSM's border is filled only from the measured cells it touches (no flux
across that edge), so nothing is extrapolated beyond where the photos looked. ``max_distance_m``
(0 = any) leaves cells farther than that from every measured cell empty.

**The area the cameras flew over** (:func:`flown_area`) is the convex hull of the reference
cameras' centres in XY, clipped to the DSM's box: the share of its cells with a height is the
coverage the export reports before and after filling.

Everything is in the world frame of the DSM's :class:`~gtkit.export.grid.Grid`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .grid import Grid

log = logging.getLogger(__name__)

GAPFILL_VERSION = 2        # bump when the fill's method changes (a DSM filled by another version is made again)
DIRECT_MAX = 60_000       # unknowns solved directly (sparse LU); larger gaps go through a coarser grid first
OBJECT_M = 2.0            # measured cells this far above a gap's border plane stand on the ground (trees, roofs)
SKIRT_M = 3.0             # how far from a crown or roof on a gap's border its draped skirt is left out of the fill
SMALL_GAP = 64            # cells: gaps up to this size are filled together, without the border's plane


@dataclass
class Cameras:
    """The reference photos that saw the ground: world-to-camera poses and their cameras."""
    poses: dict            # name -> gtkit.pose.Pose
    cams: dict             # name -> gtkit.camera.Camera

    @property
    def centres(self) -> np.ndarray:
        names = [n for n in sorted(self.poses) if n in self.cams]
        return np.array([self.poses[n].center for n in names]).reshape(-1, 3)


def project_cameras(project) -> Cameras | None:
    """The reference block's registered photos (``work/sfm_reference/poses.txt`` and
    ``intrinsics.txt``), or None when the project has no reference block."""
    from ..io.poses import read_intrinsics, read_poses

    P = project.paths
    if not (P.reference_poses.is_file() and P.reference_intrinsics.is_file()):
        return None
    poses, cams = read_poses(P.reference_poses), read_intrinsics(P.reference_intrinsics)
    cams = {n: c for n, c in cams.items() if n in poses}
    return Cameras(poses, cams) if cams else None


def flown_area(grid: Grid, centres_xy: np.ndarray) -> np.ndarray:
    """Cells whose centre lies inside the convex hull of the camera centres (XY); all False when
    fewer than three centres span an area."""
    from scipy.spatial import Delaunay, QhullError

    xy = np.unique(np.asarray(centres_xy, float)[:, :2], axis=0)
    if len(xy) < 3:
        return np.zeros(grid.shape, bool)
    try:
        tri = Delaunay(xy)
    except QhullError:                       # collinear centres: no area
        return np.zeros(grid.shape, bool)
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc, yc)
    return (tri.find_simplex(np.c_[X.ravel(), Y.ravel()]) >= 0).reshape(grid.shape)


def footprint(grid: Grid, ground: np.ndarray, cameras: Cameras, min_views: int = 2,
              max_cells: int = 1_000_000) -> np.ndarray:
    """Cells whose ground point (``ground``: a height per cell, NaN where unknown) is in front of
    and inside at least ``min_views`` photos. Computed on a grid of at most ``max_cells`` cells
    (every k-th cell) and spread back to the full grid."""
    k = max(1, int(np.ceil(np.sqrt(grid.width * grid.height / max_cells))))
    xc, yc = grid.centres()
    X, Y = np.meshgrid(xc[::k], yc[::k])
    Z = ground[::k, ::k]
    ok = np.isfinite(Z)
    pts = np.c_[X[ok], Y[ok], Z[ok]]
    count = np.zeros(len(pts), np.int32)
    for name in sorted(cameras.cams):
        pose, cam = cameras.poses[name], cameras.cams[name]
        uv, front = cam.project(pose.transform(pts))
        count += (front & cam.in_image(uv)).astype(np.int32)
    seen = np.zeros(X.shape, bool)
    seen[ok] = count >= min_views
    full = np.repeat(np.repeat(seen, k, 0), k, 1)[:grid.height, :grid.width]
    return full


def nearest_fill(height: np.ndarray) -> np.ndarray:
    """Every cell given its nearest measured cell's height (a rough ground for :func:`footprint`)."""
    from scipy.ndimage import distance_transform_edt

    valid = np.isfinite(height)
    if not valid.any():
        return height.copy()
    idx = distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return height[idx[0], idx[1]]


def laplace_fill(height: np.ndarray, unknown: np.ndarray, skirt_cells: int = 0) -> np.ndarray:
    """Heights for the ``unknown`` cells, each 4-connected region of them on its own: the plane
    fitted to the measured cells on the region's border (robustly: cells off it by more than three
    times the median deviation are left out) plus the harmonic interpolation (4-neighbour Laplace
    equation) of the border's deviations from that plane. Border cells that stand well above the
    border next to them (tree crowns, roofs: :func:`_border_plane`) are left out like cells outside
    the footprint; so are measured islands inside the region that stand above its outer border's plane
    (:func:`_standing_islands`: trees in a plain field, whose crowns would lift the field), with their
    skirts up to ``skirt_cells`` away (:func:`_skirts`), and the plane is fitted to the outer border alone. Where the region is enclosed by measured
    cells this is the plain harmonic interpolation of the border (a plane is harmonic); where it
    meets cells that are neither measured nor unknown (outside the footprint, the DSM's edge) no flux
    crosses them, so the border's trend goes on and a sloping gap does not level off. Regions that
    touch no finite cell stay NaN. Returns a copy of ``height`` with the regions filled."""
    from scipy.ndimage import binary_fill_holes, find_objects, label

    h = height.astype(np.float64, copy=True)
    unknown = unknown & ~np.isfinite(h)
    known = np.isfinite(h)
    lab, n = label(unknown)                  # 4-connected regions
    if n == 0:
        return h
    size = np.bincount(lab.ravel(), minlength=n + 1)
    small = size <= SMALL_GAP
    small[0] = False
    if small.any():                          # small holes: all at once, plain harmonic (no trend to speak of)
        touch = np.zeros(n + 1, bool)
        touch[np.unique(lab[unknown & _grow4(known)])] = True
        todo = (small & touch)[lab]
        if todo.any():
            h[todo] = _solve_direct(h, todo, known)[todo]
    for c, sl in enumerate(find_objects(lab), start=1):
        if sl is None or small[c]:
            continue
        r0, r1 = max(sl[0].start - 1, 0), min(sl[0].stop + 1, h.shape[0])
        c0, c1 = max(sl[1].start - 1, 0), min(sl[1].stop + 1, h.shape[1])
        sub_u = lab[r0:r1, c0:c1] == c
        sub_k = known[r0:r1, c0:c1]
        sub_h = h[r0:r1, c0:c1]
        ring = sub_k & _grow4(sub_u)
        if not ring.any():
            continue
        islands = binary_fill_holes(sub_u) & sub_k       # measured cells the gap encloses (trees in a field)
        outer = ring & ~islands
        trend, off = _border_plane(sub_h, outer if outer.sum() >= 6 else ring)
        if islands.any():
            off |= _standing_islands(sub_h - trend, islands)
        if skirt_cells > 0:               # crowns and roofs in the box, whose skirts may line the gap
            standing = off | (sub_k & (sub_h - trend > OBJECT_M))
            if standing.any():
                off |= _skirts(sub_h - trend, sub_k, standing, skirt_cells) & ring
        resid = np.where(sub_k, sub_h - trend, np.nan)
        if (ring & ~off).any():              # objects on the border (trees, roofs): not the gap's ground
            resid[off] = np.nan
            sub_k = sub_k & ~off
        sol = _solve(resid, sub_u, sub_k)
        sub_h[sub_u] = sol[sub_u] + trend[sub_u]
    return h


def _standing_islands(above: np.ndarray, islands: np.ndarray, object_m: float = OBJECT_M) -> np.ndarray:
    """The islands (8-connected groups of measured cells enclosed by a gap) that stand on the ground rather
    than being it: any cell more than ``object_m`` above the gap's border plane (``above``: height minus
    that plane). A tree in a plain field is such an island, crown and skirt together (the surface drapes
    from the crown down to where the gap begins: its lower cells are not the ground either); a textured
    patch of the field itself (a GCP target) is not, and the fill passes through its height."""
    from scipy.ndimage import label, maximum

    lab, n = label(islands, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros(islands.shape, bool)
    top = np.asarray(maximum(above, lab, index=np.arange(1, n + 1)))
    return np.r_[False, top > object_m][lab]


def _skirts(above: np.ndarray, known: np.ndarray, objects: np.ndarray, cells: int, low_m: float = 0.25) -> np.ndarray:
    """The measured cells that fall away from an object (``objects``) toward the gap while still above the
    border plane by more than ``low_m``, within ``cells`` of it: the skirt a surface drapes from a crown or
    a roof down to where its points end, which is not the ground beside it either."""
    from scipy.ndimage import binary_dilation

    up = known & (above > low_m)
    grown = objects & up
    for _ in range(cells):
        nxt = binary_dilation(grown, structure=np.ones((3, 3), bool)) & up
        if np.array_equal(nxt, grown):
            break
        grown = nxt
    return grown


def _grow4(m: np.ndarray) -> np.ndarray:
    out = m.copy()
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        out |= _shift(m, dr, dc)
    return out


def _border_plane(h: np.ndarray, ring: np.ndarray, max_slope: float = 1.0,
                  object_m: float = OBJECT_M) -> tuple[np.ndarray, np.ndarray]:
    """A plane (per cell of ``h``'s box) fitted robustly to ``h`` on the ``ring`` cells (the border's
    majority: a few trees on a field's border do not lift it, a forest's canopy is the canopy; a
    constant, the ring's median, where the ring is too thin to fix a slope or the plane is steeper
    than ``max_slope`` per cell), and the ring cells that stand on that surface rather than being it:
    more than ``object_m`` (or three median deviations) above the plane: tree crowns and roofs at a
    field's border, whose height the ground under the gap should not take."""
    rr, cc = np.nonzero(ring)
    z = h[rr, cc]
    R, C = np.mgrid[0:h.shape[0], 0:h.shape[1]]
    A = np.c_[np.ones(len(z)), rr - rr.mean(), cc - cc.mean()]
    coef = np.array([float(np.median(z)), 0.0, 0.0])
    keep = np.ones(len(z), bool)
    if len(z) >= 6 and np.sqrt(max(np.linalg.eigvalsh(np.cov(A[:, 1:].T)).min(), 0.0)) >= 3.0:
        for _ in range(8):
            c = np.linalg.lstsq(A[keep], z[keep], rcond=None)[0]
            r = z - A @ c
            mad = max(float(np.median(np.abs(r[keep]))), 0.05 / 3)
            # the border's majority, clipped harder above than below: objects stand on the ground, so a
            # border of ground and tree crowns (a plain field lined with trees) settles on the ground
            keep_next = (r <= 1.5 * mad) & (r >= -3.0 * mad)
            if keep_next.sum() < 6:
                break
            keep = keep_next
        else:
            if np.hypot(c[1], c[2]) <= max_slope:
                coef = c
    r = z - A @ coef
    mad = float(np.median(np.abs(r[keep]))) if keep.any() else 0.0
    off = np.zeros(h.shape, bool)
    off[rr, cc] = r > max(object_m, 3.0 * mad)
    return coef[0] + coef[1] * (R - rr.mean()) + coef[2] * (C - cc.mean()), off


def _shift(a: np.ndarray, dr: int, dc: int, fill=False) -> np.ndarray:
    """``out[i, j] = a[i + dr, j + dc]`` (``fill`` outside the array)."""
    out = np.full_like(a, fill)
    H, W = a.shape
    out[max(0, -dr):H - max(0, dr), max(0, -dc):W - max(0, dc)] = a[max(0, dr):H - max(0, -dr) or None,
                                                                    max(0, dc):W - max(0, -dc) or None]
    return out


def _solve(h: np.ndarray, unknown: np.ndarray, known: np.ndarray) -> np.ndarray:
    """The Laplace solution on ``unknown`` (every region of it touches a known cell)."""
    n = int(unknown.sum())
    if n <= DIRECT_MAX:
        return _solve_direct(h, unknown, known)
    # a large gap: solve on a grid twice as coarse, then relax on this one from that start
    H, W = h.shape
    H2, W2 = (H + 1) // 2, (W + 1) // 2
    pad = np.full((H2 * 2, W2 * 2), np.nan)
    pad[:H, :W] = np.where(known, h, np.nan)
    blocks = pad.reshape(H2, 2, W2, 2)
    cnt = np.isfinite(blocks).sum(axis=(1, 3))
    hc = np.where(cnt > 0, np.nansum(blocks, axis=(1, 3)) / np.maximum(cnt, 1), np.nan)
    upad = np.zeros((H2 * 2, W2 * 2), bool)
    upad[:H, :W] = unknown
    uc = upad.reshape(H2, 2, W2, 2).any(axis=(1, 3)) & ~np.isfinite(hc)
    coarse = laplace_fill(hc, uc)
    start = np.repeat(np.repeat(coarse, 2, 0), 2, 1)[:H, :W]
    out = np.where(known, h, np.where(unknown, start, np.nan))
    out[unknown & ~np.isfinite(out)] = np.nanmean(h[known]) if known.any() else 0.0
    return _relax(out, unknown, known | unknown, iterations=200)


def _relax(h: np.ndarray, unknown: np.ndarray, usable: np.ndarray, iterations: int) -> np.ndarray:
    """Jacobi sweeps of the 4-neighbour mean on ``unknown`` (neighbours outside ``usable`` left out)."""
    H, W = h.shape
    P = np.zeros((H + 2, W + 2))
    P[1:-1, 1:-1] = np.where(usable, h, 0.0)
    U = np.zeros((H + 2, W + 2))
    U[1:-1, 1:-1] = usable
    den = U[:-2, 1:-1] + U[2:, 1:-1] + U[1:-1, :-2] + U[1:-1, 2:]
    upd = unknown & (den > 0)
    inner = P[1:-1, 1:-1]
    for _ in range(iterations):
        s = P[:-2, 1:-1] + P[2:, 1:-1] + P[1:-1, :-2] + P[1:-1, 2:]
        inner[upd] = s[upd] / den[upd]
    out = h.copy()
    out[upd] = inner[upd]
    return out


def _solve_direct(h: np.ndarray, unknown: np.ndarray, known: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    H, W = h.shape
    idx = np.full(h.shape, -1, np.int64)
    ui = np.flatnonzero(unknown.ravel())
    idx.ravel()[ui] = np.arange(len(ui))
    r, c = np.divmod(ui, W)
    rows, cols, vals = [], [], []
    diag = np.zeros(len(ui))
    rhs = np.zeros(len(ui))
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        rr, cc = r + dr, c + dc
        inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
        rr, cc = np.where(inside, rr, 0), np.where(inside, cc, 0)
        nb_unknown = inside & unknown[rr, cc]
        nb_known = inside & known[rr, cc]
        diag += nb_unknown | nb_known
        rhs += np.where(nb_known, np.where(nb_known, h[rr, cc], 0.0), 0.0)
        k = np.flatnonzero(nb_unknown)
        rows.append(k)
        cols.append(idx[rr[k], cc[k]])
        vals.append(-np.ones(len(k)))
    rows.append(np.arange(len(ui)))
    cols.append(np.arange(len(ui)))
    vals.append(diag)
    A = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                   shape=(len(ui), len(ui))).tocsc()
    out = h.copy()
    out.ravel()[ui] = spsolve(A, rhs)
    return out


@dataclass
class GapFill:
    height: np.ndarray        # (H, W) float32 world z after filling (NaN = still empty)
    filled: np.ndarray        # (H, W) bool: the cell's height is interpolated, not measured
    flown: np.ndarray         # (H, W) bool: inside the area the cameras flew over
    footprint: np.ndarray | None   # (H, W) bool: ground seen by >= min_views photos (None: no cameras)
    summary: dict             # shares (see :func:`fill_gaps`)


def fill_gaps(height: np.ndarray, grid: Grid, cameras: Cameras | None, *, enabled: bool = True,
              max_distance_m: float = 0.0, min_views: int = 2, measured: np.ndarray | None = None,
              small_holes: int = 0) -> GapFill:
    """Fill the empty cells of ``height`` inside the photos' footprint (see the module doc).

    ``measured``: cells whose height came from the surface itself (default: the finite cells of
    ``height``); other finite cells (e.g. small holes closed before) count as filled too.
    Without ``cameras`` nothing is filled (no footprint is known) and the flown area is empty.
    ``small_holes``: passes of :func:`gtkit.export.surface.fill_small_holes` over what is still
    empty afterwards (outside the footprint, or everything when the gap fill is off).
    The summary holds ``valid_share_flown_before`` / ``_after`` (measured / all finite cells over
    the flown area's cells), ``filled_share`` (filled cells over the DSM's valid cells),
    ``filled_share_flown``, the cell counts, and the settings used."""
    h = height.astype(np.float64, copy=True)
    measured = np.isfinite(h) if measured is None else (measured & np.isfinite(h))
    fp = None
    flown = np.zeros(grid.shape, bool)
    if cameras is not None and len(cameras.cams):
        flown = flown_area(grid, cameras.centres)
        if enabled and np.isfinite(h).any():
            fp = footprint(grid, nearest_fill(h), cameras, min_views)
            unknown = fp & ~np.isfinite(h)
            if max_distance_m > 0:
                from scipy.ndimage import distance_transform_edt

                unknown &= distance_transform_edt(~np.isfinite(h)) * grid.res <= max_distance_m
            h = laplace_fill(h, unknown, skirt_cells=int(np.ceil(SKIRT_M / grid.res)))
    if small_holes > 0:
        from .surface import fill_small_holes

        h, _ = fill_small_holes(h, None, small_holes)
    valid = np.isfinite(h)
    filled = valid & ~measured
    n_flown = int(flown.sum())

    def share(mask, of):
        n = int(of.sum())
        return float((mask & of).sum() / n) if n else None

    summary = {"gap_fill": bool(enabled and fp is not None), "max_distance_m": float(max_distance_m),
               "min_views": int(min_views), "cells": int(h.size), "cells_flown": n_flown,
               "valid_share_flown_before": share(measured, flown), "valid_share_flown_after": share(valid, flown),
               "valid_share_box_before": float(measured.mean()), "valid_share_box_after": float(valid.mean()),
               "filled_cells": int(filled.sum()), "filled_share": float(filled.sum() / max(valid.sum(), 1)),
               "filled_share_flown": share(filled, flown),
               "footprint_share_box": None if fp is None else float(fp.mean()),
               "flown_area": "convex hull of the reference cameras' centres (XY), clipped to the DSM box"
               if cameras is not None else "unknown (no reference block)"}
    return GapFill(h.astype(np.float32), filled, flown, fp, summary)
