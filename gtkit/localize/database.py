"""``render-db``: the offline database of rendered views (RGB + float32 depth + pose) over the
reference model (UAVD4L §3.1), fanned out over an executor, resumable view by view.

Layout under ``work/render_db/``::

    settings.json            what the views on disk depend on (:func:`view_record`): a re-run keeps
                             every view whose name is still planned (resume, added pitch levels)
    images/<view>.jpg        RGB (JPEG, quality 95)
    depth/<view>.npz         'depth_dq': uint16 HxW steps of 'depth_scale' metres along the optical
                             axis (0 = background), each row differenced (:func:`read_depth`);
                             'valid_fraction'; dropped views keep only 'valid_fraction'
    views.json               every view: name, level, DJI angles, centre, valid fraction, kept
    poses.txt intrinsics.txt the kept views (names '<view>.jpg', world-to-camera)
    stage.json               written last; a re-run with the same settings skips the stage

View names: ``h<H>/p<position>_t<paper pitch>_y<yaw>``, see :mod:`gtkit.localize.grid`.

Memory: one view is rendered at a time per worker. Which parts of the model a view draws is
chosen per view by a *part selector* (``parts`` setting; ``all`` draws everything); a tiled
model can register a selector that picks the tiles a view sees.

Size: one module for the database stage end to end (the views the queries can reach, rendering
fanned out and resumed, the record), which share the view record and its resume rules; the grid
itself is :mod:`gtkit.localize.grid`, the grid that follows the queries :mod:`.flight`, the reach
:mod:`.reach`.
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.atomic import atomic_path, write_json
from ..io.poses import INTRINSICS, POSES, write_intrinsics, write_poses
from ..model_files import model_fingerprint
from ..project import (STAGE_RECORD, Project, file_fingerprint, mark_stage_done, settings_dict, settings_key, stage_done,
                       start_stage_clock)
from ..render.frustum import ray_box_fraction
from .executors import ExecutorSettings, iter_map, make_executor
from .flight import GRID_FIELDS, PAPER_GRID, PAPER_PITCHES, flight_inputs, grid_hfov, resolve_grid  # noqa: F401
from .flight import grid_given as _grid_given
from .grid import ANCHORS, View, ground_level, make_views

log = logging.getLogger(__name__)
STAGE = "render_db"


@dataclass(frozen=True)
class RenderDbSettings:
    # The grid (None = follows the queries, :func:`gtkit.localize.flight.resolve_grid`; a value given
    # in project.toml [render_db] or on the command line wins): heights H above the model's ground
    # level (m) from the queries' GPS altitudes above the model's ground under them; grid interval
    # alpha_t per height (m) from H and the field of view; pitches from nadir (0 = DJI -90, 45 = DJI
    # -45) from the queries' gimbal pitches; the virtual camera's horizontal field of view from the
    # queries' intrinsics. A photo without GPS altitude or gimbal angles: its geo.txt position and
    # pseudo-GT pose instead. Without any of that: PAPER_GRID.
    heights: tuple[float, ...] | None = None
    intervals: tuple[float, ...] | None = None
    paper_pitches: tuple[float, ...] | None = None
    yaw_step: float = 45.0                            # alpha_theta (deg): 8 yaws, 8 views a pitch and position
    # What the grid positions are: "camera" = camera centres (the paper: oblique views at the model's
    # edges look off it and are dropped), "look_at" = the ground points the views look at (each
    # camera stands H tan(pitch) back along its yaw): every view looks at the model.
    anchor: str = "look_at"
    width: int = 640                                  # rendered view size (px)
    height: int = 480
    hfov_deg: float | None = None                     # horizontal field of view of the virtual camera
    min_valid_fraction: float = 0.5                   # drop views that see less model than this
    jpeg_quality: int = 95
    parts: str = "all"                                # part selector (which model parts a view draws)
    model: str = "model/reference.obj"                # relative to the project; a folder (or its
                                                      # metadata.xml) = a tiled model, streamed per view
    tile_budget_mb: float = 512.0                     # GPU memory for resident tiles (tiled models)
    # Texture filtering of the views (1 = trilinear). On the CPU renderer anisotropic filtering (8)
    # cost 2x a view on average and up to 50x on views of facades with stretched texture
    # coordinates, the site-dependent stalls of render-db (see gtkit.render.renderer.Renderer).
    texture_anisotropy: float = 1.0
    # "views": a texture finer than any planned view can show is halved as it is loaded (the levels a
    # view never samples; gtkit.render.texture_detail), so a photo-built model's full-resolution
    # textures do not fill the tile budget; "stored": textures as stored.
    texture_detail: str = "views"
    # Which planned views are rendered: "reachable" = those some query's retrieval can rank among
    # the views it matches, from its GPS + gimbal priors and the project's [localize] settings
    # (:func:`gtkit.localize.reach.reachable_views`; a query without them reaches every view its
    # rotation prior keeps, a project without query photos gets every view); "all" = every view (the
    # paper's database, for queries not flown yet). localize renders any view its own settings reach
    # that is not on disk yet, so an ablation never runs on a database too small for it.
    views: str = "reachable"


# Settings that only choose *which* views exist or are kept, never what a view of a given name looks
# like: changing them keeps every view already on disk (adding a pitch level renders only the new
# level, and the feature cache of the localize stage, keyed by the same record, stays valid).
VIEW_SET_FIELDS = ("paper_pitches", "min_valid_fraction", "views")


def render_settings(d: dict) -> RenderDbSettings:
    """:class:`RenderDbSettings` from their dict (a task's, or the ``settings`` a stage record keeps;
    lists back to tuples, keys of other versions left out)."""
    known = {f.name for f in fields(RenderDbSettings)}
    return RenderDbSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in known})


def view_record(settings: dict, inputs: dict) -> dict:
    """What a view of a given name depends on (written to ``settings.json``): the settings less
    :data:`VIEW_SET_FIELDS`, and the model's fingerprint."""
    return {"settings": {k: v for k, v in settings.items() if k not in VIEW_SET_FIELDS}, "inputs": inputs}


