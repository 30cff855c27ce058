"""gtkit's main job on one project (the README's first command): ``gtkit run``'s stages, the same
table (:mod:`gtkit.stages`) with the same settings, plus the steps that need a sample's truth.

    sample site (created if DIR holds no project)            gtkit sample create DIR --preset small
    simulated target detections (sample sites: truth)        gtkit.evaluate.tracking.simulate_detections
    every stage, in order, as `gtkit run DIR` runs them      gtkit.run_site (reports/run.json)
    evaluation against truth (sample sites)                  gtkit evaluate / gtkit track evaluate
    summary of every measured figure                         reports/summary.json

So a user's ``project.toml`` ([export_dsm], [overlay], [localize], [track] ...) counts here exactly as
in ``gtkit run`` and in each stage's command. Every stage resumes: a second run with the same
settings only re-reads finished outputs.

    .venv/bin/python -m pipelines.full DIR [--preset small] [--seed 0]
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from gtkit.errors import GtkitError
from gtkit.io.atomic import write_json
from gtkit.project import PROJECT_FILE, Paths, relative_paths
from gtkit.project_lock import project_lock

log = logging.getLogger("full")


def _load(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def main(root: str | Path, preset: str = "small", seed: int = 0, progress=None, starting=None) -> dict:
    """The main job (see the module doc); returns the summary (also ``reports/summary.json``).
    Holds the project's lock (:mod:`gtkit.project_lock`) once the project exists."""
    root = Path(root)
    paths = Paths(root)
    times: dict[str, float] = {}
    if not (root / PROJECT_FILE).is_file():
        from gtkit.synth.generate import create_sample
        from gtkit.synth.settings import load_preset

        t = time.time()
        create_sample(root, load_preset(preset, seed=seed))
        times["sample"] = round(time.time() - t, 1)
    with project_lock(root):    # one writer per project: a second main job or gtkit run is refused
        return _job(root, paths, times, progress, starting)


def _job(root: Path, paths: Paths, times: dict, progress, starting) -> dict:
    from gtkit import run_site

    if paths.truth.is_dir() and not paths.detections.is_file():
        # sample sites only: a simulated detector marks the targets in the zoom photos
        from gtkit.evaluate.tracking import simulate_detections

        simulate_detections(paths, paths.detections, sigma_px=1.0, mode="box")
    run = run_site.run(root, progress=progress, starting=starting)
    times.update({k: v for k, v in (run.get("seconds") or {}).items()})
    summary: dict = {"project": str(root), "run": run_site.SUMMARY_FILE}
    gt = _load(paths.reports / "gt_report.json")     # the report stage: figures, and errors where truth is
    reg = _load(paths.stage("register") / "registration.json")
    ref = _load(paths.stage("sfm_reference") / "block.json")
    summary["pseudo_gt"] = {"reference": {k: ref.get(k) for k in ("n_registered", "n_images", "mean_reproj_px")},
                            "sequences": reg.get("sequences"),
                            **{k: gt.get(k) for k in ("n_registered", "n_unverified", "n_images", "median_reproj_px",
                                                      "median_tiepoint_reproj_px", "median_pos_err_m",
                                                      "median_rot_err_deg", "point_cloud_comparison")}}
    ov = _load(paths.reports / "overlays" / "alignment.json")
    summary["overlays"] = {k: ov.get(k) for k in ("median_misalignment_px", "median_edge_distance_px")}
    if paths.truth.is_dir():
        summary.update(_evaluate(paths))
    summary["seconds"] = times
    write_json(paths.reports / "summary.json", relative_paths(summary, root))  # portable: the project is "."
    return summary


def _evaluate(paths: Paths) -> dict:
    """Sample sites: localization and tracking against truth (the pseudo-GT's is in the GT report)."""
    from gtkit.evaluate import localization
    from gtkit.evaluate.tracking import evaluate_tracking

    out: dict = {}
    if (paths.stage("localize") / "status.json").is_file():
        out["localization"] = localization.evaluate(paths.root)
    if paths.tracks.is_file():
        from gtkit.track.rig import Rig

        rig = Rig.load(paths.rig).info if paths.rig.is_file() else {}
        rep = evaluate_tracking(paths)
        out["tracking"] = {"rig": {k: rig.get(k) for k in ("n_pairs", "median_px")},
                           "track": _load(paths.stage("track") / "summary.json"),
                           "evaluation": {k: rep[k] for k in ("n_targets", "n_failed", "median_err_h_m",
                                                              "median_err_3d_m")}}
    return out


def _print_summary(s: dict) -> None:
    pg, loc, tr = s.get("pseudo_gt") or {}, s.get("localization") or {}, (s.get("tracking") or {}).get("evaluation") or {}

    def f(v, fmt="{:.3f}"):
        return "-" if v is None else fmt.format(v)

    print("\n== gtkit on", s["project"])
    print(f"pseudo-GT     {pg.get('n_registered')}/{pg.get('n_images')} query images registered, "
          f"median error {f(pg.get('median_pos_err_m'))} m / {f(pg.get('median_rot_err_deg'))} deg vs truth, "
          f"reprojection {f(pg.get('median_reproj_px'), '{:.2f}')} px (tie points {f(pg.get('median_tiepoint_reproj_px'), '{:.2f}')} px)"
          + (f"; {pg['n_unverified']} UNVERIFIED (no sigma)" if pg.get("n_unverified") else ""))
    print(f"overlays      median misalignment {f((s.get('overlays') or {}).get('median_misalignment_px'), '{:.2f}')} px")
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
    import os

    from gtkit.supervisor import SUPERVISED, run_supervised

    if not os.environ.get(SUPERVISED) and not os.environ.get("GTKIT_NO_CHILD"):   # as the gtkit command
        sys.exit(run_supervised([sys.executable, "-m", "pipelines.full", *sys.argv[1:]], "python -m pipelines.full",
                                sys.argv[1:]))
    from gtkit.logs import exception_words, quiet_terminal, write_traceback
    from gtkit.write_errors import machine_cause

    ap = argparse.ArgumentParser(prog="python -m pipelines.full", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("project", help="project folder; a sample site is generated there if it holds none")
    ap.add_argument("--preset", default="small", help="sample preset when a site is generated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("-v", "--verbose", action="store_true",
                    help="log records (INFO), COLMAP, Open3D and Qt output on the terminal (else in "
                         "work/<stage>/log.txt)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from gtkit.commands.run import stage_done, stage_starting   # gtkit run's one line per stage

    stage_log = None
    try:
        with quiet_terminal(a.verbose) as stage_log:
            summary = main(a.project, a.preset, a.seed, stage_done, stage_starting)
        _print_summary(summary)
    except GtkitError as e:
        told = getattr(e, "traceback_file", None) is not None
        log = getattr(stage_log, "log_path", None)
        print(f"gtkit: error: {e}" + (f" (full log: {log})" if log and not told else ""), file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("gtkit: interrupted; finished stages are kept and a re-run resumes", file=sys.stderr)
        sys.exit(130)
    except Exception as e:  # the machine's cause in one line, else a bug: its traceback in a file
        cause = machine_cause(e)
        if cause is None:
            where = write_traceback(Path(a.project) / "work" / "errors" / "main_job.txt", "python -m pipelines.full")
            cause = (f"failed unexpectedly ({exception_words(e)}); "
                     f"the traceback is in {where} (please report it)")
        print(f"gtkit: error: the main job: {cause}", file=sys.stderr)
        sys.exit(2)
