"""``gtkit import model|poses DIR SOURCE``: bring a delivered reference model or existing poses into
a project (see :mod:`gtkit.imports`); what was imported and from where goes into project.toml."""
from __future__ import annotations

import argparse


def _offset(text: str):
    vals = [float(v) for v in text.replace(",", " ").split()]
    if len(vals) == 2:
        vals.append(0.0)
    if len(vals) != 3:
        raise argparse.ArgumentTypeError("--offset needs 'x,y[,z]'")
    return tuple(vals)


def register(sub):
    p = sub.add_parser("import", help="import a reference model or existing poses into a project")
    ss = p.add_subparsers(dest="import_what", metavar="WHAT")
    m = ss.add_parser("model", help="tiled OBJ (metadata.xml), ODM project, OBJ/PLY/GLB, or LAS/LAZ/PLY points")
    m.add_argument("dir", help="project folder")
    m.add_argument("source")
    m.add_argument("--crs", help="CRS of a file that states none (EPSG:n or WKT)")
    m.add_argument("--offset", type=_offset, help="x,y[,z] added to stored coordinates to give CRS coordinates")
    m.add_argument("--no-copy", action="store_true", help="do not write single meshes/point clouds into model/")
    m.add_argument("--overwrite", action="store_true", help="replace an existing model/reference.obj")
    m.set_defaults(func=run_model)
    q = ss.add_parser("poses", help="BlocksExchange XML/XMLZ, COLMAP model folder, kapture folder, or hloc pose "
                      "file (what 'gtkit export dataset' writes reads back)")
    q.add_argument("dir", help="project folder")
    q.add_argument("source")
    q.add_argument("--intrinsics", help="intrinsics file for an hloc/UAVD4L pose file (default: "
                   "queries_with_intrinsics.txt beside it, else cameras.txt)")
    q.add_argument("--drop-k3", action="store_true", help="BlocksExchange: ignore a non-zero K3")
    q.add_argument("--text", action="store_true", help="write the COLMAP export as text instead of binary")
    q.set_defaults(func=run_poses)
    p.set_defaults(func=lambda args: p.print_help() or 2)


def run_model(args):
    from ..imports import ModelImportSettings, import_model

    info = import_model(args.dir, args.source, ModelImportSettings(
        crs=args.crs, offset=args.offset, copy=not args.no_copy, overwrite=args.overwrite))
    lo, hi = info["bounds_world"]
    what = {"tiled": f"{info.get('n_tiles')} tiles", "points": f"{info.get('n_points')} points"}.get(
        info["format"], f"{info.get('n_triangles')} triangles")
    print(f"imported {info['format']} model: {what}; world bounds x {lo[0]:.1f}..{hi[0]:.1f} "
          f"y {lo[1]:.1f}..{hi[1]:.1f} z {lo[2]:.1f}..{hi[2]:.1f}"
          + (f"; written to {info['copied_to']}" if info.get("copied_to") else ""))
    from ..project import Project
    from ..view.model import prepare_cache

    print(prepare_cache(Project.load(args.dir)))
    return 0


def run_poses(args):
    from ..imports import PoseImportSettings, import_poses

    info = import_poses(args.dir, args.source, PoseImportSettings(
        intrinsics=args.intrinsics, drop_k3=args.drop_k3, colmap_binary=not args.text))
    print(f"imported {info['n_images']} poses ({info['format']}, {info['n_cameras']} cameras"
          f"{', %d photos without a pose skipped' % info['n_skipped'] if info['n_skipped'] else ''}"
          f"{', %d covariances' % info['n_covariances'] if info.get('n_covariances') else ''}) -> "
          f"{info['poses']}, COLMAP model {info['colmap']}")
    return 0