def db_camera(s: RenderDbSettings) -> Camera:
    """The virtual camera of the database views (the paper's 60 deg where the field of view is not
    resolved yet: it follows the queries once :func:`resolve_grid` ran)."""
    return Camera.from_hfov(s.width, s.height, s.hfov_deg if s.hfov_deg is not None else PAPER_GRID["hfov_deg"])


# --- part selectors: which uploaded parts a view draws (None = all) ---------------------------

def _all_parts(renderer, camera: Camera, view: View):
    return None


PART_SELECTORS: dict[str, Callable] = {"all": _all_parts}


# --- worker side --------------------------------------------------------------------------------

_WORKER: dict = {}


def open_model(root: Path, model: str, frame, tile_budget_mb: float = 512.0, anisotropy: float = 8.0,
               detail=None):
    """A renderer for the project's model ``model`` (relative to ``root``): see
    :func:`gtkit.render.tiles.open_renderer`."""
    from ..render.tiles import open_renderer

    return open_renderer(Path(root) / model, frame, tile_budget_mb, anisotropy, detail)


TEXTURE_DETAILS = ("views", "stored")


def _check_texture_detail(s: "RenderDbSettings") -> None:
    if s.texture_detail not in TEXTURE_DETAILS:
        raise GtkitError(f"render-db texture_detail must be one of {', '.join(TEXTURE_DETAILS)}, "
                         f"got {s.texture_detail!r}")


def view_detail(s: "RenderDbSettings", ground_z: float):
    """The texture detail the database views can show (None: textures as stored); ``s``: a
    resolved grid (:func:`resolve_grid`)."""
    _check_texture_detail(s)
    if s.texture_detail == "stored":
        return None
    from ..render.texture_detail import TextureDetail

    return TextureDetail.for_views(db_camera(s), ground_z + min(s.heights))


def model_bounds(r) -> np.ndarray:
    return r.model.bounds() if hasattr(r, "model") else r.bounds()


