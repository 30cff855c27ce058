"""``gtkit gcp import SITE FILE`` / ``gtkit gcp predict SITE`` / ``gtkit gcp status SITE``: a
surveyor's GCP coordinates in, their predicted positions in the photos out (issue 46)."""
from __future__ import annotations

import argparse


def register(sub):
    p = sub.add_parser("gcp", help="GCP coordinates in, predicted positions in every photo out",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Mark ground control points in gtkit.\n"
                                   "  import  read a coordinates file (first line the CRS, then 'name x y z [acc_h [acc_v]]"
                                   " [check]',\n          CSV or whitespace) into gcp/points.txt\n"
                                   "  predict every GCP in every photo of the reference block that sees it, with its "
                                   "uncertainty,\n          to work/gcp/predicted.csv (gcp, photo, x, y, sigma_px, source, where); one "
                                   "predicted just\n          outside a photo whose 2-sigma ellipse reaches into it is "
                                   "listed 'near the edge'\n"
                                   "  status  each GCP and check point: clicks, image residual, X/Y/Z error; then the\n"
                                   "          georegistration's residuals as `gtkit sfm` records them (its own refit on the\n"
                                   "          mapped block, seconds)\n"
                                   "Click them in the annotator's GCP page (gtkit annotate SITE); clicks go to "
                                   "gcp_list.txt.")
    s = p.add_subparsers(dest="gcp_command", required=True)
    i = s.add_parser("import", help="read a GCP coordinates file into the project")
    i.add_argument("project")
    i.add_argument("file", help="coordinates: first line the CRS (optional), then name x y z [acc_h [acc_v]] [check]")
    i.add_argument("--crs", default=None, help="the file's CRS when its first line names none (default: the project's)")
    i.set_defaults(func=run_import)
    for name, fn, h in (("predict", run_predict, "predicted positions to work/gcp/predicted.csv"),
                        ("status", run_status, "each GCP's clicks, residuals and errors")):
        q = s.add_parser(name, help=h)
        q.add_argument("project")
        q.set_defaults(func=fn, writes=name != "status")   # status only reads: no project lock


def run_import(args):
    from ..gcp.site import import_points
    from ..project import Project

    proj = Project.load(args.project)
    r = import_points(proj, args.file, args.crs)
    print(f"{r['n']} GCPs from {args.file} (CRS {r['crs']}; {len(r['check_points'])} check points"
          f"{': ' + ', '.join(r['check_points']) if r['check_points'] else ''}; {r['with_accuracy']} with an accuracy)"
          f" -> {r['stored']} ({r['total']} in all)")
    if r["clicked"]:
        print(f"already clicked in gcp_list.txt: {', '.join(r['clicked'])}")
    for n, d in r["coordinates_changed"]:
        print(f"note: {n}: coordinates differ from gcp_list.txt's by {d:.3f} m; gcp_list.txt now has the imported ones")
    print(f"next: gtkit gcp predict {args.project}   or click them: gtkit annotate {args.project} (GCPs tab)")
    return 0


def _table(sol) -> list[str]:
    out = [f"fit: {sol.fit}"]
    for kind, check in (("GCPs", False), ("check points", True)):
        rows = [s for s in sol.states.values() if s.check == check]
        if not rows:
            continue
        out.append(f"{kind}:")
        for s in rows:
            e = s.error_m
            out.append(f"  {s.name:12s} clicks {s.clicks_used}/{s.n_clicks}  "
                       + (f"residual {s.residual_px:.2f} px  " if s.residual_px is not None else "")
                       + (f"error X {e[0]:+.3f} Y {e[1]:+.3f} Z {e[2]:+.3f} m" if e is not None else s.reason)
                       + ("  (in the fit)" if s.in_fit else ""))
        r = sol.rmse_m(check)
        if r is not None:
            out.append(f"  RMSE {r:.3f} m")
    return out


def run_predict(args):
    from ..gcp.site import predict
    from ..project import Project

    sol, out = predict(Project.load(args.project))
    n = len({p.gcp for p in sol.predictions})
    edge = [p for p in sol.predictions if p.near_edge]
    print(f"{len(sol.predictions)} predicted positions of {n} GCPs -> {out}"
          + (f" ({len(edge)} near the edge: predicted just outside the photo, its 2-sigma ellipse reaching in)"
             if edge else ""))
    for p in edge:
        print(f"  near the edge: {p.gcp} in {p.photo} at ({p.x:.0f}, {p.y:.0f}) px, sigma {p.sigma_px:.0f} px")
    for line in _table(sol):
        print(line)
    return 0


def run_status(args):
    from ..gcp.site import current_solution, georegistration_refit, refit_lines
    from ..project import Project

    proj = Project.load(args.project)
    print("predictions' quick refit (gtkit gcp predict, the annotator's predictions):")
    for line in _table(current_solution(proj)):
        print("  " + line)
    refit = georegistration_refit(proj)
    for line in refit_lines(refit.run()) if refit.available else [f"georegistration: {refit.why}"]:
        print(line)
    return 0
