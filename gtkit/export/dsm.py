"""Digital Surface Model: the highest surface per cell, as a GeoTIFF, and the reader
(:class:`Dsm`) that the localization and tracking stages use.

Writing (``gtkit export dsm``)::

    run(project, DsmSettings())                      # model/reference.obj -> exports/dsm.tif
    run_file("model.laz", "dsm.tif", DsmSettings())  # a file outside a project (its own CRS)

Meshes and point clouds share one code path: :func:`gtkit.export.surface.rasterize_surface`
on a :class:`gtkit.export.grid.Grid`, then :func:`gtkit.export.geotiff.write_geotiff`. A DSM
needs no colours: an OBJ is read as its triangles without decoding its textures and drawn a
million triangles at a time, a tiled model a tile at a time (the heights are those of the whole
textured model drawn at once; memory: the OBJ's geometry, or one tile).
Heights in the file are CRS heights (world z + the project origin's z), exactly as the model
states them (for DJI/GPS data usually ellipsoidal; gtkit never changes the vertical datum).

Reading::

    dsm = Dsm.open(project.paths.dsm, project.frame)   # heights in the world frame
    dsm = Dsm.for_project("site")                      # the same
    z = dsm.height_at(x, y)                            # bilinear, NaN outside / where empty
    hit = dsm.intersect_ray(origin, direction)         # first crossing of a ray with the surface
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..geo import GeoFrame, crs_name
from ..project import Project, settings_dict
from .geotiff import write_geotiff
from .grid import Grid, nice_resolution
from .sources import load_surface, run_raster_stage
from .gapfill import GAPFILL_VERSION, Cameras, fill_gaps, project_cameras
from .surface import MeshSurface, ObjMeshSurface, PointSurface, SurfaceRaster, TiledSurface, rasterize_surface

log = logging.getLogger(__name__)

STAGE = "export_dsm"
HEIGHT_NOTE = "CRS heights as the source states them (e.g. ellipsoidal from GPS); not converted"
MAX_DEFAULT_CELLS = 25_000_000


@dataclass
class DsmSettings:
    resolution: float | None = None  # metres per cell; None = 2 x the source's detail, rounded to 1/2/2.5/5 x 10^k
    cog: bool = False                # write a cloud-optimised GeoTIFF (internal overviews)
    fill_holes: int = 2              # passes of small-hole filling (empty cells with >= 5 of 8 filled neighbours),
                                     # after the gap fill (so: outside the footprint, or all with gap_fill off)
    nodata: float = -9999.0          # value of empty cells in the file (read back as NaN by Dsm)
    # gaps (no surface: plain grass, water) filled by harmonic interpolation from their border, only
    # inside the ground the reference photos saw (gtkit.export.gapfill); filled cells are 1 in band 2
    gap_fill: bool = True
    gap_fill_max_m: float = 0.0      # leave cells farther than this from a measured cell empty (0 = any)
    footprint_views: int = 2         # ground counts as seen when it is inside >= this many reference photos


@dataclass
class RasterPlan:
    grid: Grid
    detail: float        # the source's finest ground detail (metres)
    clamped: bool        # the requested resolution was finer than the detail


def plan_grid(source: MeshSurface | ObjMeshSurface | TiledSurface | PointSurface, frame: GeoFrame,
              resolution: float | None, default_factor: float = 2.0) -> RasterPlan:
    """Choose the grid: a default from the source's detail, never finer than that detail."""
    detail = source.detail()
    b = source.bounds()
    area = max((b[1, 0] - b[0, 0]) * (b[1, 1] - b[0, 1]), 1e-6)
    floor_res = nice_resolution(detail)
    clamped = False
    if resolution is None:
        res = nice_resolution(max(default_factor * detail, math.sqrt(area / MAX_DEFAULT_CELLS)))
    elif resolution < detail * (1 - 1e-6):
        log.warning("resolution %.4g m is finer than the source's detail (%.4g m); using %.4g m",
                    resolution, detail, floor_res)
        res, clamped = floor_res, True
    else:
        res = float(resolution)
    grid = Grid.covering(b[0, 0], b[0, 1], b[1, 0], b[1, 1], res, frame.origin)
    return RasterPlan(grid, detail, clamped)


