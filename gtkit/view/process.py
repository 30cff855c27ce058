"""The 3D scene rendered in a child process, driven over a pipe.

VTK never renders in a process that also uses gtkit's own OpenGL renderer (moderngl on EGL): the two
share Mesa's EGL display and GL dispatch, and after VTK rendered, gtkit's renders came out blank
(its GL calls went to VTK's context), VTK's EGL window invalidated gtkit's context
(``EGL_BAD_CONTEXT``), and with VTK on OSMesa a render crashed inside libOSMesa. So the annotator's
3D tab, ``gtkit view`` and the tests all talk to a :class:`SceneProcess` (``spawn``: a fresh
interpreter, no inherited GL state).
"""
from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..project import Project
from .settings import ViewSettings


def _serve(conn, root: str, width: int, height: int, settings: dict) -> None:
    import traceback

    from . import scene as S

    try:
        t0 = time.perf_counter()
        s = S.ViewSettings(**settings)
        sc = S.load_scene(root, s)
        t_load = time.perf_counter() - t0
        t1 = time.perf_counter()
        p = S.new_plotter(width, height)
        S.build(p, sc, s)
        S.set_overview(p, sc, "oblique")
        t_build = time.perf_counter() - t1
        t2 = time.perf_counter()
        p.screenshot(None, return_img=True)  # the first frame (pyvista renders nothing before it)
        t_first = time.perf_counter() - t2
        # CPU seconds of this process from its start (interpreter, imports, load, build, first frame; all
        # threads): what the open costs on an idle core, whatever else the machine runs
        conn.send({"ok": True, "info": S.describe(sc) | {"load_s": t_load, "build_s": t_build, "first_frame_s": t_first,
                                                         "open_cpu_s": time.process_time()}})
    except Exception as e:  # noqa: BLE001 - reported to the parent as one line
        conn.send({"ok": False, "error": f"{type(e).__name__}: {e}", "trace": traceback.format_exc()})
        return
    while True:
        try:
            op, args = conn.recv()
        except EOFError:
            break
        if op == "quit":
            break
        try:
            out = _op(S, p, sc, op, args)
            if isinstance(out, np.ndarray):
                conn.send({"ok": True, "shape": out.shape})
                conn.send_bytes(np.ascontiguousarray(out).tobytes())
            else:
                conn.send({"ok": True, "value": out})
        except Exception as e:  # noqa: BLE001
            conn.send({"ok": False, "error": f"{type(e).__name__}: {e}"})
    p.close()


def _op(S, p, sc, op: str, args: tuple):
    cam = p.camera
    if op == "render":
        p.render()  # (pyvista's screenshot reads the last frame; it does not render)
        return p.screenshot(None, return_img=True)[..., :3]
    if op == "size":
        p.window_size = tuple(int(v) for v in args)
        return None
    if op == "overview":
        S.set_overview(p, sc, args[0])
        return None
    if op == "photo":
        pose, c = S.pose_of(sc, args[0])
        if pose is None:
            return False
        S.set_photo_view(p, pose, c)
        return True
    if op == "orbit":
        cam.Azimuth(float(args[0]))
        cam.Elevation(float(args[1]))
        cam.OrthogonalizeViewUp()
    elif op == "pan":
        dx, dy, h = args
        d = np.linalg.norm(np.subtract(cam.position, cam.focal_point))
        s = 2 * d * np.tan(np.radians(cam.view_angle) / 2) / max(h, 1)
        fwd = np.subtract(cam.focal_point, cam.position)
        fwd /= np.linalg.norm(fwd)
        up = np.asarray(cam.up, float)
        move = (-dx * np.cross(fwd, up) + dy * up) * s
        cam.position, cam.focal_point = np.add(cam.position, move), np.add(cam.focal_point, move)
    elif op == "dolly":
        cam.Dolly(float(args[0]))
    elif op == "camera":
        return {"position": list(cam.position), "focal_point": list(cam.focal_point), "up": list(cam.up),
                "view_angle": cam.view_angle}
    elif op == "world_to_pixel":
        p.render()
        return S.world_to_pixel(p, np.asarray(args[0], float)).tolist()
    elif op == "snapshots":
        return S.write_snapshots(p, sc, Path(args[0]), tuple(args[1]), int(args[2]))
    else:
        raise GtkitError(f"unknown scene operation {op!r}")
    p.reset_camera_clipping_range()
    return None


class SceneProcess:
    """A project's 3D scene in a child process: ``render()`` returns the view as (H, W, 3) uint8;
    ``overview``, ``photo``, ``orbit``, ``pan``, ``dolly``, ``size`` move or resize it."""

    def __init__(self, project: str | Path, width: int = 1280, height: int = 800, settings=None, timeout_s: float = 300):
        from dataclasses import asdict

        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, str(project), int(width), int(height),
                                                     asdict(settings or ViewSettings())), daemon=True)
        t0 = time.perf_counter()
        self.proc.start()
        child.close()
        if not self._conn.poll(timeout_s):
            self.close()
            raise GtkitError(f"the 3D scene process did not start within {timeout_s:.0f} s", project)
        msg = self._conn.recv()
        if not msg["ok"]:
            self.close()
            raise GtkitError(f"3D scene: {msg['error']}", project)
        self.info = msg["info"]
        self.open_s = time.perf_counter() - t0  # process start + load + build + first frame

    def _call(self, op: str, *args):
        self._conn.send((op, args))
        msg = self._conn.recv()
        if not msg["ok"]:
            raise GtkitError(f"3D scene ({op}): {msg['error']}")
        if "shape" in msg:
            return np.frombuffer(self._conn.recv_bytes(), np.uint8).reshape(msg["shape"])
        return msg["value"]

    def render(self) -> np.ndarray:
        return self._call("render")

    def size(self, w: int, h: int):
        self._call("size", w, h)

    def overview(self, which: str = "oblique"):
        self._call("overview", which)

    def photo(self, name: str) -> bool:
        return self._call("photo", name)

    def orbit(self, azimuth_deg: float, elevation_deg: float):
        self._call("orbit", azimuth_deg, elevation_deg)

    def pan(self, dx: float, dy: float, view_height: int):
        self._call("pan", dx, dy, view_height)

    def dolly(self, factor: float):
        self._call("dolly", factor)

    def camera(self) -> dict:
        return self._call("camera")

    def world_to_pixel(self, points) -> np.ndarray:
        return np.array(self._call("world_to_pixel", np.asarray(points, float).tolist()))

    def snapshots(self, out_dir, which=("oblique", "top"), orbit_frames: int = 36) -> dict:
        return self._call("snapshots", str(out_dir), list(which), orbit_frames)

    def close(self):
        try:
            if self.proc.is_alive():
                self._conn.send(("quit", ()))
                self.proc.join(10)
        except (OSError, BrokenPipeError):
            pass
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5)


def snapshots(project: Project | str | Path, settings: ViewSettings | None = None, out_dir: Path | None = None,
              orbit_frames: int = 36) -> dict:
    """Write ``reports/scene_<view>.png`` for each snapshot view (rendered in a child process, see
    :mod:`gtkit.view.process`); returns the files and timings: open (process start, load, build,
    first frame), median frame time while orbiting, the renderer process's peak memory."""
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
            ("load_s", "build_s", "first_frame_s", "open_cpu_s")}, **{k: shots[k] for k in ("frame_ms_median",
            "frame_with_readback_ms_median", "max_rss_mb")}, **info}