def render_view(r, camera: Camera, view: View, parts: str = "all", with_rgb: bool = True):
    if hasattr(r, "visible_tiles"):  # a tile streamer chooses the tiles in the view's frustum
        return r.render(camera, view.pose(), with_rgb=with_rgb)
    return r.render(camera, view.pose(), parts=PART_SELECTORS[parts](r, camera, view), with_rgb=with_rgb)


# Views off the model's edge are dropped before the full render, in two probes. First the share of a
# 40 x 30 grid of the view's rays that meet a part's (or tile's) bounding box, an upper bound of the
# share of pixels that see model (no drawing, ~2 ms); then, for a view whose rays meet the boxes less
# than BOX_SURE of the time, the view drawn as depth only at 1/8 of its size (80 x 60 px for 640 x
# 480; ~8 ms on medium). A view is dropped when a probe sees less than min_valid_fraction -
# PROBE_MARGIN: a probe's fraction differs from the full view's by the share of pixels on the model's
# outline (~2 % at 80 x 60) or missed by the ray grid (under 1 %), so the margin keeps every view the
# full render would keep; a view near the limit is rendered and judged at full size. Medium seed 6,
# 612 views: the boxes drop 58, the drawn probe 50 more of the 126 the full render drops, none kept.
PROBE_SCALE = 0.125
PROBE_MARGIN = 0.05
BOX_SURE = 0.9


def _call(_step: str, fn, *a, **k):
    return fn(*a, **k)


def probed_fraction(r, cam, probe, view: "View", s: "RenderDbSettings", boxes, timed=_call) -> float:
    """The share of ``view`` that sees the model as far as the two probes tell: the ray-box share,
    or the drawn probe's where that is not sure. The view needs its full render when this is at
    least ``min_valid_fraction - PROBE_MARGIN``. ``timed(step, fn, *args)`` wraps each probe (the
    benchmark times them)."""
    frac = timed("ray probe", ray_box_fraction, cam, view.pose(), boxes)
    if s.min_valid_fraction - PROBE_MARGIN <= frac < BOX_SURE:
        frac = float(np.isfinite(timed("drawn probe", render_view, r, probe, view, s.parts, with_rgb=False).depth).mean())
    return frac


def _renderer_for(root: str, s: "RenderDbSettings", ground_z: float):
    detail = view_detail(s, ground_z)
    key = (root, s.model, s.tile_budget_mb, s.texture_anisotropy, detail)
    if _WORKER.get("key") != key:
        if "renderer" in _WORKER:
            _WORKER.pop("renderer").release()
        _WORKER["renderer"] = open_model(Path(root), s.model, Project.load(root).frame, s.tile_budget_mb,
                                         s.texture_anisotropy, detail)
        _WORKER["key"] = key
    return _WORKER["renderer"]


def _check_current(out: Path, record: dict | None) -> None:
    """Refuse to write a view when the database's ``settings.json`` is no longer the record the view
    was planned under: a run stopped while its workers went on (their parent killed), or another
    render-db run that changed the settings and cleared the views, must not get views of another
    model or settings mixed into its folder."""
    if record is None:
        return
    try:
        now = json.loads((out / "settings.json").read_text())
    except (OSError, ValueError):
        now = None
    if now != record:
        raise GtkitError("render-db settings changed while rendering (another render-db run, or this "
                         "run was stopped): this worker stops without writing", out / "settings.json")


def _render_chunk(task) -> list[tuple[str, float]]:
    """Render a list of views; returns (name, valid fraction) for each. Writes files atomically,
    the depth file last, so an existing depth file means the view is complete. ``task``'s last item
    is the database's view record (``settings.json``), checked before each view is written."""
    import cv2

    root, settings_d, views, ground_z, record = task
    s = render_settings(settings_d)
    out = Path(root) / "work" / STAGE
    _check_current(out, record)
    r = _renderer_for(root, s, ground_z)
    cam = db_camera(s)
    probe = cam.scaled(PROBE_SCALE)
    boxes = r.boxes()
    res = []
    for vd in views:
        v = View(**{**vd, "center": tuple(vd["center"])})
        dpath = out / "depth" / f"{v.name}.npz"
        frac = probed_fraction(r, cam, probe, v, s, boxes)
        if frac >= s.min_valid_fraction - PROBE_MARGIN:
            rr = render_view(r, cam, v, s.parts)
            frac = float(np.isfinite(rr.depth).mean())
        _check_current(out, record)
        if frac >= s.min_valid_fraction:
            with atomic_path(out / "images" / f"{v.name}.jpg") as tmp:
                cv2.imwrite(str(tmp), cv2.cvtColor(rr.rgb, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, s.jpeg_quality])
            write_depth(dpath, rr.depth, frac)
        else:
            write_depth(dpath, None, frac)
        res.append((v.name, frac))
    return res


