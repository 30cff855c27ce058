"""The stage table: every stage of a project, in order, in one place.

Each :class:`Stage` names its settings section(s) in ``project.toml`` and their type, what it reads
and writes (project-relative paths), the command that runs it alone, why it would be skipped, and
its run function, which takes its settings as a required argument. Every entry point goes through
this table:

- ``gtkit run SITE`` (:mod:`gtkit.run_site`) is the loop over :data:`STAGES` plus its summary;
- each stage command (``gtkit sfm``, ``gtkit export dsm`` ...) is :func:`settings_for` with its flags
  plus the stage's own function;
- the README's main job (``python -m pipelines.full``) is ``gtkit run``'s loop plus the steps that
  need the sample's truth (the sample, simulated detections, evaluation).

:func:`settings_for` is the only place settings resolve: command-line flag > ``project.toml``
section > the settings class's defaults (:func:`gtkit.settings.resolve`; the classes validate).

    stage           settings section(s)              command
    sfm_reference   [sfm]                            gtkit sfm DIR --block reference
    model           [model_build]                    gtkit model build DIR
    sfm_queries     [sfm]                            gtkit sfm DIR --block queries
    register        [register]                       gtkit register DIR
    report          [report]                         gtkit report DIR
    export_dsm      [export_dsm]                     gtkit export dsm DIR
    export_ortho    [export_ortho]                   gtkit export ortho DIR
    export_mesh     [export_mesh]                    gtkit export mesh DIR
    overlays        [overlay]                        gtkit overlay DIR
    render_db       [render_db]                      gtkit render-db DIR
    localize        [localize]                       gtkit localize DIR
    track           [rig], [track]                   gtkit track calibrate DIR; gtkit track DIR
    export_coords   [export_coordinates]             gtkit export coords DIR   (last: it exports the tracks too)
"""
from __future__ import annotations

import importlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .errors import GtkitError
from .project import STAGE_RECORD, Project, read_stage_record
from .settings import resolve
from .sfm import registration_record as record


class Skip(Exception):
    """A stage that cannot run on what the project holds; the message says why (one line)."""


@dataclass
class Context:
    """What a run hands every stage besides its settings: where fan-out work runs."""
    executor: object = None   # gtkit.localize.executors.ExecutorSettings (None: each stage's default)


def _load(ref: str):
    """``'package.module:Name'`` -> the object (stages import their modules when they run)."""
    mod, _, name = ref.partition(":")
    return getattr(importlib.import_module(mod), name)


@dataclass(frozen=True)
class Stage:
    name: str
    what: str                                   # one line: what it makes
    command: str                                # the command that runs it alone
    sections: tuple[tuple[str, str], ...]       # (project.toml section, 'module:SettingsFactory')
    reads: tuple[str, ...]                      # project-relative paths it reads
    writes: tuple[str, ...]                     # project-relative paths it writes (a folder ends in /; * a glob)
    run: Callable[[Project, Any, Context], dict] = field(repr=False)
    record: str | None = None                   # work/<record>/stage.json: whether it ran or was up to date
    # a check of the pseudo-GT rather than a deliverable (the database, localization): its failure is
    # a problem of the run (exit 1), not the run's end: the later stages still run and export
    validation: bool = False

    def check_inputs(self, project: Project) -> None:
        """Every photo the stage reads (its ``images/...`` reads) looked at before any is used; all bad
        ones named in one error (:func:`gtkit.input_check.require_good_photos`, about 1 ms a photo)."""
        folders = tuple(r[len("images/"):].strip("/") for r in self.reads if r.startswith("images/"))
        if folders:
            from .input_check import require_good_photos

            require_good_photos(project, folders)

    def defaults(self) -> Any:
        """The settings object(s) of the stage's classes, before project.toml and flags."""
        made = {sec: _load(ref)() for sec, ref in self.sections}
        return next(iter(made.values())) if len(made) == 1 else made


def settings_for(stage: str | Stage, project: Project | None, cli: dict | None = None, base: Any = None) -> Any:
    """The stage's settings: ``cli`` ({'a.b': value}, None values ignored) > ``project.toml``
    section > defaults (``base``: other defaults of the same class, e.g. a localization ablation's).
    A stage with one section gets its settings object; one with several a dict ``{section:
    settings}``, its flags named ``'section.key'``. ``project`` None: no project.toml (a file
    outside a project)."""
    if not isinstance(stage, Stage) and stage not in STAGE:
        raise GtkitError(f"unknown stage {stage!r} (stages: {', '.join(STAGE)})")
    st = stage if isinstance(stage, Stage) else STAGE[stage]
    if len(st.sections) == 1:
        sec, ref = st.sections[0]
        return resolve(base if base is not None else _load(ref)(), sec, project, cli)
    out = {}
    for sec, ref in st.sections:
        mine = {k.split(".", 1)[1]: v for k, v in (cli or {}).items() if k.split(".", 1)[0] == sec}
        out[sec] = resolve(_load(ref)(), sec, project, mine)
    return out


