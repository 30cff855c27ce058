"""The project's 3D scene with pyvista (VTK), rendered offscreen: ``gtkit view DIR`` writes PNG
snapshots into ``reports/``, and the annotator's 3D tab shows the same scene.

What is drawn, all read from the project's files (never ``truth/``):

- the reference model (``model/``), decimated to ``max_triangles`` (vertex colours sampled from
  its textures) when larger, and cached (:mod:`gtkit.view.model`);
- reference cameras as frusta (the reference block's poses ``work/sfm_reference/poses.txt``, else
  the photos' GPS + gimbal priors);
- each query sequence's trajectory: the photos' priors (grey), pseudo-GT (``work/register``,
  green) and localized (``work/localize``) camera centres; localized centres are coloured by their
  position error from evaluation's ``reports/localization.json`` when it exists, else by their
  distance from the pseudo-GT pose;
- GCPs (``gcp_list.txt``) with their georegistration residual vectors (scaled, from
  ``work/sfm_reference/block.json``), and target tracks (``exports/tracks.csv``).

Rendering uses VTK's EGL window (``VTK_DEFAULT_OPENGL_WINDOW``), so it runs headless like the rest
of gtkit, always in a child process (:mod:`gtkit.view.process`: VTK and gtkit's own moderngl
renderer must not share a process).

Size: every layer of the scene (model, cameras, trajectories, tie points, GCPs, targets) is read
from the project and drawn by one scene builder; each layer is a small function here.
"""
from __future__ import annotations

import csv
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.poses import read_intrinsics, read_poses
from ..photo_positions import PhotoPositions
from ..pose import Pose
from ..project import IMAGE_EXT, Project
from ..sfm import registration_record
from .model import view_model
from .settings import LAYERS, SNAPSHOTS, ViewSettings  # noqa: F401 (LAYERS: part of this module's names)

log = logging.getLogger(__name__)

COLORS = {"model": "#c8c8c8", "reference": "#ffd400", "prior": "#9a9a9a", "pseudo_gt": "#00c853",
          "localized": "#2979ff", "gcp": "#ff1744", "residual": "#ff9100", "track": "#e040fb",
          "sight": "#f8bbd0", "unplaced": "#ff80ab", "tiepoint": "#00e5ff", "tiepoint_flagged": "#ffffff"}
LEGEND = (("reference", "reference", "reference cameras"), ("prior", "prior", "query priors (photo metadata)"),
          ("pseudo_gt", "pseudo_gt", "pseudo-GT"), ("localized", "localized", "localized"),
          ("tiepoint", "tiepoint", "tie points"), ("tiepoint_flagged", "tiepoint_flagged", "tie points left out"),
          ("gcp", "gcp", "GCPs"), ("gcp_residuals", "residual", "GCP residuals x{scale:g}"),
          ("targets", "track", "targets and tracks"), ("sight", "sight", "lines of sight"),
          ("unplaced", "unplaced", "clicks not placed (ray)"))  # actor, colour, text


@dataclass
class SceneData:
    """The scene's contents as plain arrays, in the project's world frame."""

    model: object | None = None                         # pyvista.PolyData list (one per part) or None
    n_triangles_model: int = 0
    n_triangles_shown: int = 0
    reference: dict[str, tuple[Pose, Camera | None]] = field(default_factory=dict)
    reference_source: str = ""
    queries: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)   # kind -> name -> centre
    query_poses: dict[str, dict[str, Pose]] = field(default_factory=dict)     # kind -> name -> pose
    errors_m: dict[str, float] = field(default_factory=dict)                 # localized name -> error
    error_source: str = ""
    gcps: list[tuple[str, np.ndarray, np.ndarray | None]] = field(default_factory=list)
    tiepoints: dict[str, np.ndarray] = field(default_factory=dict)           # id -> placed 3D point
    tiepoints_flagged: set[str] = field(default_factory=set)                # left out / clicks dropped
    tiepoint_source: str = ""
    targets: list[dict] = field(default_factory=list)   # placed: label, sequence, image, time, xyz, eye
    unplaced: list[dict] = field(default_factory=list)  # clicks without a 3D point: image, label, eye, end
    tracks: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)  # (label, sequence) -> points
    cameras: dict[str, Camera] = field(default_factory=dict)
    bounds: np.ndarray | None = None                    # (2, 3)
    seconds: dict[str, float] = field(default_factory=dict)
    project: Project | None = None


