"""``gtkit run SITE``: the stage table (:mod:`gtkit.stages`: every stage, its settings, what it
reads and writes, its command) run in order on what a project holds, then a summary.

A stage whose input is absent (no query sequences, no model, no detections ...) is skipped with one
line saying why; a stage that fails (:class:`GtkitError`) stops the run with that line, naming the
stage, except a validation stage (``Stage.validation``: the database, localization), whose failure
is listed as a problem (exit 1) while the stages after it still run: a run whose deliverables are
all written does not end in an error for a check of them (issue 58). Every stage resumes as it does on its own (``work/<stage>/stage.json``), so a second run of
a finished project re-reads the outputs and prints the same summary. Settings: each stage's from
:func:`gtkit.stages.settings_for` (``project.toml`` over the defaults), as its own command resolves them.

The summary (also ``reports/run.json``) holds what a site without truth can state: photos
registered, georegistration residuals and GPS quality (``reports/reference.json``), pseudo-GT photos
registered and their stated sigma, photos localized, targets located, and seconds per stage, and
``problems``: the sequences a stage could not place (they need clicks, or photos), each with its reason.
This module is the library side of ``gtkit run`` (gtkit/commands/run.py parses and prints).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import GtkitError
from .io.atomic import read_json_object, write_json
from .logs import exception_words, write_traceback
from .write_errors import machine_cause
from .project import Project
from .project_lock import project_lock
from .sfm import registration_record as record
from .stages import NAMES as STAGES
from .stages import STAGE, Context, Skip, model_state, record_time, rel, settings_for

log = logging.getLogger(__name__)

SUMMARY_FILE = "run.json"


@dataclass
class RunOptions:
    start: str | None = None        # --from: first stage to run
    until: str | None = None        # --until: last stage to run
    skip: tuple[str, ...] = ()      # --skip: stages not to run
    executor: object = None         # gtkit.localize.executors.ExecutorSettings for render-db / localize


@dataclass
class StageResult:
    name: str
    status: str                     # ran | up to date | skipped | not selected
    seconds: float = 0.0
    why: str = ""                   # the reason a stage was skipped
    info: dict = field(default_factory=dict)


def selected(opts: RunOptions) -> list[str]:
    """The stages ``--from`` / ``--until`` / ``--skip`` leave in, in order; unknown names refused."""
    for name in [opts.start, opts.until, *opts.skip]:
        if name is not None and name not in STAGES:
            raise GtkitError(f"unknown stage {name!r} (stages: {', '.join(STAGES)})")
    i = STAGES.index(opts.start) if opts.start else 0
    j = STAGES.index(opts.until) if opts.until else len(STAGES) - 1
    if i > j:
        raise GtkitError(f"--from {opts.start} comes after --until {opts.until} (stages: {', '.join(STAGES)})")
    return [s for s in STAGES[i:j + 1] if s not in opts.skip]


# --- the run ---------------------------------------------------------------------------------

def run(root: str | Path, opts: RunOptions | None = None, progress: Callable[[StageResult], None] | None = None,
        starting: Callable[[str], None] | None = None) -> dict:
    """Run the stages (see the module doc); returns the summary, also written to ``reports/run.json``.
    ``starting(name)`` is called before a stage runs, ``progress(result)`` after each stage.
    A stage's :class:`GtkitError` is raised again with the stage named; the summary of the stages
    before it is written first. Holds the project's lock throughout (:mod:`gtkit.project_lock`;
    re-entrant: ``gtkit run`` and the main job hold it already): another writer is refused."""
    with project_lock(root):
        return _run(root, opts, progress, starting)


def _unexpected(project: Project, name: str, e: Exception) -> GtkitError:
    """The error that stops the run at stage ``name`` for an exception that is not a GtkitError:
    the machine's cause where it is one (gtkit.write_errors: a full disk, a read-only folder, a
    file removed meanwhile), else a bug: its traceback goes to ``work/errors/<stage>.txt``."""
    cause = machine_cause(e)
    if cause is not None:
        failed = GtkitError(f"stage {name} failed: {cause}")
        failed.why = cause
        return failed
    where = write_traceback(project.paths.work / "errors" / f"{name}.txt", f"stage {name}")
    why = f"unexpected {exception_words(e)}"
    failed = GtkitError(f"stage {name} failed ({why}); the traceback is in {where} (please report it)")
    failed.traceback_file, failed.why = where, why
    return failed


def _run(root, opts, progress, starting) -> dict:
    opts = opts or RunOptions()
    project = Project.load(root)
    todo = selected(opts)
    check_photos(project, todo)
    results: list[StageResult] = []
    t_all = time.time()
    failed = None
    for name in STAGES:
        if name not in todo:
            results.append(StageResult(name, "not selected"))
            continue
        if starting:
            starting(name)
        before = record_time(project, name)
        t0 = time.time()
        try:
            info = STAGE[name].run(project, settings_for(name, project), Context(opts.executor)) or {}
        except Skip as e:
            res = StageResult(name, "skipped", round(time.time() - t0, 1), why=str(e))
        except GtkitError as e:
            failed = GtkitError(f"stage {name} failed: {e}")
            res = StageResult(name, "failed", round(time.time() - t0, 1), why=str(e))
        except Exception as e:  # the machine's (a full disk ...) in one line; a bug's traceback in a file
            failed = _unexpected(project, name, e)
            res = StageResult(name, "failed", round(time.time() - t0, 1), why=failed.why)
        else:
            after = record_time(project, name)
            status = "up to date" if (before is not None and after == before) or info.pop("_up_to_date", False) else "ran"
            res = StageResult(name, status, round(time.time() - t0, 1), info=info)
        if failed is not None and STAGE[name].validation:   # a check failed: a problem, not the run's end
            failed = None
        project = Project.load(root)    # a stage may have written project.toml (model build, import)
        results.append(res)
        if progress:
            progress(res)
        if failed is not None:
            break
    summary = collect(project, results, round(time.time() - t_all, 1))
    from .project import relative_paths

    write_json(project.paths.reports / SUMMARY_FILE, relative_paths(summary, project.paths.root))
    if failed is not None:
        raise failed
    return summary


def check_photos(project: Project, todo: list[str]) -> None:
    """Every photo the chosen stages read, looked at before the first stage runs: all bad ones (in
    every folder) named in one error (:mod:`gtkit.input_check`), not one stage at a time."""
    from .input_check import require_good_photos

    folders = {r[len("images/"):].strip("/") for n in todo for r in STAGE[n].reads if r.startswith("images/")}
    require_good_photos(project, tuple(sorted(folders)))


def _median(values) -> float | None:
    v = [float(x) for x in values if x is not None]
    return float(np.median(v)) if v else None


def collect(project: Project, results: list[StageResult], seconds: float | None = None) -> dict:
    """What the project's outputs state (no truth): read from the stages' files, so a run that
    only found finished stages states the same as the run that made them."""
    P = project.paths
    out: dict = {"project": str(P.root), "stages": {r.name: {"status": r.status, "seconds": r.seconds,
                                                              **({"why": r.why} if r.why else {})}
                                                     for r in results}}
    ref = read_json_object(P.reports / "reference.json")
    if ref:
        geo, held = ref.get("georegistration") or {}, ref.get("held_by_positions") or {}
        out["reference"] = {
            "n_registered": ref.get("n_registered"), "n_images": ref.get("n_images"), "n_models": ref.get("n_models"),
            "mean_reproj_px": ref.get("mean_reproj_px"),
            "georegistered_with": geo.get("fitted_to") or geo.get("used"),
            "tilt_from": (geo.get("fit") or {}).get("tilt_from"),
            "claimed_accuracy": geo.get("claimed_accuracy"),
            "absolute_accuracy_h_m": (geo.get("gps_quality") or {}).get("absolute_accuracy_h_m"),
            "absolute_accuracy_v_m": (geo.get("gps_quality") or {}).get("absolute_accuracy_v_m"),
            "altitude_drift_m": (geo.get("gps_quality") or {}).get("altitude_drift_m"),
            "n_inliers": geo.get("n_inliers"), "rmse_m": geo.get("rmse_m"),
            "gcp_median_err_m": geo.get("gcp_median_err_m"), "gcp_rmse_m": geo.get("gcp_rmse_m"),
            "checkpoint_median_err_m": geo.get("checkpoint_median_err_m"),
            "gps_sigma_h_m": held.get("sigma_h_m"), "gps_sigma_v_m": held.get("sigma_v_m"),
            "gps_residual_median_m": (held.get("residual_median_m") or {}).get("after")}
    state, path = model_state(project)
    out["model"] = {"source": state, "path": rel(project, path) if path else None}
    qsum = read_json_object(P.stage("sfm_queries") / "summary.json")
    if qsum:
        out["query_blocks"] = {s: ({"error": b["error"]} if "error" in b else
                                   {"n_registered": b.get("n_registered"), "n_images": b.get("n_images")})
                               for s, b in qsum.items()}
    reg = record.read_registration(P.registration)
    if reg:
        imgs = [i for i in (reg.get("images") or {}).values() if "unverified" not in i]   # the results
        out["pseudo_gt"] = {"n_registered": reg.get("n_registered"), "n_images": reg.get("n_images"),
                            "n_unverified": reg.get("n_unverified") or 0,
                            "median_sigma_pos_m": _median(i.get("sigma_pos_m") for i in imgs),
                            "median_sigma_rot_deg": _median(i.get("sigma_rot_deg") for i in imgs),
                            "median_reproj_px": reg.get("median_reproj_px"),
                            "median_tiepoint_reproj_px": reg.get("median_tiepoint_reproj_px"),
                            "registered_by": {s: record.outcome(i) for s, i in record.sequences(reg).items()
                                              if record.is_registered(i)},
                            "registered_how": {s: record.short(i) for s, i in record.sequences(reg).items()
                                               if record.is_registered(i)},
                            "errors": {s: i.get("error") for s, i in record.sequences(reg).items()
                                       if not record.is_registered(i)}}
    ali = read_json_object(P.reports / "overlays" / "alignment.json")
    if ali:
        out["overlays"] = {k: ali.get(k) for k in ("median_misalignment_px", "median_edge_distance_px")}
        out["overlays"]["n_images"] = len(ali.get("images") or {})
    loc = read_json_object(P.stage("localize") / "status.json")
    if loc:
        out["localization"] = {"n_localized": loc.get("n_localized"), "n_queries": loc.get("n_queries"),
                               "database_views": loc.get("database_views")}
    tr = read_json_object(P.stage("track") / "summary.json")
    if tr:
        out["tracking"] = {k: tr.get(k) for k in ("n_located", "n_detections", "median_sigma_h_m")}
    placed = {q for q, by in ((out.get("pseudo_gt") or {}).get("registered_by") or {}).items() if by}
    # a query block whose SfM failed is a problem only where the registration could not place its photos either
    out["problems"] = [f"query block {q}: {b['error']}" for q, b in (out.get("query_blocks") or {}).items()
                       if "error" in b and q not in placed] + [f"pseudo-GT {q}: {e}" for q, e in
                                           ((out.get("pseudo_gt") or {}).get("errors") or {}).items()]
    if (out.get("pseudo_gt") or {}).get("n_unverified"):   # poses without sigma: not results (issue 55)
        out["problems"].append(f"pseudo-GT: {out['pseudo_gt']['n_unverified']} query photos unverified (no usable sigma; "
                               "why: reports/gt_report.md, 'Unverified photos')")
    out["problems"] += [f"stage {r.name} failed: {r.why}" for r in results if r.status == "failed"]
    out["exports"] = sorted(rel(project, f) for f in (P.dsm, P.ortho, P.mesh_export, P.coordinates) if f.exists())
    out["seconds"] = {r.name: r.seconds for r in results if r.status not in ("not selected",)}
    if seconds is not None:
        out["seconds_total"] = seconds
    return out
