"""True orthophoto: every cell coloured by the highest surface at its centre (no building lean), as
an RGB + alpha GeoTIFF on the same kind of grid and georeferencing as the DSM. The default
resolution is the model's texel size (rounded to 1/2/2.5/5 x 10^k); it is never finer than that.

Two ways to colour it (``OrthoSettings.method``):

- ``photos``: the reference photos draped over the DSM (``exports/dsm.tif``, its gaps filled, so the
  orthophoto covers the whole surface), each cell from the photo that sees it most from above, the
  seams between photos blended (per-photo exposure gains, feathering; :mod:`gtkit.export.seams`).
  The record holds ``seam_difference_before`` / ``_after`` (the median colour jump across seams
  without and with blending).
- ``model``: the textured model seen straight down (cells where the model has no surface are empty).

``auto`` (default) takes ``photos`` when the project has a reference block and a DSM and no other
``--input`` is given, else ``model``.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..project import Project, settings_dict
from .dsm import plan_grid
from .geotiff import write_geotiff
from .sources import load_surface, run_raster_stage
from .surface import rasterize_surface

log = logging.getLogger(__name__)

STAGE = "export_ortho"


METHODS = ("auto", "photos", "model")


@dataclass
class OrthoSettings:
    resolution: float | None = None  # metres per cell; None = the model's texel size (rounded up)
    cog: bool = False                # write a cloud-optimised GeoTIFF (internal overviews)
    method: str = "auto"             # auto | photos (reference photos over the filled DSM) | model (see above)
    blend: bool = True               # photos: per-photo exposure gains and feathering along the seams
    feather_m: float = 0.0           # photos: feathering band on each side of a seam (metres); 0 = 8 cells

    def __post_init__(self):
        if self.method not in METHODS:
            raise GtkitError(f"[export_ortho] method must be one of {', '.join(METHODS)}, got {self.method!r}")


def make_photo_ortho(source, frame, out: Path, settings: OrthoSettings, source_name: str, dsm, cameras,
                     images: Path) -> dict:
    """The reference photos over ``dsm`` (a :class:`gtkit.export.dsm.Dsm` in ``frame``), seams
    blended, on the grid the model's detail gives (as ``model``); returns the record's summary."""
    from .seams import mosaic

    plan = plan_grid(source, frame, settings.resolution, default_factor=1.0)
    g = plan.grid
    xc, yc = g.centres()
    X, Y = np.meshgrid(xc, yc)
    heights = np.asarray(dsm.height_at(X, Y), np.float64)
    feather = (int(round(settings.feather_m / g.res)) if settings.feather_m > 0 else 8) if settings.blend else 0
    m = mosaic(g, heights, cameras, images, feather_cells=feather, compensate=settings.blend, feather=settings.blend)
    valid = m.label >= 0
    write_geotiff(out, m.rgb, g, frame.crs, frame.origin, alpha=valid, cog=settings.cog,
                  resampling="average", band_names=["red", "green", "blue", "alpha"],
                  tags={"GTKIT_PRODUCT": "true orthophoto (reference photos over the DSM, seams blended)",
                        "GTKIT_SOURCE": source_name, "GTKIT_ORIGIN": json.dumps(list(frame.origin)),
                        "GTKIT_SETTINGS": json.dumps(settings_dict(settings))})
    s = m.summary
    f = (lambda v: "n/a" if v is None else f"{v:.1f}")
    log.info("orthophoto %s: %d x %d cells at %.4g m from %d photos over the DSM, %.1f%% covered; seam difference "
             "%s before blending, %s after (neighbours within one photo: %s; 0-255)", out, g.width, g.height, g.res,
             s["n_photos_used"], 100 * valid.mean(), f(s["seam_difference_before"]), f(s["seam_difference_after"]),
             f(s["seam_difference_within"]))
    return {"path": str(out), "source": source_name, "method": "photos", "resolution": g.res, "detail": plan.detail,
            "clamped": plan.clamped, "width": g.width, "height": g.height, "dsm": str(dsm.path), **s}


def make_ortho(source, frame, out: Path, settings: OrthoSettings, source_name: str) -> dict:
    plan = plan_grid(source, frame, settings.resolution, default_factor=1.0)
    surf = rasterize_surface(source, plan.grid, with_rgb=True)
    valid = np.isfinite(surf.height)
    write_geotiff(out, surf.rgb, plan.grid, frame.crs, frame.origin, alpha=valid, cog=settings.cog,
                  resampling="average", band_names=["red", "green", "blue", "alpha"],
                  tags={"GTKIT_PRODUCT": "true orthophoto (top-down render of the model)",
                        "GTKIT_SOURCE": source_name, "GTKIT_ORIGIN": json.dumps(list(frame.origin)),
                        "GTKIT_SETTINGS": json.dumps(settings_dict(settings))})
    log.info("orthophoto %s: %d x %d cells at %.4g m, %.1f%% covered", out, plan.grid.width, plan.grid.height,
             plan.grid.res, 100 * valid.mean())
    return {"path": str(out), "source": source_name, "method": "model", "resolution": plan.grid.res,
            "detail": plan.detail, "clamped": plan.clamped, "width": plan.grid.width, "height": plan.grid.height,
            "covered_share": float(valid.mean())}


def choose_method(project: Project, settings: OrthoSettings, input) -> str:
    """``photos`` or ``model`` for this project (``auto``: photos when there is a reference block and a
    DSM and no other input); a one-line error when ``photos`` is asked for and cannot be made."""
    from .gapfill import project_cameras

    P = project.paths
    can = project_cameras(project) is not None and P.dsm.is_file() and input is None
    if settings.method == "photos" and not can:
        why = ("--input draws a given model" if input is not None else "no DSM (run `gtkit export dsm` first)"
               if not P.dsm.is_file() else "no reference block (run `gtkit sfm --block reference` first)")
        raise GtkitError(f"orthophoto from photos: {why}", P.dsm if input is None else Path(input))
    return "photos" if settings.method == "photos" or (settings.method == "auto" and can) else "model"


def run(project: Project | str | Path, settings: OrthoSettings, input: str | Path | None = None,
        crs: str | None = None, offset=None, out: str | Path | None = None) -> Path:
    """The orthophoto stage: the reference photos over the DSM, or the reference model (or ``input``)
    seen from above (see the module doc) -> ``exports/ortho.tif``."""
    proj = project if isinstance(project, Project) else Project.load(project)
    P = proj.paths
    method = choose_method(proj, settings, input)
    if method == "model":
        return run_raster_stage(proj, settings, input, crs, offset, out, default_out=P.ortho, stage=STAGE,
                                make=make_ortho, label="orthophoto")

    def make(source, frame, o, s, name):
        from .dsm import Dsm
        from .gapfill import project_cameras

        return make_photo_ortho(source, frame, o, s, name, Dsm.open(P.dsm, proj.frame), project_cameras(proj),
                                P.images)

    photos = sorted(P.reference_images.glob("*")) if P.reference_images.is_dir() else []
    return run_raster_stage(proj, settings, input, crs, offset, out, default_out=P.ortho, stage=STAGE, make=make,
                            label="orthophoto", textures=False,
                            extra_files=[P.dsm, P.reference_poses, P.reference_intrinsics, *photos])


def run_file(input: str | Path, out: str | Path, settings: OrthoSettings, crs: str | None = None,
             offset=None) -> Path:
    """An orthophoto of a mesh (or coloured point cloud) outside any project, in its own CRS."""
    source, frame = load_surface(input, None, crs, offset)
    make_ortho(source, frame, Path(out), settings, str(input))
    return Path(out)