def _use_egl():
    """Offscreen VTK renders through EGL, with or without a display (in its own process, see
    :mod:`gtkit.view.process`)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


# --- reading the project ---------------------------------------------------------------------

def _poses(path: Path) -> dict[str, Pose]:
    return read_poses(path) if path.is_file() else {}


def prior_poses(project: Project, names: list[str]) -> dict[str, Pose]:
    """The poses the photos' metadata claim (:meth:`gtkit.photo_positions.PhotoPositions.prior_pose`:
    geo.txt's position first, else EXIF GPS, with the gimbal's attitude), kept in
    ``work/view/priors.npz`` by the photo's size and modification time: reading the EXIF of 729
    medium-sample photos takes about 1 s, the cache 0.03 s."""
    P = project.paths
    cache = P.stage("view") / "priors.npz"
    known: dict[str, tuple[str, np.ndarray | None]] = {}
    try:
        with np.load(cache) as z:
            if np.allclose(z["origin"], project.frame.origin):
                known = {str(n): (str(k), (R, t) if ok else None)
                         for n, k, R, t, ok in zip(z["names"], z["keys"], z["R"], z["t"], z["ok"])}
    except (OSError, KeyError, ValueError):
        known = {}
    out, changed = {}, False
    positions = PhotoPositions(project)
    geo = P.geo_txt.stat() if P.geo_txt.is_file() else None     # a changed geo.txt moves the priors
    geo_key = f"-geo{geo.st_size}-{geo.st_mtime_ns}" if geo else ""
    for n in names:
        st = (P.images / n).stat()
        key = f"{st.st_size}-{st.st_mtime_ns}{geo_key}"
        if n not in known or known[n][0] != key:
            p = positions.prior_pose(n)
            known[n], changed = (key, None if p is None else (p.R, p.t)), True
        if known[n][1] is not None:
            out[n] = Pose(*known[n][1])
    if changed:
        from ..io.atomic import atomic_path

        rows = sorted(known.items())
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(cache) as tmp, open(tmp, "wb") as f:
                np.savez(f, origin=np.asarray(project.frame.origin, float), names=np.array([n for n, _ in rows]),
                         keys=np.array([k for _n, (k, _p) in rows]), ok=np.array([p is not None for _n, (_k, p) in rows]),
                         R=np.array([p[0] if p else np.eye(3) for _n, (_k, p) in rows]).reshape(-1, 3, 3),
                         t=np.array([p[1] if p else np.zeros(3) for _n, (_k, p) in rows]).reshape(-1, 3))
        except OSError as e:  # a read-only project is shown all the same
            log.warning("3D view: cannot keep the priors cache (%s)", e)
    return out


def load_scene(project: Project | str | Path, settings: ViewSettings | None = None) -> SceneData:
    project = project if isinstance(project, Project) else Project.load(project)
    s = settings or ViewSettings()
    P = project.paths
    out = SceneData(project=project)
    t0 = time.perf_counter()
    out.model, out.n_triangles_model, out.n_triangles_shown = view_model(project, s.max_triangles)
    out.seconds["model"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    out.cameras = read_intrinsics(P.cameras) if P.cameras.is_file() else {}
    refs = _poses(P.reference_poses)
    out.reference_source = "work/sfm_reference/poses.txt" if refs else "photo priors (GPS + gimbal)"
    ref_names = sorted(str(f.relative_to(P.images)) for f in P.reference_images.rglob("*")
                       if f.suffix.lower() in IMAGE_EXT) if P.reference_images.is_dir() else []
    if not refs:
        refs = prior_poses(project, ref_names)
    out.reference = {n: (p, out.cameras.get(n)) for n, p in refs.items()}
    from ..queries import query_photos

    q_names = query_photos(project)   # the project's query photos ([sfm] query_pattern)
    priors = prior_poses(project, q_names)
    kinds = {"prior": priors,
             "pseudo_gt": {n: p for n, p in _poses(P.pseudo_gt_poses).items() if n.startswith("queries/")},
             "localized": _poses(P.localized_poses)}
    out.query_poses = {k: v for k, v in kinds.items() if v}
    out.queries = {k: {n: p.center for n, p in v.items()} for k, v in out.query_poses.items()}
    rep = P.reports / "localization.json"
    if rep.is_file() and "localized" in out.queries:
        try:
            rows = json.loads(rep.read_text()).get("queries", [])
            out.errors_m = {r["name"]: float(r["pos_err_m"]) for r in rows if r.get("pos_err_m") is not None}
            out.error_source = "reports/localization.json (evaluation)"
        except (json.JSONDecodeError, AttributeError, TypeError, KeyError) as e:
            raise GtkitError(f"unreadable localization report ({e})", rep) from None
    elif "localized" in out.queries and "pseudo_gt" in out.queries:
        pg = out.queries["pseudo_gt"]
        out.errors_m = {n: float(np.linalg.norm(c - pg[n])) for n, c in out.queries["localized"].items() if n in pg}
        out.error_source = "distance from the pseudo-GT pose"
    if P.gcp_list.is_file():
        from ..io.odm import read_gcp_list

        res = {}
        block = P.stage("sfm_reference") / "block.json"
        if block.is_file():
            g = (json.loads(block.read_text()).get("georegistration") or {}).get("gcp_residuals") or {}
            res = {n: np.array([r["dx_m"], r["dy_m"], r["dz_m"]]) for n, r in g.items() if r.get("status") == "ok"}
        out.gcps = [(g.name, g.xyz, res.get(g.name)) for g in read_gcp_list(P.gcp_list, project.frame)]
    locator = _Surface(out.model)
    _tiepoints(project, out, locator)
    _targets(project, out, locator)
    pts = [np.asarray(pd.bounds).reshape(3, 2).T for pd, _t in (out.model or [])]
    pts += [p.center[None].repeat(2, 0) for p, _c in out.reference.values()]
    pts += [np.array(list(v.values())) for v in out.queries.values() if v]
    pts += [np.array(list(out.tiepoints.values()))] if out.tiepoints else []
    pts += [np.array([t["xyz"] for t in out.targets])] if out.targets else []
    if pts:
        allp = np.concatenate(pts)
        out.bounds = np.stack([allp.min(0), allp.max(0)])
    out.seconds["cameras_and_files"] = time.perf_counter() - t1
    return out


class _Surface:
    """Where rays first meet the model as the view draws it (VTK cell locator; no rendering)."""

    def __init__(self, model):
        self.loc = None
        if not model:
            return
        from vtkmodules.vtkCommonDataModel import vtkStaticCellLocator
        from vtkmodules.vtkFiltersCore import vtkAppendPolyData

        app = vtkAppendPolyData()
        for pd, _t in model:
            app.AddInputData(pd)
        app.Update()
        self.mesh = app.GetOutput()
        self.loc = vtkStaticCellLocator()
        self.loc.SetDataSet(self.mesh)
        self.loc.BuildLocator()
        b = np.asarray(self.mesh.GetBounds()).reshape(3, 2)
        self.reach = 4.0 * float(np.linalg.norm(b[:, 1] - b[:, 0])) + 1.0

    def hit(self, origin, direction) -> np.ndarray | None:
        if self.loc is None:
            return None
        from vtkmodules.vtkCommonCore import mutable

        o = np.asarray(origin, float)
        e = o + self.reach * np.asarray(direction, float) / np.linalg.norm(direction)
        t, x, pc, sub = mutable(0.0), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], mutable(0)
        if not self.loc.IntersectWithLine(o.tolist(), e.tolist(), 1e-6, t, x, pc, sub):
            return None
        return np.array(x)


def _ray(pose: Pose, cam: Camera, uv) -> tuple[np.ndarray, np.ndarray]:
    """A pixel's viewing ray in the world: (camera centre, unit direction)."""
    return pose.center, pose.R.T @ cam.rays(np.asarray(uv, float))


