"""True orthophoto: the textured model seen straight down, every cell coloured by the highest
surface at its centre (no building lean), as an RGB + alpha GeoTIFF on the same kind of grid
and georeferencing as the DSM. The default resolution is the model's texel size (rounded to
1/2/2.5/5 x 10^k); it is never finer than that.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..project import Project, settings_dict
from .dsm import plan_grid
from .geotiff import write_geotiff
from .sources import load_surface, run_raster_stage
from .surface import rasterize_surface

log = logging.getLogger(__name__)

STAGE = "export_ortho"


@dataclass
class OrthoSettings:
    resolution: float | None = None  # metres per cell; None = the model's texel size (rounded up)
    cog: bool = False                # write a cloud-optimised GeoTIFF (internal overviews)


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
    return {"path": str(out), "source": source_name, "resolution": plan.grid.res, "detail": plan.detail,
            "clamped": plan.clamped, "width": plan.grid.width, "height": plan.grid.height,
            "covered_share": float(valid.mean())}


def run(project: Project | str | Path, settings: OrthoSettings, input: str | Path | None = None,
        crs: str | None = None, offset=None, out: str | Path | None = None) -> Path:
    """The orthophoto stage: the reference model (or ``input``) -> ``exports/ortho.tif``."""
    proj = project if isinstance(project, Project) else Project.load(project)
    return run_raster_stage(proj, settings, input, crs, offset, out, default_out=proj.paths.ortho, stage=STAGE,
                            make=make_ortho, label="orthophoto")


def run_file(input: str | Path, out: str | Path, settings: OrthoSettings, crs: str | None = None,
             offset=None) -> Path:
    """An orthophoto of a mesh (or coloured point cloud) outside any project, in its own CRS."""
    source, frame = load_surface(input, None, crs, offset)
    make_ortho(source, frame, Path(out), settings, str(input))
    return Path(out)
