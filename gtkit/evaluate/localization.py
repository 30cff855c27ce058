"""Evaluate a localization run against ``truth/``: pose recall and errors, retrieval R@1/R@3/P@3,
seconds per query by step, and every failure with its reason.

Writes ``reports/localization.json`` (``reports/localization-<ablation>.json`` for an ablation)
and a readable Markdown twin. Missing poses count as failures. Only this module (and tests)
opens ``truth/``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_json, write_text
from ..io.poses import POSES, read_intrinsics, read_poses
from ..project import Project, read_stage_record
from .poses import THRESHOLDS, medians, pose_errors, recall
from .retrieval import retrieval_metrics, seen_fraction, surface_points

REPORT = "localization"
OVERLAP_THRESHOLD = 0.5


def _report_paths(project: Project, ablation: str) -> tuple[Path, Path]:
    stem = REPORT if ablation == "default" else f"{REPORT}-{ablation}"
    return project.paths.reports / f"{stem}.json", project.paths.reports / f"{stem}.md"


def retrieval_overlaps(project: Project, queries: list[dict], truth: dict, intrinsics: dict,
                       max_width: int = 320) -> dict[tuple[str, str], float]:
    """Overlap of each query (true pose) with each of its retrieved database views."""
    from ..localize.database import load_database, open_model

    pairs = [(q["name"], v) for q in queries for v, _s in q.get("retrieved", []) if q["name"] in truth]
    if not pairs:
        return {}
    db = load_database(project)
    views = {v.name: v for v in db.views}
    rec = read_stage_record(project.paths.stage("render_db"))
    r = open_model(project.paths.root, rec.settings.get("model", "model/reference.obj"), project.frame)
    out = {}
    try:
        for q in queries:
            name = q["name"]
            if name not in truth or not q.get("retrieved"):
                continue
            cam = intrinsics[name]
            cam = cam.scaled(min(1.0, max_width / cam.width))
            depth = r.render(cam, truth[name], with_rgb=False).depth
            pts = surface_points(cam, truth[name], depth, step=2)
            for v, _s in q["retrieved"]:
                dv = views.get(v)
                out[(name, v)] = seen_fraction(pts, db.camera, dv.pose, db.depth(dv)) if dv else 0.0
    finally:
        r.release()
    return out


def evaluate(project: Project | str | Path, ablation: str = "default", with_retrieval: bool = True) -> dict:
    from ..localize.localize import STEPS, output_dir

    project = project if isinstance(project, Project) else Project.load(project)
    run_dir = output_dir(project, ablation)
    status_file = run_dir / "status.json"
    if not status_file.is_file():
        raise GtkitError(f"no localization run to evaluate: run 'gtkit localize DIR"
                         f"{'' if ablation == 'default' else ' --ablation ' + ablation}' first", status_file)
    status = json.loads(status_file.read_text())
    truth_file = project.paths.truth_poses
    truth = read_poses(truth_file)
    queries = status["queries"]
    names = [q["name"] for q in queries]
    missing_truth = [n for n in names if n not in truth]
    if missing_truth:
        raise GtkitError(f"{len(missing_truth)} queries have no true pose (e.g. {missing_truth[0]})", truth_file)
    est = read_poses(run_dir / POSES)
    errors = pose_errors(est, truth, names)
    rep: dict = {"ablation": ablation, "n_queries": len(names), "n_localized": sum(1 for n in names if n in est)}
    rep.update(recall(errors, THRESHOLDS))
    rep.update(medians(errors))
    if with_retrieval:
        intr_file = project.paths.truth_intrinsics
        intr = read_intrinsics(intr_file) if intr_file.is_file() else read_intrinsics(project.paths.cameras)
        ov = retrieval_overlaps(project, queries, truth, intr)
        correct = {k: v > OVERLAP_THRESHOLD for k, v in ov.items()}
        retrieved = {q["name"]: [v for v, _s in q.get("retrieved", [])] for q in queries}
        rep.update(retrieval_metrics(retrieved, correct))
    secs = {k: float(np.mean([q["seconds"].get(k, 0.0) for q in queries])) for k in STEPS}
    rep["sec_per_query"] = float(np.mean([q.get("seconds_total", 0.0) for q in queries]))
    rep["sec_per_query_by_step"] = secs
    rep["cpu_sec_per_query"] = float(np.mean([q.get("cpu_seconds_total", 0.0) for q in queries]))
    rep["wall_s"] = status.get("wall_s")
    rep["executor"] = status.get("executor")
    rep["database_views"] = status.get("database_views")
    rep["settings"] = status.get("settings")
    rep["failures"] = [{"name": q["name"], "reason": q.get("reason")} for q in queries if not q["ok"]]
    per_q = []
    for q in queries:
        e = errors[q["name"]]
        row = {"name": q["name"], "ok": q["ok"], "reason": q.get("reason"),
               "pos_err_m": e.get("pos_err_m"), "rot_err_deg": e.get("rot_err_deg"),
               "n_inliers": (q.get("pnp") or {}).get("n_inliers")}
        if with_retrieval:
            row["retrieved_overlap"] = [round(ov.get((q["name"], v), 0.0), 3) for v, _s in q.get("retrieved", [])]
        per_q.append(row)
    rep["queries"] = per_q
    jpath, mpath = _report_paths(project, ablation)
    write_json(jpath, rep)
    from ..sfm.report import scene_links

    write_text(mpath, markdown(rep) + "\n".join(scene_links(mpath.parent)) + "\n")
    return rep


def _pct(v):
    return "-" if v is None else f"{100 * v:.2f}"


def markdown(rep: dict) -> str:
    L = [f"# Localization report ({rep['ablation']})", "",
         f"{rep['n_localized']} of {rep['n_queries']} queries localized; database views: {rep.get('database_views')}.", "",
         "| (1 m, 1°) | (3 m, 3°) | (5 m, 5°) | median position error | median rotation error |",
         "|---|---|---|---|---|",
         f"| {_pct(rep['recall_1m1deg'])} % | {_pct(rep['recall_3m3deg'])} % | {_pct(rep['recall_5m5deg'])} % | "
         + ("-" if rep["median_pos_err_m"] is None else f"{rep['median_pos_err_m']:.3f} m") + " | "
         + ("-" if rep["median_rot_err_deg"] is None else f"{rep['median_rot_err_deg']:.3f}°") + " |", ""]
    if "retrieval_R1" in rep:
        L += ["| retrieval R@1 | R@3 | P@3 |", "|---|---|---|",
              f"| {_pct(rep['retrieval_R1'])} % | {_pct(rep['retrieval_R3'])} % | {_pct(rep['retrieval_P3'])} % |", ""]
    L += ["Seconds per query by step (mean, measured inside the worker):", "",
          "| step | s / query |", "|---|---|"]
    L += [f"| {k} | {v:.3f} |" for k, v in rep["sec_per_query_by_step"].items()]
    L += [f"| **total** | **{rep['sec_per_query']:.3f}** |",
          f"| CPU time of the worker (all threads) | {rep.get('cpu_sec_per_query', 0.0):.3f} |", ""]
    if rep["failures"]:
        L += ["Failures:", "", "| query | reason |", "|---|---|"]
        L += [f"| {f['name']} | {f['reason']} |" for f in rep["failures"]]
        L.append("")
    return "\n".join(L)


def evaluate_project(project, ablation: str = "default", **_) -> dict:
    """Entry point used by ``gtkit evaluate`` (one per report type in gtkit.evaluate)."""
    return evaluate(project, ablation)