def _midpoint(rays) -> np.ndarray | None:
    """The point closest to all rays (least squares), if they are not nearly parallel (< 1 deg)."""
    if len(rays) < 2:
        return None
    D = np.array([d for _o, d in rays])
    if np.degrees(np.arccos(np.clip(np.min(D @ D.T), -1, 1))) < 1.0:
        return None
    A, b = np.zeros((3, 3)), np.zeros(3)
    for o, d in rays:
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ o
    return np.linalg.solve(A, b)


def _tiepoints(project: Project, out: SceneData, surface: _Surface) -> None:
    """Tie points placed in 3D: the rays of their reference clicks cast onto the model (a tie point's
    reference clicks often come from one camera station, too close to triangulate), else the point
    nearest to all their clicks' rays; flagged when the registration left them out or dropped a click."""
    from ..io.tiepoints import read_tiepoints

    P = project.paths
    if not P.tiepoints.is_file():
        return
    poses = {n: pc for n, pc in out.reference.items()}
    for kind in ("prior", "localized", "pseudo_gt"):  # the best query pose wins
        for n, pose in out.query_poses.get(kind, {}).items():
            poses[n] = (pose, out.cameras.get(n))
    tps = read_tiepoints(P.tiepoints)
    by_image: dict[str, list] = {}
    for tp in tps:
        for o in tp.observations:
            if o.image in poses and poses[o.image][1] is not None:
                by_image.setdefault(o.image, []).append(o)
    ray_of = {}
    for image, obs in by_image.items():  # one call per photo (undistorting is iterative)
        pose, cam = poses[image]
        D = cam.rays(np.array([(o.x, o.y) for o in obs], float)) @ pose.R
        ray_of.update({id(o): (pose.center, d) for o, d in zip(obs, D)})
    for tp in tps:
        obs = [o for o in tp.observations if id(o) in ray_of]
        rays = [ray_of[id(o)] for o in obs]
        hits = [h for o, r in zip(obs, rays) if o.image.startswith("reference/") and (h := surface.hit(*r)) is not None]
        X = np.mean(hits, axis=0) if hits else _midpoint(rays)
        if X is not None:
            out.tiepoints[tp.id] = X
    out.tiepoint_source = "tiepoints.json (not registered yet)"
    d = registration_record.read_registration(P.registration, strict=True)
    if d is not None:
        table, bad = registration_record.tiepoints(d), registration_record.bad_tiepoints(d)
        out.tiepoints_flagged = {t for t in out.tiepoints if t in bad or not (table.get(t) or {}).get("in_final_ba", False)}
        out.tiepoint_source = "work/register/registration.json"


