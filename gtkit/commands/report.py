"""``gtkit report DIR``: pseudo-GT quality report (reports/gt_report.json + gt_report.md)."""
from __future__ import annotations


def register(sub):
    p = sub.add_parser("report", help="pseudo-GT quality report (JSON + Markdown with plots)")
    p.add_argument("project")
    p.add_argument("--point-cloud", default=None, help="independent LAS/LAZ to compare the reference points with")
    p.add_argument("--point-cloud-crs", default=None, help="its CRS if the file does not name one")
    p.set_defaults(func=run)


def run(args):
    from ..evaluate.gt_report import run as run_report  # the stages' report + checks against truth / a point cloud
    from ..project import Project
    from ..stages import settings_for

    project = Project.load(args.project)
    r = run_report(project, settings_for("report", project, {"point_cloud": args.point_cloud,
                                                             "point_cloud_crs": args.point_cloud_crs}))
    print(f"registered {r['n_registered']}/{r['n_images']}; median reprojection {r.get('median_reproj_px')} px; "
          f"tie points {r.get('median_tiepoint_reproj_px')} px")
    if "median_pos_err_m" in r:
        print(f"vs truth: median {r['median_pos_err_m']} m, {r['median_rot_err_deg']} deg")
    pc = r.get("point_cloud_comparison")
    if pc:
        print(f"vs {pc['cloud']}: vertical offset {pc['vertical_offset_m']:+.3f} m, horizontal {pc['horizontal_offset_m']:.3f} m")
    print("wrote reports/gt_report.json and reports/gt_report.md")