# --- depth files: uint16 steps of depth_scale metres (0 = background), row-differenced, deflated ----
# The step is the view's largest depth / 65535 (1.5 mm at 100 m, 1.5 cm at 1 km): far below what
# lifting needs. Stored as each row's differences modulo 2**16 ('depth_dq'; a cumulative sum modulo
# 2**16 gives the steps back exactly), deflated at level 1: on medium seed 6's views 5 ms and 122 KB a
# view, against 14 ms and 257 KB for the steps themselves at numpy's default level (and 67 ms, 0.87
# MB for float32). Files of the earlier layouts ('depth_q' steps, float32 'depth') are still read.

def _npz_entries(path: Path, arrays: dict) -> None:
    import io
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(a), allow_pickle=False)
            z.writestr(f"{name}.npy", buf.getvalue())


def write_depth(path: Path, depth: np.ndarray | None, valid_fraction: float) -> None:
    """Write a view's depth file atomically (``depth`` None = a dropped view: the fraction only)."""
    with atomic_path(path) as tmp:
        if depth is None:
            _npz_entries(tmp, {"valid_fraction": np.float64(valid_fraction)})
            return
        top = float(np.nanmax(depth)) if np.isfinite(depth).any() else 1.0
        scale = max(top, 1e-6) / 65535.0
        q = np.nan_to_num(depth * np.float32(1.0 / scale), nan=0.0)
        np.clip(q, 1.0, 65535.0, out=q, where=q > 0)   # a surface pixel is never step 0 (background)
        q = np.rint(q).astype(np.uint16)
        _npz_entries(tmp, {"depth_dq": np.diff(q, axis=1, prepend=np.uint16(0)),
                           "depth_scale": np.float64(scale), "valid_fraction": np.float64(valid_fraction)})


def read_depth(path: Path) -> np.ndarray | None:
    """A view's depth map (float32 metres along the optical axis, NaN = background) or None."""
    try:
        with np.load(path) as z:
            if "depth_dq" in z.files or "depth_q" in z.files:
                q = (np.cumsum(z["depth_dq"], axis=1, dtype=np.uint16) if "depth_dq" in z.files
                     else z["depth_q"])
                d = q.astype(np.float32) * np.float32(z["depth_scale"])
                d[q == 0] = np.nan
                return d
            return z["depth"] if "depth" in z.files else None
    except (OSError, ValueError, EOFError, KeyError):
        return None


def _existing_fraction(path: Path) -> float | None:
    try:
        with np.load(path) as z:
            return float(z["valid_fraction"])
    except (OSError, KeyError, ValueError, EOFError):
        return None


# --- the stage ----------------------------------------------------------------------------------