def read_tracks_csv(path: Path) -> list[dict]:
    """The rows of ``exports/tracks.csv`` (gtkit track; ``#`` lines are comments)."""
    lines = [ln for ln in Path(path).read_text(encoding="utf-8").splitlines() if ln.strip() and not ln.startswith("#")]
    return list(csv.DictReader(lines))


def _targets(project: Project, out: SceneData, surface: _Surface) -> None:
    """Targets: the tracker's placed points (``exports/tracks.csv``, CRS coordinates) with the line
    of sight from the photo's camera and one track per label and sequence; clicks it could not place,
    or not yet tracked (``detections.csv``), as the zoom camera's ray to the model (needs the rig
    calibration)."""
    P = project.paths
    if not (P.tracks.is_file() or P.detections.is_file()):
        return
    from ..track.calibrate import wide_name_for

    origin = np.asarray(project.frame.origin, float)
    clicks = []
    if P.tracks.is_file():
        for r in read_tracks_csv(P.tracks):
            seq = r["image"].rsplit("/", 1)[0] if "/" in r.get("image", "") else ""
            eye = pose_of(out, wide_name_for(r.get("image", "")) or r.get("image"))[0]
            if r.get("status") == "ok" and r.get("x"):
                xyz = np.array([float(r["x"]), float(r["y"]), float(r["z"])]) - origin
                t = float(r["time"]) if r.get("time") else np.inf
                out.targets.append({"label": r["label"], "sequence": seq, "image": r["image"], "time": t, "xyz": xyz,
                                    "eye": None if eye is None else eye.center})
            else:
                clicks.append((r["image"], float(r["u"]), float(r["v"]), r.get("label", "")))
    elif P.detections.is_file():
        from ..track.targets import read_detections

        clicks = [(d.image, d.u, d.v, d.label) for d in read_detections(P.detections)]
    by_track: dict[tuple[str, str], list] = {}
    for t in out.targets:
        by_track.setdefault((t["label"], t["sequence"]), []).append((t["time"], t["image"], t["xyz"]))
    out.tracks = {k: np.array([p[2] for p in sorted(v, key=lambda p: p[:2])]) for k, v in by_track.items()}
    if clicks and P.rig.is_file():
        from ..io.exif import read_photo_meta
        from ..track.rig import Rig

        rig = Rig.load(P.rig)
        for image, u, v, label in clicks:
            wide = pose_of(out, wide_name_for(image))[0]
            if wide is None:
                continue
            meta = read_photo_meta(P.images / image)
            zoom = rig.zoom_pose(wide)
            o, d = _ray(zoom, rig.zoom_camera(meta.width, meta.height, meta.focal_mm), (u, v))
            end = surface.hit(o, d)
            out.unplaced.append({"image": image, "label": label, "eye": o,
                                 "end": end if end is not None else o + 100.0 * d,  # 100 m of the ray
                                 "on_model": end is not None})
    elif clicks:
        out.unplaced = [{"image": i, "label": lb, "eye": None, "end": None, "on_model": False} for i, _u, _v, lb in clicks]


