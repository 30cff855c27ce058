"""A DSM against the true world of a sample site (evaluation code: reads ``truth/``).

The true world mesh (``truth/world.ply``, world frame) is rasterised on the DSM's own grid by the
same code as the DSM export. Cells within ``edge_m`` of a height jump (the true surface changes by
more than ``jump_m`` between neighbouring cells: building outlines, tree crowns) are reported apart.
Completeness: the share of the grid's cells with a true height that the DSM also fills; with
``area_of`` (another DSM, e.g. of the delivered model) also the share of that DSM's filled cells.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..project import Project


def _stats(e: np.ndarray) -> dict:
    if not len(e):
        return {"cells": 0, "median": float("nan"), "p95": float("nan")}
    return {"cells": int(len(e)), "median": float(np.median(e)), "p95": float(np.percentile(e, 95))}


def dsm_vs_truth(project_dir: str | Path, dsm_path: str | Path, edge_m: float = 1.0, jump_m: float = 2.0,
                 area_of: str | Path | None = None) -> dict:
    from scipy.ndimage import binary_dilation, maximum_filter, minimum_filter

    from ..export.dsm import Dsm
    from ..export.surface import MeshSurface, rasterize_surface
    from ..io.mesh import read_mesh_file

    proj = Project.load(project_dir)
    d = Dsm.open(Path(dsm_path), proj.frame)
    world = read_mesh_file(proj.paths.truth / "world.ply")
    truth = rasterize_surface(MeshSurface(world), d.grid).height.astype(np.float64)
    has_truth = np.isfinite(truth)
    ok = np.isfinite(d.heights) & has_truth
    filled = np.where(has_truth, truth, np.nanmin(truth))
    jump = (maximum_filter(filled, size=3) - minimum_filter(filled, size=3)) > jump_m
    r = max(1, int(np.ceil(edge_m / d.resolution)))
    near_edge = binary_dilation(jump, structure=np.ones((2 * r + 1, 2 * r + 1), bool))
    err = np.abs(d.heights - truth)
    out = {"resolution": d.resolution, "completeness": float(ok.sum() / max(has_truth.sum(), 1)),
           "area_m2": float(ok.sum() * d.resolution ** 2),
           "bias": float(np.median((d.heights - truth)[ok])) if ok.any() else float("nan"),
           "all": _stats(err[ok]), "off_edges": _stats(err[ok & ~near_edge]), "near_edges": _stats(err[ok & near_edge])}
    if area_of is not None:
        other = Dsm.open(Path(area_of), proj.frame)
        x, y = d.grid.centres()
        X, Y = np.meshgrid(x, y)
        their = np.isfinite(other.height_at(X, Y)) & has_truth
        out["completeness_of_other_area"] = float((their & ok).sum() / max(their.sum(), 1))
    return out