FILLED_NOTE = ("band 2 'filled': 1 where the height is interpolated from the gap's border (no surface was "
               "measured there), 0 where measured, nodata where band 1 is empty")


def write_dsm(path: Path, surf: SurfaceRaster, frame: GeoFrame, settings: DsmSettings, tags: dict,
              filled: np.ndarray | None = None) -> Path:
    """Write heights (world z -> CRS heights) as a float32 GeoTIFF with nodata; band 2 ``filled``
    (1 = interpolated, 0 = measured) when ``filled`` is given."""
    z = surf.height.astype(np.float64) + frame.origin[2]
    ok = np.isfinite(z)
    data = np.where(ok, z, settings.nodata).astype(np.float32)
    names = ["height"]
    if filled is not None:
        mask = np.where(ok, filled.astype(np.float32), settings.nodata).astype(np.float32)
        data = np.stack([data, mask], axis=-1)
        names.append("filled")
        tags = {"GTKIT_FILLED": FILLED_NOTE, **tags}
    return write_geotiff(path, data, surf.grid, frame.crs, frame.origin, nodata=settings.nodata,
                         cog=settings.cog, band_names=names, tags={
                             "GTKIT_PRODUCT": "DSM (highest surface per cell, sampled at cell centres)",
                             "GTKIT_UNITS": "metre", "GTKIT_HEIGHTS": HEIGHT_NOTE,
                             "GTKIT_ORIGIN": json.dumps(list(frame.origin)), **tags})


def make_dsm(source, frame: GeoFrame, out: Path, settings: DsmSettings, source_name: str,
             cameras: Cameras | None = None) -> dict:
    """Rasterise ``source``, close small holes, fill the gaps inside the footprint of ``cameras``
    (the reference photos; None: no gap fill) and write the DSM; returns a summary (grid, detail,
    coverage before and after filling, the share filled)."""
    plan = plan_grid(source, frame, settings.resolution)
    surf = rasterize_surface(source, plan.grid)
    gf = fill_gaps(surf.height, plan.grid, cameras, enabled=settings.gap_fill, max_distance_m=settings.gap_fill_max_m,
                   min_views=settings.footprint_views, small_holes=settings.fill_holes)
    surf.height = gf.height
    write_dsm(out, surf, frame, settings, {"GTKIT_SOURCE": source_name,
                                           "GTKIT_SETTINGS": json.dumps(settings_dict(settings))}, filled=gf.filled)
    valid = np.isfinite(surf.height)
    summary = {"path": str(out), "source": source_name, "kind": source.kind, "crs": crs_name(frame.crs),
               "resolution": plan.grid.res, "detail": plan.detail, "clamped": plan.clamped,
               "width": plan.grid.width, "height": plan.grid.height, "valid_share": float(valid.mean()),
               **gf.summary}
    fs = gf.summary
    pct = (lambda v: "n/a" if v is None else f"{100 * v:.1f}%")
    log.info("DSM %s: %d x %d cells at %.4g m (%s, detail %.3g m), %.1f%% of the box valid; inside the flown area "
             "(%s) %s valid as measured, %s after filling; %d cells filled (%s of the valid cells)%s", out,
             plan.grid.width, plan.grid.height, plan.grid.res, source.kind, plan.detail, 100 * valid.mean(),
             fs["flown_area"], pct(fs["valid_share_flown_before"]), pct(fs["valid_share_flown_after"]),
             fs["filled_cells"], pct(fs["filled_share"]),
             "" if fs["gap_fill"] else " (gap fill off" + ("" if settings.gap_fill else " by setting")
             + ("; no reference block: footprint unknown" if cameras is None else "") + ")")
    return summary