# --- what the project holds ------------------------------------------------------------------

def rel(project: Project, p) -> str:
    p = Path(p)
    try:
        return str(p.resolve().relative_to(project.paths.root.resolve()))
    except ValueError:
        return str(p)


def model_state(project: Project) -> tuple[str, Path | None]:
    """(``none`` | ``built`` | ``imported``, the model's path). ``imported`` is any model that
    ``gtkit model build`` did not write (``gtkit import model`` or files placed in model/);
    a built one is rebuilt when its reference block changed (the build stage's own resume)."""
    from .model_files import reference_model

    try:
        path = reference_model(project.paths)
    except GtkitError:
        return "none", None
    built = project.config.get("model", {})
    imported = project.config.get("imports", {}).get("model")
    if built.get("source") == "built" and not (imported and str(imported.get("when", "")) > str(built.get("when", ""))):
        return "built", path
    return "imported", path


def need_model(project: Project) -> Path:
    state, path = model_state(project)
    if state == "none":
        raise Skip("no reference model (gtkit model build, or gtkit import model)")
    return path


def record_time(project: Project, name: str) -> tuple | None:
    """When the stage's record(s) were last written (None: no record); unchanged = up to date."""
    glob = STAGE[name].record
    if glob is None:
        return None
    recs = sorted(project.paths.work.glob(f"{glob}/{STAGE_RECORD}"))   # a sequence's, a format's
    times = tuple(r.stat().st_mtime_ns for r in recs if r.is_file())
    return times or None


def zoom_photos(project: Project) -> int:
    q = project.paths.query_images
    return sum(1 for f in q.glob("*/*") if f.stem.upper().endswith("_Z")) if q.is_dir() else 0


def on_cluster(ctx: Context):
    """The executor for the SfM's features + matching and the model's depth maps: a Dask cluster when
    the run was given one (``--executor dask``), else None (in the stage's own process, as ``gtkit sfm``
    and ``gtkit model build`` run by default); render-db and localize use ``ctx.executor`` whatever it is."""
    ex = ctx.executor
    return ex if ex is not None and getattr(ex, "kind", None) == "dask" else None


def _executor(ctx: Context):
    from .localize.executors import ExecutorSettings

    return ctx.executor or ExecutorSettings()


# --- the stages: each takes (project, settings, context), returns a dict for the summary or raises Skip

def _sfm_reference(project, s, ctx):
    from .sfm.blocks import run_reference

    r = run_reference(project, s, executor=on_cluster(ctx))
    out = {"n_registered": r.get("n_registered"), "n_images": r.get("n_images")}
    if (r.get("mapping") or {}).get("reused"):   # a GCP click / geo.txt edit: the georegistration alone
        out["mapping"] = "reused (georegistration only)"
    return out


def _model(project, s, ctx):
    from .model.build import run
    from .view.model import prepare_cache

    state, path = model_state(project)
    if state == "imported":
        raise Skip(f"a model was imported or delivered ({rel(project, path)}); not building one "
                   "(`gtkit model build SITE --use` builds one and makes it the project's)")
    from .model.build import NoStereo

    try:
        r = run(project, s, executor=on_cluster(ctx))
    except NoStereo as e:   # the photos cannot make a model: the pseudo-GT still can (issue 55)
        raise Skip(f"no model can be built ({e}): the pseudo-GT's automatic ties stay on the reference SfM's "
                   "points; the DSM, orthophoto, overlays and localization need a model (gtkit import model)") from None
    prepare_cache(project)          # the 3D view's decimated copy, as `gtkit model build` makes it
    return {"triangles": r.get("triangles"), "photos": r.get("photos"), "depth_maps": r.get("depth_maps")}


def _sfm_queries(project, s, ctx):
    from .sfm.blocks import run_queries

    if not project.paths.query_sequences():
        raise Skip("no query sequences (gtkit init --queries)")
    res = run_queries(project, s, executor=on_cluster(ctx))
    return {seq: ({"error": r["error"]} if "error" in r else {"n_registered": r["n_registered"], "n_images": r["n_images"]})
            for seq, r in res.items()}


def _register(project, s, ctx):
    from .sfm.register import run

    if not project.paths.query_sequences():
        raise Skip("no query sequences to register")
    r = run(project, s)
    return {"n_registered": r.get("n_registered"), "n_images": r.get("n_images"),
            "errors": {q: i.get("error") for q, i in record.sequences(r).items() if not record.is_registered(i)}}


def _report(project, s, ctx):
    from .evaluate.gt_report import run

    r = run(project, s)
    return {"n_registered": r.get("n_registered"), "n_images": r.get("n_images")}


