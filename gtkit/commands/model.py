"""``gtkit model build|compare``: the reference model from the photos (see :mod:`gtkit.model`).

Examples::

    gtkit model build site                      # after `gtkit sfm site --block reference`
    gtkit model build site --depth-method sgbm  # the CPU path even where a GPU is there
    gtkit model build site --executor dask --address tcp://host:8786   # depth maps on a Dask cluster
    gtkit model build site --use                # a delivered model exists: make the built one the project's
    gtkit model compare site                    # DSM height difference built - delivered (GeoTIFF)
"""
from __future__ import annotations


def register(sub):
    from ..model.settings import ModelSettings as S
    from .render_db import _executor_args

    p = sub.add_parser("model", help="build the reference model (dense depth, fusion, surface, texture) "
                       "from the reference photos; compare two models")
    ms = p.add_subparsers(dest="model_what", metavar="WHAT", required=True)
    b = ms.add_parser("build", help="textured reference model from the georegistered reference block")
    b.add_argument("project")
    # flags left out take project.toml [model_build], then ModelSettings' defaults (gtkit.stages.settings_for)
    b.add_argument("--max-image-size", type=int, default=None, help=f"px (default {S.max_image_size})")
    b.add_argument("--neighbours", type=int, default=None, help=f"stereo neighbours a photo (default {S.neighbours})")
    b.add_argument("--max-triangles", type=int, default=None, help=f"simplification budget (default {S.max_triangles})")
    b.add_argument("--poisson-depth", type=int, default=None, help=f"Poisson octree depth (default {S.poisson_depth})")
    b.add_argument("--depth-method", choices=("auto", "sgbm", "patchmatch"), default=None,
                   help="depth maps by SGBM on the CPU or COLMAP's PatchMatch on an NVIDIA GPU (pycolmap-cuda12); "
                        f"auto: PatchMatch where CUDA is there (default {S.depth_method})")
    b.add_argument("--voxel", type=float, default=None, help=f"fusion voxel, m (default {S.voxel_m})")
    b.add_argument("--use", action="store_true",
                   help="make the built model the project's model even when a delivered one exists "
                        "(the delivered files move to model/delivered/)")
    _executor_args(b, None, "compute the SGBM depth maps as tasks there: local processes or a Dask cluster "
                            "(default: in this process; the maps are the same)")
    b.add_argument("--force", action="store_true", help="rebuild even when up to date (finished depth maps are kept)")
    b.set_defaults(func=run_build)

    c = ms.add_parser("compare", help="height difference of two models' DSMs as a GeoTIFF (A - B)")
    c.add_argument("project")
    c.add_argument("--a", help="model A (default: the built model)")
    c.add_argument("--b", help="model B (default: the delivered model)")
    c.add_argument("--resolution", type=float, default=None, help="metres per cell (default: from the models)")
    c.add_argument("--out", help="output GeoTIFF (default exports/model_diff.tif)")
    c.set_defaults(func=run_compare)


def run_build(args):
    from ..model.build import run
    from ..project import Project
    from ..stages import STAGE, settings_for
    from .render_db import executor_settings

    project = Project.load(args.project)
    STAGE["model"].check_inputs(project)      # every bad reference photo named at once
    s = settings_for("model", project, {
        "max_image_size": args.max_image_size, "neighbours": args.neighbours, "max_triangles": args.max_triangles,
        "poisson_depth": args.poisson_depth, "voxel_m": args.voxel, "depth_method": args.depth_method})
    r = run(project, s, force=args.force, use=True if args.use else None, executor=executor_settings(args))
    print(f"model: {r['model']} ({r['triangles']} triangles, {r['parts']} textured parts) from {r['depth_maps']} "
          f"depth maps ({r.get('depth_method', 'sgbm')}) of {r['photos']} photos; {r['points']} fused points")
    if r.get("textureless"):
        print(f"texture test: {100 * r['textureless']['share']:.1f} % of the depth given up as textureless (plain ground, "
              "water: the DSM fills it, marked; [model_build] texture_min_contrast = 0 turns the test off)")
    print("seconds " + ", ".join(f"{k} {v}" for k, v in r["seconds"].items())
          + "; peak memory GB " + ", ".join(f"{k} {v}" for k, v in r["peak_memory_gb"].items()))
    for n, why in r["skipped"].items():
        print(f"  skipped {n}: {why}")
    from ..view.model import prepare_cache

    print(prepare_cache(project))  # the project's model, built or delivered (run() recorded it in project)


def run_compare(args):
    from ..model.compare import run

    r = run(args.project, args.a, args.b, args.resolution, args.out)
    print(f"{r['out']}: A - B over {r['cells']} common cells ({r['resolution']} m): median {r['median']:+.3f} m, "
          f"median |d| {r['median_abs']:.3f} m, p95 |d| {r['p95_abs']:.3f} m")
