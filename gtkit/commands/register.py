"""``gtkit register DIR``: registration of each query block (clicked tie points, else automatic matches)
+ joint bundle adjustment. Exit status 1 when a sequence could not be registered, or a photo has no sigma (unverified) (each is named with
its reason and what to click)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("register", help="register query blocks to the reference by tie points (a sequence without "
                       "3 usable clicks: by its photos' automatic matches, guided by their GPS + gimbal metadata); "
                       "joint BA; writes pseudo-GT poses")
    p.add_argument("project")
    p.add_argument("--sim3-max-error-m", type=float, default=None, help="Sim(3) RANSAC threshold (default 1.5 m)")
    p.add_argument("--tie-max-px", type=float, default=None, help="click residual threshold (default 4 px)")
    p.add_argument("--refine-query-intrinsics", action="store_true")
    p.add_argument("--no-auto-ties", action="store_true",
                   help="no automatic tie points (query photos SIFT-matched to the reference block's 3D points): "
                        "the annotators' clicks only")
    p.add_argument("--force", action="store_true")
    p.set_defaults(func=run)


def run(args):
    from ..project import Project
    from ..sfm import registration_record as record
    from ..sfm.register import run as run_register
    from ..stages import settings_for

    project = Project.load(args.project)
    s = settings_for("register", project, {
        "sim3_max_error_m": args.sim3_max_error_m, "tie_max_px": args.tie_max_px,
        "refine_query_intrinsics": True if args.refine_query_intrinsics else None,
        "cross.enabled": False if args.no_auto_ties else None})
    r = run_register(project, s, force=args.force)
    failed = 0
    for seq, info in record.sequences(r).items():
        failed += not record.is_registered(info)
        print(f"{seq}: {record.describe(info)}")
    parts = [f"{what} {r[key]:.2f} px" for what, key in (
        ("median reprojection: SfM points", "median_reproj_px"), ("clicked tie points", "median_tiepoint_reproj_px"),
        ("automatic tie points", "median_auto_tiepoint_reproj_px")) if r.get(key) is not None]
    print(f"pseudo-GT: {r['n_registered']}/{r['n_images']} query photos; " + (", ".join(parts) or "no reprojection figures")
          + f"; {r.get('n_auto_tiepoints_in_ba', 0)} automatic tie points in the joint BA")
    for tid, b in (r.get("bad_tiepoints") or {}).items():
        print(f"  bad tie point {tid}: {b['reason']}; " + ", ".join(
            f"{c['image']} ({c['residual_px']:.0f} px)" for c in b["dropped_clicks"]))
    unverified = {n: i["unverified"] for n, i in (r.get("images") or {}).items() if i.get("unverified")}
    for n, why in sorted(unverified.items()):   # a pose without sigma is not a result
        print(f"  UNVERIFIED {n}: {why}")
    return 1 if failed or unverified else 0