def run(project: Project | str | Path, settings: DsmSettings, input: str | Path | None = None,
        crs: str | None = None, offset=None, out: str | Path | None = None) -> Path:
    """The DSM stage of a project: the reference model (or ``input``) -> ``exports/dsm.tif``.
    Skips when the output exists and settings and inputs are unchanged."""
    proj = project if isinstance(project, Project) else Project.load(project)
    P = proj.paths
    cams = [P.reference_poses, P.reference_intrinsics] if settings.gap_fill else []

    def make(source, frame, out, s, name):
        return make_dsm(source, frame, out, s, name, cameras=project_cameras(proj) if s.gap_fill else None)

    return run_raster_stage(proj, settings, input, crs, offset, out, default_out=P.dsm, stage=STAGE,
                            make=make, label="DSM", textures=False, extra_files=cams,
                            version=f"gapfill {GAPFILL_VERSION}" if settings.gap_fill else None)


def run_file(input: str | Path, out: str | Path, settings: DsmSettings, crs: str | None = None,
             offset=None) -> Path:
    """A DSM of a mesh or point cloud outside any project, in the file's own CRS."""
    source, frame = load_surface(input, None, crs, offset, textures=False)
    make_dsm(source, frame, Path(out), settings, str(input))
    return Path(out)


# --- reading --------------------------------------------------------------------------------