def _export_dsm(project, s, ctx):
    from .export import dsm

    need_model(project)
    return {"file": rel(project, dsm.run(project, s))}


def _export_ortho(project, s, ctx):
    from .export import ortho

    need_model(project)
    return {"file": rel(project, ortho.run(project, s))}


def _export_mesh(project, s, ctx):
    from .export import mesh_export

    need_model(project)
    return {"file": rel(project, mesh_export.run(project, s))}


def _overlays(project, s, ctx):
    from .render.overlay import default_pose_file, reference_block_pose_file, write_overlays

    need_model(project)
    P = project.paths
    poses = None if default_pose_file(P) is not None else reference_block_pose_file(P)
    if default_pose_file(P) is None and poses is None:
        raise Skip("no poses to overlay (no reference block, no pseudo-GT)")
    r = write_overlays(P.root, poses, None, s)
    return {"_up_to_date": not r.get("n_rendered"),
            "n_images": len(r.get("images", [])), "median_misalignment_px": r.get("median_misalignment_px"),
            "median_edge_distance_px": r.get("median_edge_distance_px"),
            "poses": "reference block only (no pseudo-GT poses)" if poses is not None else "pseudo-GT + reference block"}


def _query_names(project, localize_settings):
    from .localize.reach import query_names

    return query_names(project, localize_settings)


def _render_db(project, s, ctx):
    from .localize import database

    need_model(project)
    loc = settings_for("localize", project)     # its priors choose the views the queries can reach
    if not _query_names(project, loc):
        raise Skip("no query photos to localize")
    out = database.run(project, s, _executor(ctx), localize_settings=loc)
    rec = read_stage_record(out).summary
    if rec.get("n_kept") == 0:
        raise Skip(empty_database(rec, s.min_valid_fraction))
    return {"n_views": rec.get("n_views"), "n_kept": rec.get("n_kept")}


def empty_database(rec: dict, min_valid: float) -> str:
    """Why the database holds no view, in one line (``rec``: render-db's record)."""
    g = rec.get("grid") or {}
    src = g.get("source") or {}
    return (f"no database view sees enough of the model (>= {min_valid:g} of the view): none of the "
            f"{rec.get('n_views')} views planned at heights {g.get('heights')} m ({src.get('heights', '-')}), "
            f"pitches {g.get('paper_pitches')} deg off nadir ({src.get('paper_pitches', '-')}); localization "
            "skipped ([render_db] heights / paper_pitches / anchor in project.toml plan others)")


def _localize(project, s, ctx):
    from .localize import localize

    if not _query_names(project, s):
        raise Skip("no query photos to localize")
    db = read_stage_record(project.paths.stage("render_db"))
    if db is None:
        raise Skip("no rendered database (render_db did not run)")
    if db.summary.get("n_kept") == 0:
        raise Skip("the rendered database holds no view (see render_db's line)")
    out = localize.run(project, s, executor=_executor(ctx))
    st = json.loads((out / "status.json").read_text())
    return {"n_localized": st.get("n_localized"), "n_queries": st.get("n_queries")}


def _track(project, s, ctx):
    from .track import calibrate
    from .track.tracker import run

    P = project.paths
    t = s["track"]
    if not zoom_photos(project):
        raise Skip("no zoom photos (*_Z) in the query sequences")
    det = Path(t.detections) if t.detections else P.detections
    if not det.exists():
        raise Skip(f"no target detections ({rel(project, det)}: click targets with gtkit annotate)")
    poses = Path(t.poses) if t.poses else P.localized_poses
    if not poses.is_file():
        raise Skip(f"no wide-camera poses ({rel(project, poses)})")
    if not P.cameras.is_file():
        raise Skip("no cameras.txt (the rig calibration takes the wide camera's calibration from it)")
    if not P.dsm.is_file():
        raise Skip("no DSM (export_dsm did not run)")
    calibrate.run(project, s["rig"])
    r = run(project, t)
    return {"n_located": r.get("n_located"), "n_detections": r.get("n_detections"),
            "median_sigma_h_m": r.get("median_sigma_h_m")}


def _export_coords(project, s, ctx):
    from .export import coordinates

    P = project.paths
    if not (coordinates.default_pose_files(project) or P.gcp_list.is_file() or P.tracks.is_file()):
        raise Skip("no poses, GCPs or tracks to export")
    return {"files": sorted(coordinates.run(project, s))}


