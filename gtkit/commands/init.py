"""``gtkit init DIR --reference PHOTOS ...``: a project folder from your own photos and survey files."""
from __future__ import annotations

import argparse


def register(sub):
    p = sub.add_parser(
        "init", help="make a project folder from your own photos (and GCP / geo / camera files)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Make a project folder from a folder of reference photos, optional query sequences\n"
                    "(one folder each; wide/zoom photos paired by *_W / *_Z names) and optional\n"
                    "OpenDroneMap gcp_list.txt / geo.txt and a cameras.txt. Photos are linked (--copy copies).\n"
                    "CRS: --crs, else the GCP / geo file's first line, else the UTM zone of the photos' GPS.\n"
                    "Every photo and every line of the files is checked first; all problems are listed at once.")
    p.add_argument("project", help="the new project folder")
    p.add_argument("--reference", required=True, metavar="PHOTOS", help="folder of the reference (oblique) photos")
    p.add_argument("--queries", nargs="*", default=[], metavar="SEQ_DIR", help="query sequence folders")
    p.add_argument("--crs", default=None, help="project CRS: EPSG:<code>, WKT or PROJ (projected, metres)")
    p.add_argument("--gcp", default=None, metavar="FILE", help="OpenDroneMap gcp_list.txt")
    p.add_argument("--gcp-points", default=None, metavar="FILE",
                   help="GCP coordinates to click in the annotator: [CRS line] then name x y z [acc_h [acc_v]] [check]")
    p.add_argument("--geo", default=None, metavar="FILE", help="OpenDroneMap geo.txt (photo positions)")
    p.add_argument("--cameras", default=None, metavar="FILE", help="cameras.txt (fixed calibrations)")
    p.add_argument("--copy", action="store_true", help="copy the photos instead of linking them")
    p.add_argument("--name", default=None, help="project name (default: the folder's name)")
    p.add_argument("--skip-bad-photos", action="store_true",
                   help="leave out photos that cannot be used (empty, not an image, truncated, unreadable) instead "
                        "of refusing; they are listed in project.toml [imports.photos.left_out]")
    p.set_defaults(func=run)


def run(args):
    from ..project_init import init_project

    r = init_project(args.project, args.reference, args.queries, args.crs, args.gcp, args.geo, args.cameras,
                     args.copy, args.name, args.gcp_points, args.skip_bad_photos)
    ref = r.reference
    print(f"project {r.root}: CRS {r.crs} (from {r.crs_from}), origin {r.origin[0]:.0f} {r.origin[1]:.0f}")
    print(f"reference photos: {ref['photos']} ({', '.join(ref['sizes'])}); GPS {ref['gps']}, DJI XMP {ref['dji_xmp']}, "
          f"EXIF focal {ref['exif_focal']}")
    for s, q in r.queries.items():
        print(f"query sequence {s}: {q['photos']} photos ({q['wide']} wide *_W, {q['zoom']} zoom *_Z); GPS {q['gps']}, "
              f"DJI XMP {q['dji_xmp']}")
    if r.gcps.get("n") is not None:
        g = r.gcps
        print(f"GCPs: {g['n']} with {g['clicks']} clicks; check points: {', '.join(g['check_points']) or 'none'}"
              + (f"; fewer than 2 clicks: {', '.join(g['with_fewer_than_2_clicks'])}" if g['with_fewer_than_2_clicks'] else ""))
    if r.gcps.get("points"):
        g = r.gcps
        print(f"GCP coordinates: {g['points']} (CRS {g['points_crs']}; check points: {', '.join(g['points_check']) or 'none'})"
              " -> gcp/points.txt; click them in the annotator's GCPs tab after `gtkit sfm --block reference`")
    if r.geo:
        print(f"geo.txt: {r.geo['n']} positions, {r.geo['matching_photos']} match a photo, "
              f"{r.geo['with_accuracy']} with accuracy columns")
    if r.cameras:
        print(f"cameras.txt: {r.cameras} calibrations (kept fixed)")
    if r.left_out:
        from ..input_check import listing

        print(f"left out {len(r.left_out)} bad photo{'s' if len(r.left_out) != 1 else ''} (--skip-bad-photos; listed in "
              f"project.toml [imports.photos.left_out]): {listing(r.left_out, shown=len(r.left_out))}")
    for n in r.notes:
        print(f"note: {n}")
    for m in r.missing:
        print(f"missing: {m}")
    print(f"next: gtkit run {args.project}   (every stage; or stage by stage: gtkit sfm {args.project} --block reference)")
    return 0
