"""``gtkit export dsm|ortho|mesh|coords|dataset``: surveyor outputs in the project CRS (see gtkit.export),
and the pseudo-GT as a dataset to publish (see gtkit.dataset).

Examples::

    gtkit export dsm site [--resolution 0.5] [--cog]
    gtkit export dsm --input model.laz --crs EPSG:32615 --out dsm.tif     # a file outside a project
    gtkit export dsm site [--no-gap-fill] [--gap-fill-max-m 50]              # gaps filled inside the footprint
    gtkit export ortho site [--resolution 0.1] [--method photos|model] [--no-blend]
    gtkit export mesh site --format glb [--decimate 200000]
    gtkit export coords site [--poses work/register/poses.txt] [--targets exports/tracks.csv]
    gtkit export dataset site OUT [--format kapture,colmap,hloc] [--copy] [--with-model] [--no-depth]
"""
from __future__ import annotations


def _offset(text):
    from ..errors import GtkitError

    try:
        v = [float(s) for s in text.replace(",", " ").split()]
    except ValueError:
        v = []
    if len(v) != 3:
        raise GtkitError(f"--offset needs three numbers 'E,N,H', got {text!r}")
    return v


def _source_args(p, raster: bool):
    p.add_argument("project", nargs="?", help="project folder (optional with --input and --out)")
    p.add_argument("--input", help="mesh (.obj/.ply/.glb) or point cloud (.las/.laz/.ply) instead of the "
                   "project's model/reference.obj")
    p.add_argument("--crs", help="CRS of --input when it has no sidecar/header CRS, e.g. EPSG:32615")
    p.add_argument("--offset", help="'E,N,H' added to --input's coordinates when it has no sidecar")
    if raster:
        p.add_argument("--resolution", type=float, help="metres per cell (default: from the model's detail; "
                       "never finer than it)")
        p.add_argument("--cog", action="store_true", help="write a cloud-optimised GeoTIFF")
        p.add_argument("--out", help="output GeoTIFF (default: exports/<product>.tif in the project)")


def register(sub):
    p = sub.add_parser("export", help="DSM / orthophoto GeoTIFFs, textured mesh, coordinates in the project CRS")
    ex = p.add_subparsers(dest="export_what", metavar="WHAT", required=True)

    d = ex.add_parser("dsm", help="digital surface model GeoTIFF (highest surface per cell)")
    _source_args(d, raster=True)
    d.add_argument("--fill-holes", type=int, default=None, help="passes of small-hole filling (0 = none; default 2)")
    d.add_argument("--no-gap-fill", action="store_true", help="leave the gaps (cells without surface) empty; by "
                   "default those inside the reference photos' footprint are interpolated from their border and "
                   "marked 1 in band 2 'filled'")
    d.add_argument("--gap-fill-max-m", type=float, default=None, help="leave cells farther than this from a measured "
                   "cell empty (default 0 = any distance inside the footprint)")
    d.add_argument("--footprint-views", type=int, default=None, help="reference photos that must see a cell for it "
                   "to be filled (default 2)")
    d.set_defaults(func=run_dsm)

    o = ex.add_parser("ortho", help="true orthophoto GeoTIFF (RGB + alpha): the reference photos over the DSM "
                      "(seams blended), or the textured model seen from above")
    _source_args(o, raster=True)
    o.add_argument("--method", choices=("auto", "photos", "model"), default=None,
                   help="photos: the reference photos over exports/dsm.tif; model: the textured model; auto "
                   "(default): photos when the project has a reference block and a DSM")
    o.add_argument("--no-blend", action="store_true", help="photos: no exposure compensation or feathering")
    o.add_argument("--feather-m", type=float, default=None, help="photos: feathering band on each side of a seam "
                   "(metres; default 0 = 8 cells)")
    o.set_defaults(func=run_ortho)

    m = ex.add_parser("mesh", help="textured mesh in the project CRS + offset sidecar")
    _source_args(m, raster=False)
    m.add_argument("--format", choices=("obj", "ply", "glb"), default=None, help="default obj")
    m.add_argument("--decimate", type=int, help="target number of triangles (pymeshlab)")
    m.add_argument("--out-dir", help="output folder (default: exports/mesh)")
    m.set_defaults(func=run_mesh)

    c = ex.add_parser("coords", help="camera poses and targets as CSV / GeoJSON (WGS84 + CRS) and ODM geo.txt")
    c.add_argument("project")
    c.add_argument("--poses", help="pose file (default: work/register/poses.txt (pseudo-GT) + work/sfm_reference/poses.txt if present)")
    c.add_argument("--targets", help="targets CSV: x,y,z or easting,northing,height (CRS) | lon,lat,height | world_x,world_y,world_z (default: exports/tracks.csv if present)")
    c.add_argument("--no-gcps", action="store_true", help="do not export gcp_list.txt's points")
    c.add_argument("--out-dir", help="output folder (default: exports/coordinates)")
    c.set_defaults(func=run_coords)

    s = ex.add_parser("dataset", help="the pseudo-GT as a dataset to publish: kapture, COLMAP and hloc files, "
                      "sigma and covariance of every pose, a datasheet (DATASET.md, dataset.json)")
    s.add_argument("project")
    s.add_argument("out", help="output folder (new, empty, or a dataset exported before: replaced whole; "
                   "unchanged inputs: nothing is written)")
    s.add_argument("--format", default="kapture,colmap,hloc",
                   help="comma-separated formats to write (default kapture,colmap,hloc)")
    s.add_argument("--copy", action="store_true", help="copy the photos instead of linking them")
    s.add_argument("--with-model", action="store_true", help="add the reference model and the DSM")
    s.add_argument("--no-depth", action="store_true", help="leave the rendered views' depth maps out of "
                   "kapture/mapping (float32, 1.2 MB a 640x480 view)")
    s.set_defaults(func=run_dataset)


