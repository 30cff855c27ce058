"""``gtkit overlay DIR``: overlay PNGs (model rendered at each pose over the photo) for every image,
plus ``alignment.json`` with each image's alignment measure; headless."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("overlay", help="write render-over-photo overlay PNGs and alignment measures")
    p.add_argument("project")
    p.add_argument("--poses", help="pose file (default: the register stage's pseudo-GT poses)")
    p.add_argument("--out", help="output folder (default: reports/overlays)")
    # flags left out take project.toml [overlay], then OverlaySettings' defaults (gtkit.stages.settings_for)
    p.add_argument("--modes", default=None, help="comma-separated overlay modes (default blend,swipe,edges,checker)")
    p.add_argument("--max-side", type=int, default=None, help="long side of the overlays in pixels (default 1024)")
    p.add_argument("--images", nargs="*", help="only these images (names relative to images/)")
    p.add_argument("--model", help="model to draw: a mesh file, or a tiled model folder (streamed: only the tiles "
                                   "each photo sees are uploaded) (default: model/reference.obj, else the tiled model)")
    p.set_defaults(func=run)


def run(args):
    from ..project import Project
    from ..render.overlay import write_overlays
    from ..stages import STAGE, settings_for

    modes = tuple(m for m in args.modes.split(",") if m) if args.modes is not None else None
    project = Project.load(args.project)
    if not (args.images or args.poses):      # the project's own photos: every bad one named at once
        STAGE["overlays"].check_inputs(project)
    st = settings_for("overlays", project, {"max_side": args.max_side, "modes": modes})

    def progress(k, n, name, a):
        print(f"[{k}/{n}] {name}: misalignment {a.misalignment_px:.2f} px, edge distance {a.edge_distance_px:.2f} px",
              flush=True)

    s = write_overlays(args.project, args.poses, args.out, st, args.images, progress, model_path=args.model)
    print(f"median misalignment {s['median_misalignment_px']} px, median edge distance "
          f"{s['median_edge_distance_px']} px over {len(s['images'])} images")
