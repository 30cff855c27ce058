"""gtkit's main job, top to bottom, on one project (the README's first command):

    sample site (created if DIR holds no project)            gtkit sample create DIR --preset small
    1. pseudo-GT: SfM of both blocks, tie points, joint BA   pipelines/pseudo_gt.py
    2. surveyor exports: DSM, orthophoto, mesh, coordinates  gtkit export dsm|ortho|mesh|coords DIR
    3. review overlays of the pseudo-GT poses                gtkit overlay DIR
    4. localization: render database, localize, evaluate    pipelines/localize.py
    5. target tracking on the localized poses                pipelines/track.py
    summary of every measured figure                         reports/summary.json

Every stage resumes: a second run with the same settings only re-reads finished outputs.

    .venv/bin/python -m pipelines.full DIR [--preset small] [--seed 0]
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from gtkit.errors import GtkitError
from gtkit.io.atomic import write_json
from gtkit.project import PROJECT_FILE, Paths, relative_paths

from ._timing import timed

log = logging.getLogger("full")


def _timed(times: dict, name: str, fn, *a, **kw):
    return timed(times, name, fn, *a, log=log, **kw)


def main(root: str | Path, preset: str = "small", seed: int = 0) -> dict:
    from gtkit.export import coordinates, dsm, mesh_export, ortho
    from gtkit.render.overlay import OverlaySettings, write_overlays

    from . import localize as localize_pipeline
    from . import pseudo_gt
    from . import track as track_pipeline

    root = Path(root)
    paths = Paths(root)
    times: dict[str, float] = {}
    if not (root / PROJECT_FILE).is_file():
        from gtkit.synth.generate import create_sample
        from gtkit.synth.settings import load_preset

        _timed(times, "sample", create_sample, root, load_preset(preset, seed=seed))
    summary: dict = {"project": str(root)}

    summary["pseudo_gt"] = _timed(times, "pseudo_gt", pseudo_gt.main, str(root))
    _timed(times, "export_dsm", dsm.run, root)
    _timed(times, "export_ortho", ortho.run, root)
    _timed(times, "export_mesh", mesh_export.run, root)
    _timed(times, "export_coords", coordinates.run, root)
    ov = _timed(times, "overlays", write_overlays, root, None, None, OverlaySettings(modes=("blend", "edges")))
    summary["overlays"] = {k: ov.get(k) for k in ("median_misalignment_px", "median_edge_distance_px")}

    reports = _timed(times, "localize", localize_pipeline.run, root)
    summary["localization"] = reports.get("default")

    if paths.truth.is_dir() and not paths.detections.is_file():
        # sample sites only: a simulated detector marks the targets in the zoom photos
        from gtkit.evaluate.tracking import simulate_detections

        simulate_detections(paths, paths.detections, sigma_px=1.0, mode="box")
    loc_poses = paths.stage("localize") / "poses.txt"
    summary["tracking"] = _timed(times, "track", track_pipeline.main, str(root),
                                 poses=str(loc_poses) if loc_poses.is_file() else "")
    summary["seconds"] = times
    write_json(paths.reports / "summary.json", relative_paths(summary, root))  # portable: the project is "."
    return summary


def _print_summary(s: dict) -> None:
    pg, loc, tr = s.get("pseudo_gt") or {}, s.get("localization") or {}, (s.get("tracking") or {}).get("evaluation") or {}

    def f(v, fmt="{:.3f}"):
        return "-" if v is None else fmt.format(v)

    print("\n== gtkit on", s["project"])
    print(f"pseudo-GT     {pg.get('n_registered')}/{pg.get('n_images')} query images registered, "
          f"median error {f(pg.get('median_pos_err_m'))} m / {f(pg.get('median_rot_err_deg'))} deg vs truth, "
          f"reprojection {f(pg.get('median_reproj_px'), '{:.2f}')} px (tie points {f(pg.get('median_tiepoint_reproj_px'), '{:.2f}')} px)")
    print(f"overlays      median misalignment {f(s['overlays'].get('median_misalignment_px'), '{:.2f}')} px")
    if loc:
        print(f"localization  recall (1m,1°)/(3m,3°)/(5m,5°) = {100 * loc['recall_1m1deg']:.1f} / "
              f"{100 * loc['recall_3m3deg']:.1f} / {100 * loc['recall_5m5deg']:.1f} %, "
              f"R@1 {f(loc.get('retrieval_R1'), '{:.2f}')}, median {f(loc.get('median_pos_err_m'))} m, "
              f"{f(loc.get('sec_per_query'), '{:.2f}')} s/query")
    if tr:
        print(f"tracking      {tr.get('n_targets')} targets, median error {f(tr.get('median_err_h_m'), '{:.2f}')} m "
              f"horizontal, {f(tr.get('median_err_3d_m'), '{:.2f}')} m 3D, {tr.get('n_failed')} failed")
    print("seconds       " + ", ".join(f"{k} {v}" for k, v in s["seconds"].items()))
    print("reports       " + str(Path(s["project"]) / "reports"))


if __name__ == "__main__":
    from gtkit.logs import quiet_terminal

    ap = argparse.ArgumentParser(prog="python -m pipelines.full", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", help="project folder; a sample site is generated there if it holds none")
    ap.add_argument("--preset", default="small", help="sample preset when a site is generated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("-v", "--verbose", action="store_true",
                    help="COLMAP, Open3D and Qt output on the terminal (else in work/<stage>/log.txt)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        with quiet_terminal(a.verbose) as stage_log:
            summary = main(a.project, a.preset, a.seed)
        _print_summary(summary)
    except GtkitError as e:
        print(f"gtkit: error: {e}" + (f" (full log: {stage_log.log_path})" if stage_log.log_path else ""),
              file=sys.stderr)
        sys.exit(2)
