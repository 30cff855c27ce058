"""``gtkit run SITE``: every stage that can run on what a project holds, in order, then a summary.

    sfm_reference   SfM of the reference block, georegistered          gtkit sfm DIR --block reference
    model           the reference model, when none was imported         gtkit model build DIR
    sfm_queries     one block per query sequence                        gtkit sfm DIR --block queries
    register        pseudo-GT poses of the query photos                 gtkit register DIR
    report          pseudo-GT quality report                            gtkit report DIR
    export_dsm, export_ortho, export_mesh                               gtkit export dsm|ortho|mesh DIR
    overlays        the model drawn over each posed photo               gtkit overlay DIR
    render_db       the localization database                           gtkit render-db DIR
    localize        every query photo against the database              gtkit localize DIR
    track           targets from zoom-photo detections                  gtkit track calibrate DIR; gtkit track DIR
    export_coords   cameras, GCPs and tracks as CSV / GeoJSON / geo.txt  gtkit export coords DIR (last: it
                    exports the tracks too)

A stage whose input is absent (no query sequences, no model, no detections ...) is skipped with one
line saying why; a stage that fails (:class:`GtkitError`) stops the run with that line, naming the
stage. Every stage resumes as it does on its own (``work/<stage>/stage.json``), so a second run of
a finished project re-reads the outputs and prints the same summary. Settings: ``project.toml``
sections over the stages' defaults (:mod:`gtkit.settings`), as each subcommand resolves them.

The summary (also ``reports/run.json``) holds what a site without truth can state: photos
registered, georegistration residuals and GPS quality (``reports/reference.json``), pseudo-GT photos
registered and their stated sigma, photos localized, targets located, and seconds per stage, and
``problems``: the sequences a stage could not place (they need clicks, or photos), each with its reason.
This module is the library side of ``gtkit run`` (gtkit/commands/run.py parses and prints).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import GtkitError
from .io.atomic import write_json
from .logs import write_traceback
from .project import STAGE_RECORD, Project
from .sfm import registration_record as record

log = logging.getLogger(__name__)

STAGES = ("sfm_reference", "model", "sfm_queries", "register", "report", "export_dsm", "export_ortho",
          "export_mesh", "overlays", "render_db", "localize", "track", "export_coords")
# the stage records (work/<glob>/stage.json) that tell whether a stage ran or was up to date
RECORDS = {"sfm_reference": "sfm_reference", "model": "model", "sfm_queries": "sfm_queries/*", "register": "register",
           "export_dsm": "export_dsm", "export_ortho": "export_ortho", "export_mesh": "export_mesh_*",
           "export_coords": "export_coordinates", "render_db": "render_db", "localize": "localize",
           "track": "track"}
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


# --- what the project holds ------------------------------------------------------------------

def model_state(project: Project) -> tuple[str, Path | None]:
    """(``none`` | ``built`` | ``imported``, the model's path). ``imported`` is any model that
    ``gtkit model build`` did not write (``gtkit import model`` or files placed in model/);
    a built one is rebuilt when its reference block changed (the build stage's own resume)."""
    from .export.sources import reference_model

    try:
        path = reference_model(project.paths)
    except GtkitError:
        return "none", None
    built = project.config.get("model", {})
    imported = project.config.get("imports", {}).get("model")
    if built.get("source") == "built" and not (imported and str(imported.get("when", "")) > str(built.get("when", ""))):
        return "built", path
    return "imported", path


def _record_time(project: Project, name: str) -> tuple | None:
    """When the stage's record(s) were last written (None: no record); unchanged = up to date."""
    if name not in RECORDS:
        return None
    recs = sorted(project.paths.work.glob(f"{RECORDS[name]}/{STAGE_RECORD}"))   # a sequence's, a format's
    times = tuple(r.stat().st_mtime_ns for r in recs if r.is_file())
    return times or None


def _zoom_photos(project: Project) -> int:
    q = project.paths.query_images
    return sum(1 for f in q.glob("*/*") if f.stem.upper().endswith("_Z")) if q.is_dir() else 0


# --- the stages: each returns a dict for the summary, or raises Skip(reason) -------------------

class Skip(Exception):
    """A stage that cannot run on what the project holds; the message says why (one line)."""


def _sfm_settings(project):
    from .settings import resolve
    from .sfm.blocks import SfmSettings

    return resolve(SfmSettings(), "sfm", project)


def _on_cluster(opts):
    """The executor for the SfM's features + matching and the model's depth maps: a Dask cluster when
    the run was given one (``--executor dask``), else None (in the stage's own process, as ``gtkit sfm``
    and ``gtkit model build`` run by default); render-db and localize use ``opts.executor`` whatever it is."""
    ex = opts.executor
    return ex if ex is not None and getattr(ex, "kind", None) == "dask" else None


def st_sfm_reference(project, opts):
    from .sfm.blocks import run_reference

    r = run_reference(project, _sfm_settings(project), executor=_on_cluster(opts))
    return {"n_registered": r.get("n_registered"), "n_images": r.get("n_images")}


def st_model(project, opts):
    from .model.build import run
    from .model.settings import ModelSettings
    from .settings import resolve

    state, path = model_state(project)
    if state == "imported":
        raise Skip(f"a model was imported or delivered ({_rel(project, path)}); not building one "
                   "(`gtkit model build SITE --use` builds one and makes it the project's)")
    r = run(project, resolve(ModelSettings(), "model_build", project), executor=_on_cluster(opts))
    from .view.model import prepare_cache

    prepare_cache(project)          # the 3D view's decimated copy, as `gtkit model build` makes it
    return {"triangles": r.get("triangles"), "photos": r.get("photos"), "depth_maps": r.get("depth_maps")}


def st_sfm_queries(project, opts):
    from .sfm.blocks import run_queries

    if not project.paths.query_sequences():
        raise Skip("no query sequences (gtkit init --queries)")
    res = run_queries(project, _sfm_settings(project), executor=_on_cluster(opts))
    return {seq: ({"error": r["error"]} if "error" in r else {"n_registered": r["n_registered"], "n_images": r["n_images"]})
            for seq, r in res.items()}


def st_register(project, opts):
    from .settings import resolve
    from .sfm.register import RegisterSettings, run

    if not project.paths.query_sequences():
        raise Skip("no query sequences to register")
    r = run(project, resolve(RegisterSettings(), "register", project))
    return {"n_registered": r.get("n_registered"), "n_images": r.get("n_images"),
            "errors": {s: i.get("error") for s, i in record.sequences(r).items() if not record.is_registered(i)}}


def st_report(project, opts):
    from .evaluate.gt_report import run

    r = run(project)
    return {"n_registered": r.get("n_registered"), "n_images": r.get("n_images")}


def _need_model(project):
    state, path = model_state(project)
    if state == "none":
        raise Skip("no reference model (gtkit model build, or gtkit import model)")
    return path


def st_export_dsm(project, opts):
    from .export import dsm
    from .settings import resolve

    _need_model(project)
    return {"file": _rel(project, dsm.run(project, resolve(dsm.DsmSettings(), "export_dsm", project)))}


def st_export_ortho(project, opts):
    from .export import ortho
    from .settings import resolve

    _need_model(project)
    return {"file": _rel(project, ortho.run(project, resolve(ortho.OrthoSettings(), "export_ortho", project)))}


def st_export_mesh(project, opts):
    from .export import mesh_export
    from .settings import resolve

    _need_model(project)
    return {"file": _rel(project, mesh_export.run(project, resolve(mesh_export.MeshExportSettings(), "export_mesh",
                                                                   project)))}


def st_export_coords(project, opts):
    from .export import coordinates
    from .settings import resolve

    P = project.paths
    if not (coordinates.default_pose_files(project) or P.gcp_list.is_file() or P.tracks.is_file()):
        raise Skip("no poses, GCPs or tracks to export")
    files = coordinates.run(project, resolve(coordinates.CoordinatesSettings(), "export_coordinates", project))
    return {"files": sorted(files)}


def st_overlays(project, opts):
    from .render.overlay import OverlaySettings, default_pose_file, reference_block_pose_file, write_overlays
    from .settings import resolve

    _need_model(project)
    P = project.paths
    poses = None if default_pose_file(P) is not None else reference_block_pose_file(P)
    if default_pose_file(P) is None and poses is None:
        raise Skip("no poses to overlay (no reference block, no pseudo-GT)")
    s = write_overlays(P.root, poses, None, resolve(OverlaySettings(), "overlay", project))
    return {"_up_to_date": not s.get("n_rendered"),
            "n_images": len(s.get("images", [])), "median_misalignment_px": s.get("median_misalignment_px"),
            "median_edge_distance_px": s.get("median_edge_distance_px"),
            "poses": "reference block only (no pseudo-GT poses)" if poses is not None else "pseudo-GT + reference block"}


def _query_names(project):
    from .localize.localize import query_names, settings_for
    from .settings import resolve

    s = resolve(settings_for("default"), "localize", project)
    return s, query_names(project, s)


def st_render_db(project, opts):
    from .localize import database
    from .localize.executors import ExecutorSettings
    from .settings import resolve

    _need_model(project)
    if not _query_names(project)[1]:
        raise Skip("no query photos to localize")
    out = database.run(project, resolve(database.RenderDbSettings(), "render_db", project),
                       opts.executor or ExecutorSettings())
    rec = json.loads((out / STAGE_RECORD).read_text()).get("summary", {})
    return {"n_views": rec.get("n_views"), "n_kept": rec.get("n_kept")}


def st_localize(project, opts):
    from .localize import localize
    from .localize.executors import ExecutorSettings

    s, names = _query_names(project)
    if not names:
        raise Skip("no query photos to localize")
    if not (project.paths.stage("render_db") / STAGE_RECORD).is_file():
        raise Skip("no rendered database (render_db did not run)")
    out = localize.run(project, s, executor=opts.executor or ExecutorSettings())
    st = json.loads((out / "status.json").read_text())
    return {"n_localized": st.get("n_localized"), "n_queries": st.get("n_queries")}


def st_track(project, opts):
    from .settings import resolve
    from .track import calibrate
    from .track.tracker import TrackSettings, run

    P = project.paths
    s = resolve(TrackSettings(), "track", project)
    if not _zoom_photos(project):
        raise Skip("no zoom photos (*_Z) in the query sequences")
    det = Path(s.detections) if s.detections else P.detections
    if not det.exists():
        raise Skip(f"no target detections ({_rel(project, det)}: click targets with gtkit annotate)")
    poses = Path(s.poses) if s.poses else P.stage("localize") / "poses.txt"
    if not poses.is_file():
        raise Skip(f"no wide-camera poses ({_rel(project, poses)})")
    if not P.cameras.is_file():
        raise Skip("no cameras.txt (the rig calibration takes the wide camera's calibration from it)")
    if not P.dsm.is_file():
        raise Skip("no DSM (export_dsm did not run)")
    calibrate.run(project)
    r = run(project, s)
    return {"n_located": r.get("n_located"), "n_detections": r.get("n_detections"),
            "median_sigma_h_m": r.get("median_sigma_h_m")}


RUNNERS: dict[str, Callable] = {name: globals()[f"st_{name}"] for name in STAGES}


def _rel(project: Project, p) -> str:
    p = Path(p)
    try:
        return str(p.resolve().relative_to(project.paths.root.resolve()))
    except ValueError:
        return str(p)


# --- the run ---------------------------------------------------------------------------------

def run(root: str | Path, opts: RunOptions | None = None, progress: Callable[[StageResult], None] | None = None,
        starting: Callable[[str], None] | None = None) -> dict:
    """Run the stages (see the module doc); returns the summary, also written to ``reports/run.json``.
    ``starting(name)`` is called before a stage runs, ``progress(result)`` after each stage.
    A stage's :class:`GtkitError` is raised again with the stage named; the summary of the stages
    before it is written first."""
    opts = opts or RunOptions()
    project = Project.load(root)
    todo = selected(opts)
    results: list[StageResult] = []
    t_all = time.time()
    failed = None
    for name in STAGES:
        if name not in todo:
            results.append(StageResult(name, "not selected"))
            continue
        if starting:
            starting(name)
        before = _record_time(project, name)
        t0 = time.time()
        try:
            info = RUNNERS[name](project, opts) or {}
        except Skip as e:
            res = StageResult(name, "skipped", round(time.time() - t0, 1), why=str(e))
        except GtkitError as e:
            failed = GtkitError(f"stage {name} failed: {e}")
            res = StageResult(name, "failed", round(time.time() - t0, 1), why=str(e))
        except Exception as e:  # a bug, not bad input: one line here, the traceback in a file
            where = write_traceback(project.paths.work / "errors" / f"{name}.txt", f"stage {name}")
            why = f"unexpected {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}".rstrip(": ")
            failed = GtkitError(f"stage {name} failed ({why}); the traceback is in {where} (please report it)")
            failed.traceback_file = where
            res = StageResult(name, "failed", round(time.time() - t0, 1), why=why)
        else:
            after = _record_time(project, name)
            status = "up to date" if (before is not None and after == before) or info.pop("_up_to_date", False) else "ran"
            res = StageResult(name, status, round(time.time() - t0, 1), info=info)
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


def _load(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


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
    ref = _load(P.reports / "reference.json")
    if ref:
        geo, held = ref.get("georegistration") or {}, ref.get("held_by_positions") or {}
        out["reference"] = {
            "n_registered": ref.get("n_registered"), "n_images": ref.get("n_images"), "n_models": ref.get("n_models"),
            "mean_reproj_px": ref.get("mean_reproj_px"),
            "georegistered_with": geo.get("fitted_to") or geo.get("used"),
            "tilt_from": (geo.get("fit") or {}).get("tilt_from"),
            "absolute_accuracy_h_m": (geo.get("gps_quality") or {}).get("absolute_accuracy_h_m"),
            "absolute_accuracy_v_m": (geo.get("gps_quality") or {}).get("absolute_accuracy_v_m"),
            "altitude_drift_m": (geo.get("gps_quality") or {}).get("altitude_drift_m"),
            "n_inliers": geo.get("n_inliers"), "rmse_m": geo.get("rmse_m"),
            "gcp_median_err_m": geo.get("gcp_median_err_m"), "gcp_rmse_m": geo.get("gcp_rmse_m"),
            "checkpoint_median_err_m": geo.get("checkpoint_median_err_m"),
            "gps_sigma_h_m": held.get("sigma_h_m"), "gps_sigma_v_m": held.get("sigma_v_m"),
            "gps_residual_median_m": (held.get("residual_median_m") or {}).get("after")}
    state, path = model_state(project)
    out["model"] = {"source": state, "path": _rel(project, path) if path else None}
    qsum = _load(P.stage("sfm_queries") / "summary.json")
    if qsum:
        out["query_blocks"] = {s: ({"error": b["error"]} if "error" in b else
                                   {"n_registered": b.get("n_registered"), "n_images": b.get("n_images")})
                               for s, b in qsum.items()}
    reg = _load(P.stage("register") / "registration.json")
    if reg:
        imgs = (reg.get("images") or {}).values()
        out["pseudo_gt"] = {"n_registered": reg.get("n_registered"), "n_images": reg.get("n_images"),
                            "median_sigma_pos_m": _median(i.get("sigma_pos_m") for i in imgs),
                            "median_sigma_rot_deg": _median(i.get("sigma_rot_deg") for i in imgs),
                            "median_reproj_px": reg.get("median_reproj_px"),
                            "median_tiepoint_reproj_px": reg.get("median_tiepoint_reproj_px"),
                            "registered_by": {s: record.short(i) for s, i in record.sequences(reg).items()
                                              if record.is_registered(i)},
                            "errors": {s: i.get("error") for s, i in record.sequences(reg).items()
                                       if not record.is_registered(i)}}
    ali = _load(P.reports / "overlays" / "alignment.json")
    if ali:
        out["overlays"] = {k: ali.get(k) for k in ("median_misalignment_px", "median_edge_distance_px")}
        out["overlays"]["n_images"] = len(ali.get("images") or {})
    loc = _load(P.stage("localize") / "status.json")
    if loc:
        out["localization"] = {"n_localized": loc.get("n_localized"), "n_queries": loc.get("n_queries"),
                               "database_views": loc.get("database_views")}
    tr = _load(P.stage("track") / "summary.json")
    if tr:
        out["tracking"] = {k: tr.get(k) for k in ("n_located", "n_detections", "median_sigma_h_m")}
    placed = {q for q, by in ((out.get("pseudo_gt") or {}).get("registered_by") or {}).items() if by}
    # a query block whose SfM failed is a problem only where the registration could not place its photos either
    out["problems"] = [f"query block {q}: {b['error']}" for q, b in (out.get("query_blocks") or {}).items()
                       if "error" in b and q not in placed] + [f"pseudo-GT {q}: {e}" for q, e in
                                           ((out.get("pseudo_gt") or {}).get("errors") or {}).items()]
    out["exports"] = sorted(_rel(project, f) for f in (P.dsm, P.ortho, P.mesh_export, P.coordinates) if f.exists())
    out["seconds"] = {r.name: r.seconds for r in results if r.status not in ("not selected",)}
    if seconds is not None:
        out["seconds_total"] = seconds
    return out
