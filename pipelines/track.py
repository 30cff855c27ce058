"""Hierarchical target tracking, top-down (UAVD4L §3.3):

    the wide camera is localized (gtkit localize, or any pose file)
    -> the zoom camera's pose follows from the rig (gtkit track calibrate)
    -> each detection's foot-point ray is marched to its first DSM crossing (gtkit export dsm)
    -> per-target points with uncertainty, smoothed tracks (gtkit track)
    -> on sample sites, errors against the true tracks (gtkit track evaluate)

    .venv/bin/python -m pipelines.track DIR [--poses FILE] [--detections FILE]
"""
from __future__ import annotations

import argparse
import json
import logging
import sys

from gtkit.errors import GtkitError
from gtkit.export import dsm as dsm_stage
from gtkit.project import Project
from gtkit.track import calibrate
from gtkit.stages import settings_for
from gtkit.track.tracker import run as track


def main(root: str, poses: str = "", detections: str = "", evaluate: bool = True) -> dict:
    project = Project.load(root)
    if not project.paths.dsm.is_file():
        dsm_stage.run(project, settings_for("export_dsm", project))   # exports/dsm.tif from the reference model
    s = settings_for("track", project, {"track.poses": poses or None, "track.detections": detections or None})
    rig = calibrate.run(project, s["rig"])                      # work/rig/rig.json
    summary = track(project, s["track"])                        # exports/tracks.csv/.geojson
    out = {"rig": {k: rig.info[k] for k in ("n_pairs", "median_px")}, "track": summary}
    if evaluate and project.paths.truth.is_dir():
        from gtkit.evaluate.tracking import evaluate_tracking

        rep = evaluate_tracking(project.paths)                  # reports/tracking.json + tracking.png
        out["evaluation"] = {k: rep[k] for k in ("n_targets", "n_failed", "median_err_h_m", "median_err_3d_m")}
    return out


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project")
    ap.add_argument("--poses", default="")
    ap.add_argument("--detections", default="")
    a = ap.parse_args()
    try:
        print(json.dumps(main(a.project, a.poses, a.detections), indent=2, default=str))
    except GtkitError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
