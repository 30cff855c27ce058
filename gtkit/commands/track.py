"""``gtkit track``: target positions from zoom-photo detections, the rig and the DSM.

    gtkit track DIR [--poses FILE] [--detections FILE] [--foot-point centre|bottom_centre] [--no-smooth]
    gtkit track calibrate DIR        wide/zoom rig calibration -> work/rig/rig.json
    gtkit track evaluate DIR         against truth/ (sample sites) -> reports/tracking.json + plot
"""
from __future__ import annotations

import argparse
import textwrap

ACTIONS = ("calibrate", "evaluate", "run")


def register(sub):
    p = sub.add_parser("track", help="3D target tracks from zoom-photo detections (ray cast on the DSM); "
                       "'track calibrate DIR' calibrates the wide/zoom rig, 'track evaluate DIR' scores "
                       "the tracks against truth/",
                       description=textwrap.dedent(__doc__.split("\n\n", 1)[1]).strip(),
                       usage="gtkit track [calibrate | evaluate | run] DIR [options]",
                       formatter_class=argparse.RawDescriptionHelpFormatter)  # the usage lines as written
    p.add_argument("first", metavar="[ACTION] DIR", help="project folder, optionally preceded by "
                   "calibrate | evaluate | run (default run)")
    p.add_argument("second", nargs="?", default=None, metavar="[DIR]", help=a_help())
    p.add_argument("--poses", default="", help="wide pose file (name qw qx qy qz tx ty tz); default "
                   "work/localize/poses.txt; e.g. a pseudo-GT pose file")
    p.add_argument("--covariances", default="", help="6x6 pose covariances (default: covariances.txt "
                   "beside the poses, if present; else default sigmas)")
    p.add_argument("--detections", default="", help="CSV or labelme JSON (default: DIR/detections.csv)")
    p.add_argument("--foot-point", default=None, choices=("bottom_centre", "centre"),
                   help="how a box gives the ground point: its centre, cast at half the target's height "
                   "above the DSM (default), or its bottom centre")
    p.add_argument("--no-smooth", action="store_true", help="no RTS-smoothed track")
    p.add_argument("--force", action="store_true", help="recompute even if up to date")
    p.set_defaults(func=run)


def a_help():
    return "the project folder when an action is given"


def run(args):
    import json

    from ..errors import GtkitError

    if args.second is not None:
        action, root = args.first, args.second
        if action not in ACTIONS:
            raise GtkitError(f"unknown track action {action!r} (choose {', '.join(ACTIONS)})")
    else:
        action, root = "run", args.first
    if action == "calibrate":
        from ..project import Project
        from ..stages import STAGE, settings_for
        from ..track.calibrate import run as calibrate

        project = Project.load(root)
        STAGE["track"].check_inputs(project)      # every bad query photo named at once
        rig = calibrate(project, settings_for("track", project)["rig"], force=args.force)
        print(json.dumps({k: v for k, v in rig.info.items() if k != "per_pair"}, indent=2))
        return 0
    if action == "evaluate":
        from ..evaluate.tracking import evaluate_tracking
        from ..project import Paths

        rep = evaluate_tracking(Paths(root))
        print(json.dumps({k: rep[k] for k in ("n_targets", "n_failed", "median_err_h_m", "median_err_3d_m",
                                              "recall_h") if k in rep}, indent=2))
        return 0
    from ..project import Project
    from ..stages import settings_for
    from ..track.tracker import run as track

    # flags given > project.toml [track] > TrackSettings' defaults (gtkit.stages.settings_for)
    s = settings_for("track", Project.load(root), {
        "track.detections": args.detections or None, "track.poses": args.poses or None,
        "track.covariances": args.covariances or None, "track.foot_point": args.foot_point,
        "track.smooth": False if args.no_smooth else None})["track"]
    summary = track(root, s, force=args.force)
    print(json.dumps({k: summary[k] for k in ("n_detections", "n_located", "status", "median_sigma_h_m",
                                              "csv", "geojson")}, indent=2))
    return 0