def _settings(stage: str, project_dir, cli: dict):
    """Flags given > project.toml (when there is a project) > defaults (gtkit.stages.settings_for)."""
    from ..project import Project
    from ..stages import settings_for

    return settings_for(stage, Project.load(project_dir) if project_dir is not None else None, cli)


def _need_project_or_out(args):
    from ..errors import GtkitError

    if args.project is None and (args.input is None or getattr(args, "out", None) is None):
        raise GtkitError("give a project folder, or --input and --out for a file outside a project")


def run_dsm(args):
    from ..export import dsm

    _need_project_or_out(args)
    s = _settings("export_dsm", args.project,
                  {"resolution": args.resolution, "cog": args.cog or None, "fill_holes": args.fill_holes,
                   "gap_fill": False if args.no_gap_fill else None, "gap_fill_max_m": args.gap_fill_max_m,
                   "footprint_views": args.footprint_views})
    off = _offset(args.offset) if args.offset else None
    if args.project is None:
        out = dsm.run_file(args.input, args.out, s, args.crs, off)
    else:
        out = dsm.run(args.project, s, args.input, args.crs, off, args.out)
    print(out)


def run_ortho(args):
    from ..export import ortho

    _need_project_or_out(args)
    s = _settings("export_ortho", args.project,
                  {"resolution": args.resolution, "cog": args.cog or None, "method": args.method,
                   "blend": False if args.no_blend else None, "feather_m": args.feather_m})
    off = _offset(args.offset) if args.offset else None
    if args.project is None:
        out = ortho.run_file(args.input, args.out, s, args.crs, off)
    else:
        out = ortho.run(args.project, s, args.input, args.crs, off, args.out)
    print(out)


def run_mesh(args):
    from ..errors import GtkitError
    from ..export import mesh_export

    if args.project is None:
        raise GtkitError("gtkit export mesh needs a project folder (its CRS and origin)")
    s = _settings("export_mesh", args.project,
                  {"format": args.format, "decimate": args.decimate})
    print(mesh_export.run(args.project, s, args.input, args.crs, _offset(args.offset) if args.offset else None,
                          args.out_dir))


def run_coords(args):
    from ..export import coordinates

    s = _settings("export_coords", args.project,
                  {"poses": args.poses, "targets": args.targets, "include_gcps": False if args.no_gcps else None})
    for path in coordinates.run(args.project, s, args.out_dir).values():
        print(path)


def run_dataset(args):
    from ..dataset.stage import DatasetSettings, run

    info = run(args.project, args.out, DatasetSettings(formats=tuple(args.format.split(",")), copy=args.copy,
                                                       with_model=args.with_model, depth=not args.no_depth))
    if info["status"] == "up to date":
        print(f"{info['out']}: up to date (nothing written)")
    else:
        kept = ", ".join(f"{v} {k}" for k, v in sorted(info["kept_out_by_kind"].items()))
        print(f"{info['out']}: {info['n_published']} pseudo-GT poses published ({', '.join(info['formats'])}), "
              f"{info['n_kept_out']} photos kept out{f' ({kept})' if kept else ''}; see DATASET.md")
