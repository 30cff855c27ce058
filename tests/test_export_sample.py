"""The DSM of the sample project's reference model against the TRUE world surface.

Evaluation code (reads truth/): the true world mesh (truth/world.ply, world frame) is rasterised
on the DSM's own grid by the same renderer path, and |DSM - truth| is measured per cell,
over all cells and over "edge" cells (where the true surface jumps by more than 2 m within one
cell's neighbourhood: building outlines, tree crowns).
"""
from __future__ import annotations

import numpy as np

from gtkit.project import Project


def dsm_vs_true_world(sample_root, dsm_path) -> dict:
    """Median / 95th percentile of |DSM - true surface| (metres), all cells and edge cells."""
    from scipy.ndimage import maximum_filter, minimum_filter

    from gtkit.export.dsm import Dsm
    from gtkit.export.surface import MeshSurface, rasterize_surface
    from gtkit.io.mesh import read_mesh_file

    proj = Project.load(sample_root)
    d = Dsm.open(dsm_path, proj.frame)
    world = read_mesh_file(proj.paths.truth / "world.ply")  # world frame, no offset
    truth = rasterize_surface(MeshSurface(world), d.grid).height.astype(np.float64)
    ok = np.isfinite(d.heights) & np.isfinite(truth)
    filled = np.where(np.isfinite(truth), truth, np.nanmin(truth))
    jump = maximum_filter(filled, size=3) - minimum_filter(filled, size=3)
    edge = ok & (jump > 2.0)
    err = np.abs(d.heights - truth)
    return {"resolution": d.resolution, "cells": int(ok.sum()), "coverage": float(ok.sum() / np.isfinite(truth).sum()),
            "median": float(np.median(err[ok])), "p95": float(np.percentile(err[ok], 95)),
            "edge_cells": int(edge.sum()), "edge_median": float(np.median(err[edge])) if edge.any() else float("nan"),
            "edge_p95": float(np.percentile(err[edge], 95)) if edge.any() else float("nan"),
            "bias": float(np.median((d.heights - truth)[ok]))}


def scratch_project(sample_root, tmp_path) -> Project:
    """A project beside the read-only sample that shares its model/ (exports go to tmp)."""
    src = Project.load(sample_root)
    proj = Project.create(tmp_path / "site", src.frame, "sample-export")
    (proj.paths.root / "model").symlink_to(src.paths.model.resolve(), target_is_directory=True)
    return proj


def test_sample_dsm_matches_the_true_world(small_sample, tmp_path):
    import rasterio

    from gtkit.export import dsm

    proj = scratch_project(small_sample, tmp_path)
    out = dsm.run(proj, dsm.DsmSettings())
    with rasterio.open(out) as src:
        assert src.crs == rasterio.crs.CRS.from_user_input(proj.frame.crs_spec)
        assert src.transform.a == -src.transform.e and src.transform.b == 0 == src.transform.d
    m = dsm_vs_true_world(small_sample, out)
    print("sample small DSM vs true world:", {k: round(v, 4) if isinstance(v, float) else v for k, v in m.items()})
    # the reference model is the world decimated with a few cm of noise (see gtkit.synth.refmodel)
    assert m["coverage"] > 0.98
    assert m["median"] < 0.05 and m["p95"] < 0.5