# --- drawing ---------------------------------------------------------------------------------

def frusta(cams: list[tuple[Pose, Camera | None]], depth: float) -> "object":
    """Camera frusta as one line set: apex to the four image corners at ``depth`` metres, and the rim."""
    import pyvista as pv

    pts, lines = [], []
    for pose, cam in cams:
        cam = cam or Camera.from_hfov(4, 3, 70.0)
        corners = np.array([[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]], float)
        rays = np.linalg.solve(cam.K(), np.c_[corners, np.ones(4)].T).T  # camera frame, z = 1
        Xc = rays * depth
        Xw = (Xc - pose.t) @ pose.R                                    # R^T (x - t)
        base = len(pts)
        pts += [pose.center, *Xw]
        lines += [[2, base, base + k] for k in range(1, 5)]
        lines += [[2, base + k, base + 1 + k % 4] for k in range(1, 5)]
    if not pts:
        return None
    return pv.PolyData(np.array(pts), lines=np.array(lines).ravel())


def _frustum_depth(centres, diag: float) -> float:
    """Frusta a third of the typical spacing between camera stations (five-eye cameras share one),
    at most 3 % of the scene's diagonal: a dense block stays readable."""
    if len(centres) < 2:
        return 0.03 * diag
    from scipy.spatial import cKDTree

    C = np.unique(np.round(np.asarray(centres), 1), axis=0)
    if len(C) < 2:
        return 0.03 * diag
    d, _ = cKDTree(C).query(C, k=2)
    return float(np.clip(np.median(d[:, 1]) / 3, 0.002 * diag, 0.03 * diag))