STAGES: tuple[Stage, ...] = (
    # two steps with a fingerprint each (gtkit.sfm.georeg_step): the mapping (photos, cameras.txt, [sfm]) kept
    # in work/sfm_reference/mapped/, then the georegistration, which a GCP click or a geo.txt edit re-runs alone
    Stage("sfm_reference", "SfM of the reference block, georegistered", "gtkit sfm DIR --block reference",
          (("sfm", "gtkit.sfm.blocks:SfmSettings"),),
          ("images/reference/", "gcp_list.txt", "geo.txt", "cameras.txt"),
          ("work/sfm_reference/", "reports/reference.md", "reports/reference.json"), _sfm_reference, "sfm_reference"),
    Stage("model", "the reference model from the photos, when none was imported", "gtkit model build DIR",
          (("model_build", "gtkit.model.settings:ModelSettings"),),
          ("images/reference/", "work/sfm_reference/"), ("work/model/", "model/"), _model, "model"),
    Stage("sfm_queries", "one SfM block per query sequence", "gtkit sfm DIR --block queries",
          (("sfm", "gtkit.sfm.blocks:SfmSettings"),),
          ("images/queries/", "cameras.txt"), ("work/sfm_queries/",), _sfm_queries, "sfm_queries/*"),
    Stage("register", "pseudo-GT poses of the query photos (tie points, Sim(3), joint BA)", "gtkit register DIR",
          (("register", "gtkit.sfm.register:RegisterSettings"),),
          ("work/sfm_reference/", "work/sfm_queries/", "tiepoints.json", "model/"),
          ("work/register/",), _register, "register"),
    Stage("report", "the pseudo-GT quality report", "gtkit report DIR",
          (("report", "gtkit.evaluate.gt_report:ReportSettings"),),
          ("work/sfm_reference/", "work/sfm_queries/", "work/register/", "review.json"),
          ("reports/gt_report.json", "reports/gt_report.md", "reports/gt_pos_err.svg", "reports/gt_sigma.svg"), _report),
    Stage("export_dsm", "DSM GeoTIFF of the reference model", "gtkit export dsm DIR",
          (("export_dsm", "gtkit.export.dsm:DsmSettings"),), ("model/", "work/sfm_reference/"),
          ("exports/dsm.tif", "work/export_dsm/"),
          _export_dsm, "export_dsm"),
    Stage("export_ortho", "true orthophoto GeoTIFF (the reference photos over the filled DSM, seams blended; or the model)",
          "gtkit export ortho DIR", (("export_ortho", "gtkit.export.ortho:OrthoSettings"),),
          ("model/", "exports/dsm.tif", "work/sfm_reference/", "images/reference/"), ("exports/ortho.tif", "work/export_ortho/"),
          _export_ortho, "export_ortho"),
    Stage("export_mesh", "textured mesh in the project CRS", "gtkit export mesh DIR",
          (("export_mesh", "gtkit.export.mesh_export:MeshExportSettings"),), ("model/",), ("exports/mesh/", "work/export_mesh_*/"),
          _export_mesh, "export_mesh_*"),
    Stage("overlays", "the model drawn over each posed photo, with its misalignment", "gtkit overlay DIR",
          (("overlay", "gtkit.render.overlay:OverlaySettings"),),
          ("model/", "work/register/poses.txt", "work/sfm_reference/poses.txt", "images/reference/", "images/queries/"),
          ("reports/overlays/",), _overlays),
    Stage("render_db", "the localization database rendered over the model", "gtkit render-db DIR",
          (("render_db", "gtkit.localize.database:RenderDbSettings"),), ("model/", "images/queries/"),
          ("work/render_db/",), _render_db, "render_db", validation=True),
    Stage("localize", "every query photo localized against the database", "gtkit localize DIR",
          (("localize", "gtkit.localize.localize:settings_for"),), ("work/render_db/", "images/queries/"),
          ("work/localize/", "work/localize_db/"), _localize, "localize", validation=True),
    Stage("track", "targets from zoom-photo detections (rig, ray cast on the DSM)",
          "gtkit track calibrate DIR; gtkit track DIR",
          (("rig", "gtkit.track.rig:RigCalibrationSettings"), ("track", "gtkit.track.tracker:TrackSettings")),
          ("detections.csv", "cameras.txt", "work/localize/poses.txt", "exports/dsm.tif", "images/queries/"),
          ("work/rig/", "work/track/", "exports/tracks.csv", "exports/tracks.geojson"), _track, "track"),
    Stage("export_coords", "cameras, GCPs and tracks as CSV / GeoJSON / geo.txt", "gtkit export coords DIR",
          (("export_coordinates", "gtkit.export.coordinates:CoordinatesSettings"),),
          ("work/register/poses.txt", "work/sfm_reference/poses.txt", "gcp_list.txt", "exports/tracks.csv"),
          ("exports/coordinates/", "work/export_coordinates/"), _export_coords, "export_coordinates"),
)
STAGE: dict[str, Stage] = {s.name: s for s in STAGES}
NAMES: tuple[str, ...] = tuple(STAGE)