class Dsm:
    """A DSM in a world frame: ``heights[i, j]`` is the surface at the centre of cell (i, j) of
    ``grid`` (world z; NaN where empty). Open one with :meth:`open`."""

    def __init__(self, heights: np.ndarray, grid: Grid, frame: GeoFrame, path: Path | None = None,
                 filled: np.ndarray | None = None):
        if heights.shape != grid.shape:
            raise GtkitError(f"heights {heights.shape} do not match the grid {grid.shape}", path)
        self.heights = heights
        self.grid = grid
        self.frame = frame
        self.path = path
        # True where the height was interpolated over a gap (the file's band 'filled'); all False
        # for a DSM without that band
        self.filled = np.zeros(grid.shape, bool) if filled is None else np.asarray(filled, bool)

    @classmethod
    def open(cls, path: str | Path, frame: GeoFrame | None = None) -> "Dsm":
        """Read a DSM GeoTIFF. With ``frame`` (the project's), the file's CRS must equal the
        frame's and coordinates/heights are in that world frame; without, the world frame is
        the file's CRS itself (origin 0)."""
        import rasterio

        path = Path(path)
        if not path.is_file():
            raise GtkitError("DSM not found (run `gtkit export dsm` first)", path)
        try:
            with rasterio.open(path) as src:
                if src.crs is None:
                    raise GtkitError("DSM has no CRS", path)
                a = src.read(1).astype(np.float64)
                filled = None
                if src.count >= 2 and (src.descriptions[1] or "") == "filled":
                    f = src.read(2)
                    filled = (f == 1) & (f != src.nodata)
                nodata = src.nodata
                transform, w, h = src.transform, src.width, src.height
                file_crs = src.crs.to_wkt()
        except rasterio.errors.RasterioIOError as e:
            raise GtkitError(f"not a readable GeoTIFF ({e})", path) from None
        from ..geo import parse_crs

        fcrs = parse_crs(file_crs, path)
        if frame is None:
            frame = GeoFrame(crs_name(fcrs), (0.0, 0.0, 0.0), source=str(path))
        elif not fcrs.equals(frame.crs):
            raise GtkitError(f"DSM CRS {crs_name(fcrs)} does not match the project CRS {frame.crs_spec}", path)
        if nodata is not None:
            a[a == nodata] = np.nan
        a[~np.isfinite(a)] = np.nan
        grid = Grid.from_transform(transform, w, h, frame.origin)
        return cls(a - frame.origin[2], grid, frame, path, filled=None if filled is None else filled & np.isfinite(a))

    @classmethod
    def for_project(cls, project: Project | str | Path) -> "Dsm":
        """The project's ``exports/dsm.tif`` in its world frame."""
        proj = project if isinstance(project, Project) else Project.load(project)
        return cls.open(proj.paths.dsm, proj.frame)

    @property
    def resolution(self) -> float:
        return self.grid.res

    def filled_at(self, x, y) -> np.ndarray:
        """Whether the cell that holds world (x, y) has an interpolated (filled) height; False
        outside the raster."""
        i, j, inside = self.grid.cell_of(np.atleast_1d(x), np.atleast_1d(y))
        out = np.zeros(inside.shape, bool)
        out[inside] = self.filled[i[inside], j[inside]]
        return out if np.ndim(x) or np.ndim(y) else bool(out.ravel()[0])

    def height_at(self, x, y) -> np.ndarray:
        """Bilinear height (world z) at world (x, y) (scalars or arrays) from the cell centres.
        Empty neighbour cells are left out of the weights; NaN outside the raster or where all
        four neighbours are empty. Between the outermost cell centres and the raster's edge the
        edge cells' values are used."""
        g = self.grid
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        inside = (x >= g.xmin) & (x <= g.xmax) & (y >= g.ymin) & (y <= g.ymax)
        fc = np.clip((x - g.xmin) / g.res - 0.5, 0, g.width - 1)
        fr = np.clip((g.ymax - y) / g.res - 0.5, 0, g.height - 1)
        c0 = np.minimum(np.floor(fc).astype(np.int64), max(g.width - 2, 0))
        r0 = np.minimum(np.floor(fr).astype(np.int64), max(g.height - 2, 0))
        tc, tr = fc - c0, fr - r0
        c1, r1 = np.minimum(c0 + 1, g.width - 1), np.minimum(r0 + 1, g.height - 1)
        num = np.zeros(np.broadcast(x, y).shape)
        den = np.zeros_like(num)
        for r, c, w in ((r0, c0, (1 - tr) * (1 - tc)), (r0, c1, (1 - tr) * tc),
                        (r1, c0, tr * (1 - tc)), (r1, c1, tr * tc)):
            v = self.heights[r, c]
            ok = np.isfinite(v) & (w > 0)
            num += np.where(ok, w * np.where(ok, v, 0.0), 0.0)
            den += np.where(ok, w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where((den > 1e-12) & inside, num / np.where(den > 0, den, 1.0), np.nan)
        return z if z.ndim else float(z)

    def intersect_ray(self, origin, direction, max_distance: float | None = None,
                      step: float | None = None) -> np.ndarray | None:
        """First point where the ray ``origin + s * direction`` (world, s >= 0) goes below the
        surface, refined by bisection to ~1 mm; None if it leaves the raster or ``max_distance``
        first. ``step`` defaults to half a cell."""
        o = np.asarray(origin, np.float64)
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        step = step or 0.5 * self.grid.res
        if max_distance is None:
            g = self.grid
            corners = np.array([[g.xmin, g.ymin], [g.xmax, g.ymax]])
            max_distance = float(np.linalg.norm(corners[1] - corners[0])
                                 + np.linalg.norm(o[:2] - corners.mean(0))
                                 + abs(o[2] - np.nanmean(self.heights)) + 1.0)
        s = np.arange(0.0, max_distance + step, step)
        p = o + s[:, None] * d
        f = p[:, 2] - self.height_at(p[:, 0], p[:, 1])
        below = np.flatnonzero(np.isfinite(f) & (f <= 0))
        if not len(below):
            return None
        k = below[0]
        if k == 0:
            return o.copy()
        lo, hi = s[k - 1], s[k]
        if not np.isfinite(f[k - 1]):  # entered the raster between two samples: search from the entry
            lo = hi - step
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            q = o + mid * d
            fm = q[2] - self.height_at(q[0], q[1])
            if np.isfinite(fm) and fm <= 0:
                hi = mid
            else:
                lo = mid
            if hi - lo < 1e-3:
                break
        return o + hi * d