def build(plotter, scene: SceneData, settings: ViewSettings | None = None) -> dict:
    """Add the scene's actors to a pyvista plotter; returns the actors by name."""
    import pyvista as pv

    s = settings or ViewSettings()
    actors = {}
    diag = float(np.linalg.norm(np.ptp(scene.bounds, 0))) if scene.bounds is not None else 100.0
    on = set(s.layers)
    for k, (pd, tex) in enumerate(scene.model if "model" in on and scene.model else []):
        if tex is not None:
            actors[f"model{k}"] = plotter.add_mesh(pd, texture=tex, lighting=False)
        elif "rgb" in pd.point_data:
            actors[f"model{k}"] = plotter.add_mesh(pd, scalars="rgb", rgb=True, lighting=False)
        else:
            actors[f"model{k}"] = plotter.add_mesh(pd, color=COLORS["model"])
    depth = s.frustum_m or _frustum_depth([p.center for p, _c in scene.reference.values()], diag)
    fr = frusta(list(scene.reference.values()), depth) if "reference" in on else None
    if fr is not None:
        actors["reference"] = plotter.add_mesh(fr, color=COLORS["reference"], line_width=2, lighting=False)
    for kind in ("prior", "pseudo_gt", "localized"):
        centres = scene.queries.get(kind) if "queries" in on else None
        if not centres:
            continue
        by_seq: dict[str, list[str]] = {}
        for n in sorted(centres):
            by_seq.setdefault(n.split("/")[1] if n.count("/") >= 2 else "", []).append(n)
        for seq, names in by_seq.items():
            P = np.array([centres[n] for n in names])
            if len(P) > 1:
                actors[f"{kind}_{seq}_line"] = plotter.add_mesh(pv.lines_from_points(P), color=COLORS[kind],
                                                                line_width=3 if kind != "prior" else 2, lighting=False)
        names = sorted(centres)
        cloud = pv.PolyData(np.array([centres[n] for n in names]))
        if kind == "localized" and scene.errors_m:
            cloud.point_data["error_m"] = np.array([scene.errors_m.get(n, np.nan) for n in names])
            actors[kind] = plotter.add_mesh(cloud, scalars="error_m", cmap="turbo", point_size=12,
                                            render_points_as_spheres=True, nan_color="white", lighting=False,
                                            clim=[0.0, max(0.5, float(np.nanmax(cloud.point_data["error_m"])))],
                                            scalar_bar_args={"title": "position error m", "vertical": True})
        else:
            actors[kind] = plotter.add_mesh(cloud, color=COLORS[kind], point_size=8 if kind != "prior" else 6,
                                            render_points_as_spheres=True, lighting=False)
    if scene.gcps and "gcps" in on:
        xyz = np.array([g[1] for g in scene.gcps])
        actors["gcp"] = plotter.add_mesh(pv.PolyData(xyz), color=COLORS["gcp"], point_size=14,
                                         render_points_as_spheres=True, lighting=False)
        vec = [(x, r) for _n, x, r in scene.gcps if r is not None]
        if vec:
            pts = np.array([x for x, _r in vec])
            d = np.array([r for _x, r in vec]) * s.residual_scale
            lines = pv.PolyData(np.concatenate([pts, pts + d]),
                                lines=np.array([[2, k, k + len(pts)] for k in range(len(pts))]).ravel())
            actors["gcp_residuals"] = plotter.add_mesh(lines, color=COLORS["residual"], line_width=3, lighting=False)
    if scene.tiepoints and "tiepoints" in on:
        for flagged, colour in ((False, "tiepoint"), (True, "tiepoint_flagged")):
            pts = [x for t, x in sorted(scene.tiepoints.items()) if (t in scene.tiepoints_flagged) == flagged]
            if pts:
                actors[colour] = plotter.add_mesh(pv.PolyData(np.array(pts)), color=COLORS[colour], point_size=7,
                                                  render_points_as_spheres=True, lighting=False)
    if "targets" in on or "tracks" in on:
        for (label, seq), P in scene.tracks.items():
            if len(P) > 1:
                actors[f"track_{label}_{seq}"] = plotter.add_mesh(pv.lines_from_points(P), color=COLORS["track"],
                                                                  line_width=3, lighting=False)
        sights = [(t["eye"], t["xyz"]) for t in scene.targets if t["eye"] is not None]
        sights += [(u["eye"], u["end"]) for u in scene.unplaced if u["eye"] is not None]
        if sights:
            ends = np.array([p for pair in sights for p in pair])
            lines = np.array([[2, 2 * k, 2 * k + 1] for k in range(len(sights))]).ravel()
            n_placed = sum(t["eye"] is not None for t in scene.targets)
            for name, sl, colour in (("sight", slice(0, n_placed), "sight"), ("unplaced", slice(n_placed, None), "unplaced")):
                sel = lines.reshape(-1, 3)[sl]
                if len(sel):
                    actors[name] = plotter.add_mesh(pv.PolyData(ends, lines=sel.ravel()), color=COLORS[colour],
                                                    line_width=1 if name == "sight" else 2, lighting=False)
        if scene.targets:
            actors["targets"] = plotter.add_mesh(pv.PolyData(np.array([t["xyz"] for t in scene.targets])),
                                                 color=COLORS["track"], point_size=10, render_points_as_spheres=True,
                                                 lighting=False)
    if s.legend:
        entries = [[text.format(scale=s.residual_scale), COLORS[colour]] for actor, colour, text in LEGEND if actor in actors]
        if entries:
            plotter.add_legend(entries, bcolor="#20242a", border=False, size=(0.2, 0.03 * len(entries)),
                               loc="upper left", face="circle")
    return actors


