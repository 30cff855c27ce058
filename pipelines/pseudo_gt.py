"""Pseudo ground truth for a new site, top-down (UAVD4L §3.2, with pycolmap instead of a
commercial package):

    reference photos -> SfM, georegistered by RTK GPS and GCPs   (gtkit sfm DIR --block reference)
    each query sequence's wide photos -> its own SfM block      (gtkit sfm DIR --block queries)
    tie points (GUI clicks or simulated) -> Sim(3) per sequence -> + automatic SIFT tie points
        -> one joint BA, reference fixed
                                                                 (gtkit register DIR)
    quality report, against truth/ where it exists              (gtkit report DIR)

Every stage resumes when its settings and inputs are unchanged (work/<stage>/stage.json).

    .venv/bin/python -m pipelines.pseudo_gt DIR [--point-cloud model.laz] [--force]
"""
from __future__ import annotations

import argparse
import json
import logging
import sys

from gtkit.errors import GtkitError
from gtkit.project import Project
from gtkit.stages import settings_for

from ._timing import timed
from gtkit.evaluate import gt_report as report  # the report plus checks against truth / a point cloud
from gtkit.sfm import blocks, register

log = logging.getLogger("pseudo_gt")


def main(root: str, sfm: blocks.SfmSettings | None = None, reg: register.RegisterSettings | None = None,
         rep: report.ReportSettings | None = None, force: bool = False) -> dict:
    """Settings given here (a benchmark's) replace the stage table's (project.toml over defaults)."""
    project = Project.load(root)
    sfm = sfm or settings_for("sfm_reference", project)
    reg = reg or settings_for("register", project)
    rep = rep or settings_for("report", project)
    times = {}

    def stage(name, fn, *a, **kw):
        return timed(times, name, fn, *a, log=log, **kw)

    ref = stage("sfm_reference", blocks.run_reference, project, sfm, force=force)
    qb = {}
    if project.paths.query_sequences():
        qb = stage("sfm_queries", blocks.run_queries, project, sfm, force=force)
    r = {}
    if qb:   # no tiepoints.json: sequences placed by automatic matches
        r = stage("register", register.run, project, reg, force=force)
    summary = stage("report", report.run, project, rep)
    return {"seconds": times, "reference": {k: ref.get(k) for k in ("n_registered", "n_images", "mean_reproj_px")},
            "sequences": r.get("sequences"),
            **{k: summary.get(k) for k in ("n_registered", "n_images", "median_reproj_px", "median_tiepoint_reproj_px",
                                           "median_pos_err_m", "median_rot_err_deg", "point_cloud_comparison")}}


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project")
    ap.add_argument("--point-cloud", default=None, help="independent LAS/LAZ to compare the reference points with")
    ap.add_argument("--gps-inlier-m", type=float, default=None, help="GPS Sim(3) threshold (consumer GPS: 5)")
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    try:
        proj = Project.load(a.project)
        s = settings_for("sfm_reference", proj, {"georegister.gps_inlier_m": a.gps_inlier_m})
        print(json.dumps(main(a.project, s, rep=settings_for("report", proj, {"point_cloud": a.point_cloud}),
                              force=a.force), indent=2,
                         default=str))
    except GtkitError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