def plan_views(project: Project, s: RenderDbSettings) -> tuple[list[View], dict, RenderDbSettings]:
    """The viewpoints for this model and settings, the extent, ground level and grid used, and the
    settings with the grid resolved (:func:`resolve_grid`)."""
    s = replace(s, **{k: tuple(float(v) for v in getattr(s, k)) for k in ("heights", "intervals", "paper_pitches")
                      if getattr(s, k) is not None})
    if s.heights is not None and s.intervals is not None and len(s.heights) != len(s.intervals):
        raise GtkitError(f"render-db needs one interval per height, got heights {s.heights} "
                         f"and intervals {s.intervals}")
    r = open_model(project.paths.root, s.model, project.frame, s.tile_budget_mb)
    try:
        b = model_bounds(r)
        extent = (float(b[0, 0]), float(b[0, 1]), float(b[1, 0]), float(b[1, 1]))
        g = ground_level(r, *extent)
        s, grid = resolve_grid(project, s, r, extent, g)
    finally:
        r.release()
    if s.anchor not in ANCHORS:
        raise GtkitError(f"render-db anchor must be one of {', '.join(ANCHORS)}, got {s.anchor!r}")
    views = make_views(extent, g, s.heights, s.intervals, s.paper_pitches, s.yaw_step, s.anchor)
    return views, {"extent_xmin_ymin_xmax_ymax": extent, "ground_level_z": g,
                   "grid": {**grid, **{k: getattr(s, k) for k in GRID_FIELDS}}}, s


def run(project: Project | str | Path, settings: RenderDbSettings,
        executor: ExecutorSettings = ExecutorSettings(), chunk: int = 8, force: bool = False, *,
        localize_settings) -> Path:
    """Render the database; returns its folder. Resumes view by view when settings match.
    ``localize_settings``: the localize stage's settings (``gtkit.stages.settings_for("localize", ...)``),
    whose priors choose the views when ``settings.views`` is "reachable" (None only with "all")."""
    project = project if isinstance(project, Project) else Project.load(project)
    _check_texture_detail(settings)              # an unknown texture_detail is refused before any work
    if settings.views not in ("reachable", "all"):
        raise GtkitError(f"[render_db] views must be \"reachable\" or \"all\", not {settings.views!r}",
                         project.paths.project_toml)
    P = project.paths
    out = P.stage(STAGE)
    model_in = {"model": model_fingerprint(P.root, settings.model)}
    inputs = dict(model_in)
    if settings.views == "reachable":
        from .reach import prior_settings_key

        if localize_settings is None:
            raise GtkitError("render-db: the reachable views need the localize settings (their priors)")
        inputs["localize_priors"] = prior_settings_key(localize_settings)
    if not _grid_given(settings) or settings.views == "reachable":   # the queries' files are inputs
        from ..queries import query_cameras, query_photos

        names = query_photos(project)
        inputs["queries"] = settings_key({n: file_fingerprint(P.images / n) for n in names})
        if not _grid_given(settings):
            inputs.update(flight_inputs(project, names))   # geo.txt, pseudo-GT: where the photos' sensors are silent
        if settings.hfov_deg is None and not _grid_given(settings):
            try:
                inputs["query_hfov"] = grid_hfov(c.camera.hfov_deg() for c in query_cameras(project, names).values())
            except (GtkitError, ValueError):
                inputs["query_hfov"] = None
    if not force and stage_done(out, settings, inputs):
        log.info("render-db: up to date (%s)", out)
        return out
    start_stage_clock(out)
    views, info, settings_in = plan_views(project, settings)   # settings_in: the grid resolved
    for k in ("heights", "intervals", "paper_pitches", "hfov_deg"):
        log.info("render-db: %s = %s (%s)", k, getattr(settings_in, k), info["grid"]["source"][k])
    sd = view_record(settings_dict(settings_in), model_in)
    sfile = out / "settings.json"
    if sfile.is_file() and view_record(**json.loads(sfile.read_text())) != sd:
        log.info("render-db: view settings changed; removing the old views")
        for sub in ("images", "depth"):
            shutil.rmtree(out / sub, ignore_errors=True)
        for f in ("views.json", POSES, INTRINSICS, STAGE_RECORD):
            (out / f).unlink(missing_ok=True)
    write_json(sfile, sd)
    fractions: dict[str, float] = {}
    for v in views:
        f = _existing_fraction(out / "depth" / f"{v.name}.npz")
        if f is not None:
            fractions[v.name] = f
    n_before = len(fractions)
    cam = db_camera(settings_in)
    record = json.loads(sfile.read_text())

    def render(todo: list[View]) -> None:
        tasks = [(str(P.root), asdict(settings_in), [v.as_dict() for v in todo[i:i + chunk]], info["ground_level_z"],
                  record) for i in range(0, len(todo), chunk)]
        ex = make_executor(executor)
        try:
            for res in iter_map(ex, _render_chunk, tasks, progress="render-db"):
                fractions.update(dict(res))
        finally:
            ex.close()

    t0 = time.perf_counter()
    reach = None
    if settings.views == "reachable":
        reach = render_reachable(project, views, fractions, settings.min_valid_fraction, cam, out, render,
                                 localize_settings)
    if reach is None:                            # every view (settings, or nothing to reach from)
        todo = [v for v in views if v.name not in fractions]
        log.info("render-db: %d views planned, %d already on disk, %d to render", len(views), n_before, len(todo))
        if todo:
            render(todo)
    dt = time.perf_counter() - t0
    n_rendered = len(fractions) - n_before
    kept = _write_views(out, views, fractions, settings.min_valid_fraction, cam, info)
    disk = sum(f.stat().st_size for sub in ("images", "depth") for f in (out / sub).rglob("*") if f.is_file())
    mark_stage_done(out, settings, inputs, grid=info["grid"], n_views=len(views), n_kept=len(kept), n_rendered=n_rendered,
                    n_on_disk=len(fractions), views_rendered="all" if reach is None else "reachable",
                    render_rounds=reach,
                    seconds=round(dt, 2), views_per_s=round(n_rendered / dt, 3) if n_rendered and dt > 0 else None,
                    disk_mb=round(disk / 2**20, 1), disk_kb_per_kept_view=round(disk / 2**10 / max(1, len(kept)), 1))
    log.info("render-db: %d of %d views kept (%d rendered in %.1f s)", len(kept), len(views), n_rendered, dt)
    return out


