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
from ..io.exif import prior_pose
from ..io.poses import read_intrinsics, read_poses
from ..pose import Pose
from ..project import Project
from .model import view_model

log = logging.getLogger(__name__)

COLORS = {"model": "#c8c8c8", "reference": "#ffd400", "prior": "#9a9a9a", "pseudo_gt": "#00c853",
          "localized": "#2979ff", "gcp": "#ff1744", "residual": "#ff9100", "track": "#e040fb"}
SNAPSHOTS = ("oblique", "top")


@dataclass
class ViewSettings:
    max_triangles: int = 60_000       # the model is decimated to at most this many triangles (frame time
                                      # on CPU rendering grows with them; 60k at 1280x800: see docs/view.md)
    width: int = 1280                 # snapshot size, pixels
    height: int = 800
    frustum_m: float | None = None    # frustum depth; default 3 % of the site's diagonal
    residual_scale: float = 50.0      # GCP residual vectors drawn this many times longer
    snapshots: tuple[str, ...] = SNAPSHOTS
    layers: tuple[str, ...] = ("model", "reference", "queries", "gcps", "tracks")  # what is drawn


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
    tracks: dict[str, np.ndarray] = field(default_factory=dict)
    cameras: dict[str, Camera] = field(default_factory=dict)
    bounds: np.ndarray | None = None                    # (2, 3)
    seconds: dict[str, float] = field(default_factory=dict)


def _use_egl():
    """Offscreen VTK renders through EGL, with or without a display (in its own process, see
    :mod:`gtkit.view.process`)."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


# --- reading the project ---------------------------------------------------------------------

def _poses(path: Path) -> dict[str, Pose]:
    return read_poses(path) if path.is_file() else {}


def load_scene(project: Project | str | Path, settings: ViewSettings | None = None) -> SceneData:
    project = project if isinstance(project, Project) else Project.load(project)
    s = settings or ViewSettings()
    P = project.paths
    out = SceneData()
    t0 = time.perf_counter()
    out.model, out.n_triangles_model, out.n_triangles_shown = view_model(project, s.max_triangles)
    out.seconds["model"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    out.cameras = read_intrinsics(P.cameras) if P.cameras.is_file() else {}
    refs = _poses(P.stage("sfm_reference") / "poses.txt")
    out.reference_source = "work/sfm_reference/poses.txt" if refs else "photo priors (GPS + gimbal)"
    ref_names = sorted(str(f.relative_to(P.images)) for f in P.reference_images.rglob("*")
                       if f.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff")) if P.reference_images.is_dir() else []
    if not refs:
        refs = {n: p for n in ref_names if (p := prior_pose(P.images / n, project.frame)) is not None}
    out.reference = {n: (p, out.cameras.get(n)) for n, p in refs.items()}
    q_names = sorted(str(f.relative_to(P.images)) for f in P.query_images.rglob("*_W.*")) if P.query_images.is_dir() else []
    priors = {n: p for n in q_names if (p := prior_pose(P.images / n, project.frame)) is not None}
    kinds = {"prior": priors,
             "pseudo_gt": {n: p for n, p in _poses(P.stage("register") / "poses.txt").items() if n.startswith("queries/")},
             "localized": _poses(P.stage("localize") / "poses.txt")}
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
    if P.tracks.is_file():
        tr: dict[str, list] = {}
        with open(P.tracks, newline="") as f:
            for r in csv.DictReader(f):
                if r.get("status") == "ok" and r.get("x"):
                    tr.setdefault(r["label"], []).append((r.get("time", ""), float(r["x"]), float(r["y"]), float(r["z"])))
        out.tracks = {k: np.array([p[1:] for p in sorted(v)]) for k, v in tr.items()}
    pts = [np.asarray(pd.bounds).reshape(3, 2).T for pd, _t in (out.model or [])]
    pts += [p.center[None].repeat(2, 0) for p, _c in out.reference.values()]
    pts += [np.array(list(v.values())) for v in out.queries.values() if v]
    if pts:
        allp = np.concatenate(pts)
        out.bounds = np.stack([allp.min(0), allp.max(0)])
    out.seconds["cameras_and_files"] = time.perf_counter() - t1
    return out


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
    for label, P in (scene.tracks.items() if "tracks" in on else ()):
        if len(P) > 1:
            actors[f"track_{label}"] = plotter.add_mesh(pv.lines_from_points(P), color=COLORS["track"], line_width=3,
                                                        lighting=False)
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
    its camera, or (None, None)."""
    if not name:
        return None, None
    for kind in ("pseudo_gt", "localized", "prior"):
        if name in scene.query_poses.get(kind, {}):
            return scene.query_poses[kind][name], scene.cameras.get(name)
    return scene.reference.get(name, (None, None))


def describe(scene: SceneData) -> dict:
    return {"triangles": [scene.n_triangles_model, scene.n_triangles_shown],
            "n_reference_cameras": len(scene.reference), "reference_source": scene.reference_source,
            "reference_centres": [p.center.tolist() for p, _c in scene.reference.values()],
            "trajectories": {k: len(v) for k, v in scene.queries.items()}, "error_source": scene.error_source,
            "n_gcps": len(scene.gcps), "n_tracks": len(scene.tracks),
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


def snapshots(project: Project | str | Path, settings: ViewSettings | None = None, out_dir: Path | None = None,
              orbit_frames: int = 36) -> dict:
    """Write ``reports/scene_<view>.png`` for each snapshot view (rendered in a child process, see
    :mod:`gtkit.view.process`); returns the files and timings: open (process start, load, build,
    first frame), median frame time while orbiting, the renderer process's peak memory."""
    from .process import SceneProcess

    project = project if isinstance(project, Project) else Project.load(project)
    s = settings or ViewSettings()
    out_dir = Path(out_dir) if out_dir else project.paths.reports
    sp = SceneProcess(project.paths.root, s.width, s.height, s)
    try:
        shots = sp.snapshots(out_dir.absolute(), s.snapshots, orbit_frames)
    finally:
        sp.close()
    info = {k: v for k, v in sp.info.items() if k != "reference_centres"}
    return {"files": shots["files"], "open_s": round(sp.open_s, 3), **{k: round(info.pop(k), 3) for k in
            ("load_s", "build_s", "first_frame_s")}, **{k: shots[k] for k in ("frame_ms_median",
            "frame_with_readback_ms_median", "max_rss_mb")}, **info}