def set_overview(plotter, scene: SceneData, which: str = "oblique") -> None:
    """Look at the whole scene: ``oblique`` from the south-west at 35 degrees, or ``top`` (nadir)."""
    lo, hi = (scene.bounds if scene.bounds is not None else np.array([[-50, -50, 0], [50, 50, 20.0]]))
    c = (lo + hi) / 2
    r = max(float(np.linalg.norm(hi - lo)) / 2, 1.0)
    cam = plotter.camera
    if which == "top":
        cam.position, cam.focal_point, cam.up = c + [0, 0, 2.6 * r], c, (0, 1, 0)
    else:
        el, az = np.radians(35), np.radians(225)
        d = 2.4 * r * np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
        cam.position, cam.focal_point, cam.up = c + d, c, (0, 0, 1)
    cam.view_angle = 30.0
    plotter.reset_camera_clipping_range()


def set_photo_view(plotter, pose: Pose, cam: Camera | None, distance: float = 100.0) -> None:
    """Look through a photo: the camera at its centre, its axis and up, its vertical field of view."""
    R = pose.R
    c = pose.center
    vcam = plotter.camera
    vcam.position = c
    vcam.focal_point = c + R[2] * distance           # optical axis (camera z) in the world
    vcam.up = -R[1]                                  # image y points down
    if cam is not None:
        vcam.view_angle = float(np.degrees(2 * np.arctan(cam.height / 2 / cam.fy)))
    plotter.reset_camera_clipping_range()


def new_plotter(width: int, height: int):
    import pyvista as pv

    _use_egl()
    # no anti-aliasing: on Mesa's llvmpipe (CPU) pyvista's default 4x MSAA made a frame 6x slower
    # (112 vs 17 ms at 1280x800), and FXAA falls back to SSAA in VTK's EGL build (229 ms)
    import copy

    theme = copy.deepcopy(pv.global_theme)
    theme.multi_samples = 0
    p = pv.Plotter(off_screen=True, window_size=(width, height), theme=theme)
    p.set_background("#20242a")
    return p


def world_to_pixel(plotter, X: np.ndarray) -> np.ndarray:
    """Pixel positions (x right, y down) of world points in the plotter's last rendered view."""
    ren = plotter.renderer
    h = plotter.window_size[1]
    out = []
    for x in np.atleast_2d(X):
        ren.SetWorldPoint(*x, 1.0)
        ren.WorldToDisplay()
        dx, dy, _ = ren.GetDisplayPoint()
        out.append((dx, h - dy))
    return np.array(out)


