"""Export times: DSM, orthophoto, mesh (obj/glb/ply, decimated) and coordinates.

    .venv/bin/python benchmarks/bench_export.py                       # synthetic small + medium, Brighton LAZ
    .venv/bin/python benchmarks/bench_export.py --sample site         # also a sample project (left untouched)

Synthetic projects: the analytic scene of tests/test_export.py (120 x 100 m, 4 buildings,
512^2 texture) and a medium one (1 km x 1 km, 400 buildings, 200 x 200 terrain grid, 4096^2
texture). Prints one table; times are wall seconds on this machine (noisy, shared CPU).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from gtkit.geo import GeoFrame  # noqa: E402
from gtkit.io.mesh import Mesh, MeshPart, write_obj, write_offset_sidecar  # noqa: E402
from gtkit.project import Project  # noqa: E402


def medium_project(root: Path) -> Project:
    """1 km^2: gently rolling terrain (200 x 200 grid, 4096^2 texture) + 400 box buildings."""
    from test_export import _box

    rng = np.random.default_rng(0)
    n, size = 200, 1000.0
    xs, ys = np.meshgrid(np.linspace(0, size, n + 1), np.linspace(0, size, n + 1))
    z = 5 * np.sin(xs / 170) * np.cos(ys / 130)
    V = np.c_[xs.ravel(), ys.ravel(), z.ravel()]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    F = np.concatenate([np.c_[a, a + 1, a + n + 2], np.c_[a, a + n + 2, a + n + 1]])
    tex = (rng.random((4096, 4096, 3)) * 255).astype(np.uint8)
    parts = [MeshPart(V, F, uv=V[:, :2] / size, texture=tex, name="terrain")]
    for k in range(400):
        b = (rng.uniform(30, 970), rng.uniform(30, 970), rng.uniform(5, 15), rng.uniform(5, 15),
             rng.uniform(0, 90), rng.uniform(8, 60))
        bv, bf = _box(b)
        parts.append(MeshPart(bv, bf, colors=np.full((8, 3), 100, np.uint8), name=f"b{k}"))
    frame = GeoFrame("EPSG:32650", (500123.0, 4000456.0, 50.0))
    proj = Project.create(root, frame, "bench-medium")
    off = np.array([500000.0, 4000000.0, 0.0])
    obj = proj.paths.model / "reference.obj"
    write_obj(obj, Mesh(parts).translated(np.asarray(frame.origin) - off))
    write_offset_sidecar(obj, frame.crs_spec, off)
    return proj


class Rows(list):
    """Prints each row as it comes (a slow step still shows the ones before it)."""

    def append(self, r):
        super().append(r)
        name, step, size, t = r
        print(f"{name:<26} {step:<24} {size:<28} {t:8.2f}", flush=True)


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def bench_project(name: str, proj: Project, rows: list):
    from gtkit.export import coordinates, dsm, mesh_export, ortho
    from gtkit.export.dsm import Dsm
    from gtkit.io.mesh import load_model
    from gtkit.project import clear_stage

    for stage in ("export_dsm", "export_ortho", "export_mesh_obj", "export_mesh_glb", "export_mesh_ply",
                  "export_coordinates"):
        clear_stage(proj.paths.stage(stage))
    from gtkit.export.sources import reference_model

    t, mesh = timed(lambda: load_model(reference_model(proj.paths), proj.frame))
    rows.append((name, "load model", f"{mesh.n_triangles} tri", t))
    t, p = timed(lambda: dsm.run(proj, dsm.DsmSettings()))
    d = Dsm.open(p, proj.frame)
    rows.append((name, "dsm (default res)", f"{d.grid.width}x{d.grid.height} @ {d.resolution} m", t))
    t, _ = timed(lambda: dsm.run(proj, dsm.DsmSettings()))
    rows.append((name, "dsm (unchanged: skip)", "", t))
    t, p = timed(lambda: dsm.run(proj, dsm.DsmSettings(cog=True), out=proj.paths.exports / "dsm_cog.tif"))
    rows.append((name, "dsm COG", "", t))
    t, p = timed(lambda: ortho.run(proj, ortho.OrthoSettings()))
    import rasterio

    with rasterio.open(p) as s:
        rows.append((name, "ortho (default res)", f"{s.width}x{s.height} @ {s.transform.a} m", t))
    for fmt in ("obj", "glb", "ply"):
        t, _ = timed(lambda: mesh_export.run(proj, mesh_export.MeshExportSettings(format=fmt)))
        rows.append((name, f"mesh {fmt}", "", t))
    target = max(1000, mesh.n_triangles // 10)
    t, _ = timed(lambda: mesh_export.run(proj, mesh_export.MeshExportSettings(format="obj", decimate=target,
                                                                              name="model_decimated")))
    rows.append((name, "mesh obj decimated", f"-> {target} tri", t))
    poses = proj.paths.truth / "poses.txt"  # benchmark only: any pose file will do
    if poses.is_file():
        t, _ = timed(lambda: coordinates.run(proj, coordinates.CoordinatesSettings(poses=str(poses))))
        rows.append((name, "coords", "truth poses", t))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--project", action="append", default=[], help="an existing project (exports are "
                    "written into it)")
    ap.add_argument("--sample", action="append", default=[], help="a sample project (gtkit sample create), "
                    "left untouched: exports go to a scratch project sharing its model/")
    ap.add_argument("--no-medium", action="store_true")
    args = ap.parse_args()
    print(f"{'project':<26} {'step':<24} {'size':<28} {'seconds':>8}", flush=True)
    rows = Rows()
    with tempfile.TemporaryDirectory(prefix="bench_export_") as tmp:
        from test_export import make_project

        bench_project("synthetic-small", make_project(Path(tmp) / "small"), rows)
        if not args.no_medium:
            t, proj = timed(lambda: medium_project(Path(tmp) / "medium"))
            rows.append(("synthetic-medium", "build + write OBJ", "", t))
            bench_project("synthetic-medium", proj, rows)
        for p in args.project:
            bench_project(Path(p).name, Project.load(p), rows)
        for k, p in enumerate(args.sample):
            from test_export_sample import scratch_project

            proj = scratch_project(p, Path(tmp) / f"sample{k}")
            (proj.paths.root / "truth").symlink_to(Path(p, "truth").resolve(), target_is_directory=True)
            bench_project(f"sample:{Path(p).name}", proj, rows)
        laz = ROOT.parent / "shared" / "data" / "brighton_beach" / "model.laz"
        if laz.is_file():
            from gtkit.export import dsm

            t, out = timed(lambda: dsm.run_file(laz, Path(tmp) / "bb.tif", dsm.DsmSettings()))
            rows.append(("brighton-laz (940k pts)", "dsm (default res)", "", t))


if __name__ == "__main__":
    main()
