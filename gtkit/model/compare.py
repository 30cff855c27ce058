"""Two models of one site compared: their DSMs on one grid and the height difference A - B as a
GeoTIFF (``gtkit model compare``). Either model may be a mesh (with its offset sidecar) or a
LAS/LAZ/PLY point cloud in the project CRS; by default A is the built model, B the delivered one.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..export.geotiff import write_geotiff
from ..export.grid import Grid, nice_resolution
from ..export.sources import load_surface
from ..export.surface import rasterize_surface
from ..project import Project

NODATA = -9999.0


def default_models(project: Project) -> tuple[Path, Path]:
    P = project.paths
    rec = project.config.get("model", {})
    built = P.root / rec["built"] if rec.get("built") else None
    if built is None or not built.is_file():
        raise GtkitError("no built model recorded in project.toml: run `gtkit model build` first", P.project_toml)
    for cand in (P.model / "delivered" / "reference.obj", P.model / "reference.obj"):
        if cand.is_file() and cand.resolve() != built.resolve():
            return built, cand
    raise GtkitError("no delivered model to compare with (expected model/reference.obj or model/delivered/); "
                     "give --b", P.model)


def height_difference(project: Project, a: Path, b: Path, resolution: float | None = None):
    """(A - B heights on a common grid (NaN where either is empty), grid)."""
    sa, _ = load_surface(a, project.frame, textures=False)
    sb, _ = load_surface(b, project.frame, textures=False)
    ba, bb = sa.bounds(), sb.bounds()
    lo, hi = np.maximum(ba[0], bb[0]), np.minimum(ba[1], bb[1])
    if np.any(hi[:2] <= lo[:2]):
        raise GtkitError(f"the models do not overlap ({a.name} and {b.name})", a)
    res = resolution or nice_resolution(2 * max(sa.detail(), sb.detail()))
    grid = Grid.covering(lo[0], lo[1], hi[0], hi[1], res, project.frame.origin)
    ha = rasterize_surface(sa, grid).height.astype(np.float64)
    hb = rasterize_surface(sb, grid).height.astype(np.float64)
    return ha - hb, grid


def run(project: Project | str | Path, a=None, b=None, resolution: float | None = None, out=None) -> dict:
    project = project if isinstance(project, Project) else Project.load(project)
    da, db = default_models(project) if a is None or b is None else (None, None)
    a = Path(a) if a is not None else da
    b = Path(b) if b is not None else db
    diff, grid = height_difference(project, a, b, resolution)
    out = Path(out) if out is not None else project.paths.exports / "model_diff.tif"
    ok = np.isfinite(diff)
    if not ok.any():
        raise GtkitError("the two models share no cell with a height", a)
    write_geotiff(out, np.where(ok, diff, NODATA).astype(np.float32), grid, project.frame.crs, project.frame.origin,
                  nodata=NODATA, band_names=["height_difference"],
                  tags={"GTKIT_PRODUCT": f"height difference A - B (metres); A = {a}, B = {b}"})
    d = diff[ok]
    return {"out": str(out), "a": str(a), "b": str(b), "resolution": grid.res, "cells": int(ok.sum()),
            "median": float(np.median(d)), "median_abs": float(np.median(np.abs(d))),
            "p95_abs": float(np.percentile(np.abs(d), 95))}