def pose_of(scene: SceneData, name: str | None):
    """The best pose the project has for a photo (pseudo-GT, localized, reference block, prior) and
    its camera, or (None, None). A zoom photo (``<idx>_Z``) looks from its wide twin's pose through
    the rig calibration (``work/rig/rig.json``), else through the wide camera."""
    if not name:
        return None, None
    for kind in ("pseudo_gt", "localized", "prior"):
        if name in scene.query_poses.get(kind, {}):
            return scene.query_poses[kind][name], scene.cameras.get(name)
    if name in scene.reference:
        return scene.reference[name]
    from ..track.calibrate import wide_name_for

    wide = wide_name_for(name)
    pose, cam = pose_of(scene, wide) if wide else (None, None)
    if pose is None or scene.project is None or not scene.project.paths.rig.is_file():
        return pose, cam
    from ..io.exif import read_photo_meta
    from ..track.rig import Rig

    try:
        rig = Rig.load(scene.project.paths.rig)
        meta = read_photo_meta(scene.project.paths.images / name)
        return rig.zoom_pose(pose), rig.zoom_camera(meta.width, meta.height, meta.focal_mm)
    except GtkitError:
        return pose, cam


def describe(scene: SceneData) -> dict:
    return {"triangles": [scene.n_triangles_model, scene.n_triangles_shown],
            "n_reference_cameras": len(scene.reference), "reference_source": scene.reference_source,
            "reference_centres": [p.center.tolist() for p, _c in scene.reference.values()],
            "trajectories": {k: len(v) for k, v in scene.queries.items()}, "error_source": scene.error_source,
            "n_gcps": len(scene.gcps), "n_tracks": len(scene.tracks),
            "n_tiepoints": len(scene.tiepoints), "n_tiepoints_flagged": len(scene.tiepoints_flagged),
            "tiepoint_source": scene.tiepoint_source, "n_targets": len(scene.targets),
            "n_targets_unplaced": len(scene.unplaced),
            "n_targets_unplaced_drawn": sum(u["eye"] is not None for u in scene.unplaced),
            "seconds": {k: round(v, 3) for k, v in scene.seconds.items()}}


def write_snapshots(plotter, scene: SceneData, out_dir: Path, which=SNAPSHOTS, orbit_frames: int = 36) -> dict:
    """Write ``scene_<view>.png`` for each view into ``out_dir``; then orbit the oblique view and
    time the frames (render only, and render + read-back)."""
    from ..io.atomic import atomic_path

    out_dir.mkdir(parents=True, exist_ok=True)
    files = {}
    for w in which:
        set_overview(plotter, scene, w)
        plotter.render()  # pyvista's screenshot reads the last frame; it does not render
        with atomic_path(out_dir / f"scene_{w}.png") as tmp:
            plotter.screenshot(str(tmp) + ".png")
            os.replace(str(tmp) + ".png", tmp)
        files[w] = str(out_dir / f"scene_{w}.png")
    set_overview(plotter, scene, "oblique")
    frame, frame_rb = [], []
    for _ in range(orbit_frames):  # orbiting: the camera turns about the scene's vertical axis
        plotter.camera.Azimuth(360.0 / max(orbit_frames, 1))
        t = time.perf_counter()
        plotter.render()
        frame.append(time.perf_counter() - t)
        t = time.perf_counter()
        plotter.screenshot(None, return_img=True)
        frame_rb.append(frame[-1] + time.perf_counter() - t)
    return {"files": files,
            "frame_ms_median": round(1000 * float(np.median(frame)), 2) if frame else None,
            "frame_with_readback_ms_median": round(1000 * float(np.median(frame_rb)), 2) if frame_rb else None,
            "max_rss_mb": peak_rss_mb()}


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss it is not carried over from the
    parent across exec, so a renderer spawned by a big process reports its own)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    import resource

    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