def render_reachable(project: Project, views: list[View], fractions: dict[str, float], min_valid: float,
                     cam: Camera, out: Path, render: Callable[[list[View]], None], localize_settings) -> int | None:
    """Render the planned ``views`` some query can reach (``fractions``: the views on disk, updated
    by ``render``), round by round until none is missing: each round takes as candidates every view
    not known to be dropped (on disk and kept, or not rendered yet), so the views a query ranks
    first are all rendered and kept when it stops, and the database gives each query the ranking
    the whole grid would. Returns the rounds, or None when no query photo (or its camera) can say
    which views it reaches: then every view is rendered. The codebook's views
    (:func:`gtkit.localize.reach.codebook_views`) are rendered too."""
    from ..queries import query_cameras
    from .reach import query_names

    try:
        names = query_names(project, localize_settings)
        cams = {n: qc.camera for n, qc in query_cameras(project, names).items()} if names else {}
    except GtkitError as e:
        log.info("render-db: every view (the queries' cameras: %s)", e)
        return None
    if not names:
        log.info("render-db: no query photos: every view is rendered")
        return None
    planned = [v.name for v in views]
    rounds = 0
    while True:
        cand = [v for v in views if fractions.get(v.name, min_valid) >= min_valid]
        want, todo = reachable_not_rendered(project, planned, cand, set(fractions), cam, out, localize_settings,
                                            names, cams)
        log.info("render-db: round %d: %d of %d planned views reachable from %d queries (or the codebook's), "
                 "%d to render",
                 rounds + 1, len(want), len(views), len(names), len(todo))
        if not todo:
            return rounds
        render(todo)
        rounds += 1


def reachable_not_rendered(project: Project, planned: list[str], cand: list[View], on_disk: set[str], cam: Camera,
                           out: Path, localize_settings, names: list[str], cams: dict) -> tuple[set[str], list[View]]:
    """One round of :func:`render_reachable`: among the candidate views ``cand`` (those not known to
    be dropped), the names the queries reach over the levels a run ranks, with the VLAD codebook's
    views (spread over the ``planned`` grid: the same codebook as a database of every view), and the
    candidates among them not ``on_disk``."""
    from .reach import codebook_views, reachable_views, select_views

    sub = select_views(database_of(out, cam, cand), localize_settings)
    need = reachable_views(project, sub, localize_settings, names, cams)
    want = {v.name for v, r in zip(sub.views, need) if r} | set(codebook_views(planned, localize_settings))
    return want, [v for v in cand if v.name in want and v.name not in on_disk]


def _write_views(out: Path, views: list[View], fractions: dict[str, float], min_valid: float, cam: Camera,
                 info: dict) -> list[View]:
    """views.json (every planned view; one not rendered has no valid_fraction), poses.txt and
    intrinsics.txt (the kept views); returns the kept views."""
    kept = [v for v in views if fractions.get(v.name, -1.0) >= min_valid]
    write_json(out / "views.json", {
        **info, "camera": cam.to_line(),
        "note": "paper pitch 0 = nadir = DJI pitch -90; paper pitch 45 = DJI pitch -45; heights above ground_level_z; "
                "a view with valid_fraction null is planned but not rendered (no query reaches it)",
        "views": [{**v.as_dict(), "valid_fraction": fractions.get(v.name),
                   "kept": fractions.get(v.name, -1.0) >= min_valid} for v in views]})
    write_poses(out / POSES, {f"{v.name}.jpg": v.pose() for v in kept}, header="render-db views")
    write_intrinsics(out / INTRINSICS, {f"{v.name}.jpg": cam for v in kept})
    return kept


# --- reading the database ---------------------------------------------------------------------

@dataclass
class DbView:
    name: str              # '<view>' (no extension)
    image: Path
    depth_path: Path
    pose: object           # gtkit.pose.Pose
    yaw: float
    pitch: float
    roll: float
    height: float
    paper_pitch: float


@dataclass
class Database:
    root: Path
    camera: Camera
    views: list[DbView] = field(default_factory=list)

    def depth(self, view: DbView) -> np.ndarray | None:
        """The view's depth map, or None when the file holds no depth."""
        return read_depth(view.depth_path)

    def subset(self, heights=None, paper_pitches=None) -> "Database":
        vs = [v for v in self.views if (heights is None or v.height in heights)
              and (paper_pitches is None or v.paper_pitch in paper_pitches)]
        return Database(self.root, self.camera, vs)


def load_database(project: Project) -> Database:
    return load_grid(project)[0]


def load_grid(project: Project) -> tuple[Database, list[View], list[str]]:
    """The rendered database (its kept views), the planned views not known to be dropped (kept, or
    not rendered: no query reached them yet) and every planned view's name, from one read of
    ``views.json``."""
    out = project.paths.stage(STAGE)
    vfile = out / "views.json"
    if not vfile.is_file() or not (out / STAGE_RECORD).is_file():
        raise GtkitError("no rendered database: run 'gtkit render-db DIR' first", out)
    d = json.loads(vfile.read_text())
    f = d["camera"].split()
    cam = Camera(f[0], int(f[1]), int(f[2]), tuple(float(x) for x in f[3:]))
    kept, cand = [], []
    for vd in d["views"]:
        if vd["kept"] or vd.get("valid_fraction") is None:
            cand.append(_view(vd))
            if vd["kept"]:
                kept.append(cand[-1])
    return database_of(out, cam, kept), cand, [vd["name"] for vd in d["views"]]


def _view(vd: dict) -> View:
    return View(**{k: vd[k] for k in ("name", "height", "paper_pitch", "yaw", "pitch", "roll")}, center=tuple(vd["center"]))


def database_of(out: Path, cam: Camera, views: list[View]) -> Database:
    """A :class:`Database` of these views (planned or rendered) under ``out``."""
    return Database(out, cam, [DbView(v.name, out / "images" / f"{v.name}.jpg", out / "depth" / f"{v.name}.npz",
                                      v.pose(), v.yaw, v.pitch, v.roll, v.height, v.paper_pitch) for v in views])


def planned_names(project: Project) -> list[str]:
    """Every planned view's name, rendered or not."""
    return load_grid(project)[2]


def planned_not_rendered(project: Project) -> list[View]:
    """The planned views not rendered (no query reached them yet)."""
    db, cand, _names = load_grid(project)
    kept = {v.name for v in db.views}
    return [v for v in cand if v.name not in kept]
