"""The 3D tab's interactive view: pyvistaqt's ``QtInteractor`` (VTK renders into an OpenGL widget of
the annotator: GLX under X), with VTK's own mouse handling (left drag rotates, middle drag or
Shift+left pans, wheel or right drag zooms).

It offers what :class:`gtkit.view.process.SceneProcess` offers (``render``, ``overview``, ``photo``,
``orbit``, ``camera``, ``info``, ``open_s``), so :class:`gui.scene_page.ScenePage` drives either.
Measured on this project's machine (docs/view.md): it needs an OpenGL window (Qt's offscreen platform
has none: "QOpenGLWidget is not supported on this platform"), and on CPU rendering (Mesa llvmpipe
under Xvfb) a frame costs about 4x what the child process's EGL image does (the widget's frame is
composed and swapped through X), so :func:`choose` takes it only on a hardware OpenGL. gtkit's own
renderer (moderngl on EGL) keeps rendering correctly in the same process beside VTK on GLX
(tests/test_gui_x11.py).
"""
from __future__ import annotations

import os
import time

import numpy as np

SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "software")


def gl_renderer() -> str | None:
    """The OpenGL renderer string Qt's windows get here, or None when Qt has no OpenGL windows."""
    from PySide6.QtGui import QGuiApplication, QOffscreenSurface, QOpenGLContext

    if QGuiApplication.platformName() in ("offscreen", "minimal"):
        return None
    ctx, surf = QOpenGLContext(), QOffscreenSurface()
    surf.create()
    if not ctx.create() or not ctx.makeCurrent(surf):
        return None
    try:
        return str(ctx.functions().glGetString(0x1F01) or "")  # GL_RENDERER
    finally:
        ctx.doneCurrent()


def choose() -> tuple[str, str]:
    """("interactive" | "image", why). ``GTKIT_SCENE_VIEW=interactive|image`` overrides."""
    import importlib.util

    want = os.environ.get("GTKIT_SCENE_VIEW", "auto").lower()
    if want in ("interactive", "image"):
        return want, f"GTKIT_SCENE_VIEW={want}"
    r = gl_renderer()
    if r is None:
        return "image", "Qt has no OpenGL windows on this platform"
    if any(s in r.lower() for s in SOFTWARE_GL):
        return "image", f"CPU rendering ({r}): the offscreen image is faster"
    if importlib.util.find_spec("pyvistaqt") is None:  # (importing it costs 1-2 s: pyvista's plotting, matplotlib)
        return "image", "pyvistaqt is not installed"
    return "interactive", f"OpenGL: {r}"


class InteractiveScene:
    """The scene in a QtInteractor inside ``parent``; ``widget`` goes into the tab's layout."""

    def __init__(self, project_root, parent=None, settings=None):
        from pyvistaqt import QtInteractor

        from gtkit.view import scene as S

        t0 = time.perf_counter()
        self.S = S
        self.settings = settings or S.ViewSettings()
        self.scene = S.load_scene(project_root, self.settings)
        t_load = time.perf_counter() - t0
        t1 = time.perf_counter()
        self.qi = QtInteractor(parent, multi_samples=0)  # MSAA on llvmpipe: several times slower frames
        self.qi.set_background("#20242a")
        S.build(self.qi, self.scene, self.settings)
        S.set_overview(self.qi, self.scene, "oblique")
        self.widget = self.qi.interactor
        self.info = S.describe(self.scene) | {"load_s": t_load, "build_s": time.perf_counter() - t1}
        self.open_s = time.perf_counter() - t0

    def _current(self):
        self.widget.makeCurrent()  # gtkit's renderer (the review) may have made its own context current

    def render(self) -> np.ndarray:
        self._current()
        self.qi.render()
        return self.qi.screenshot(None, return_img=True)[..., :3]

    def draw(self):
        self._current()
        self.qi.render()

    def overview(self, which: str = "oblique"):
        self.S.set_overview(self.qi, self.scene, which)

    def photo(self, name: str) -> bool:
        pose, cam = self.S.pose_of(self.scene, name)
        if pose is None:
            return False
        self.S.set_photo_view(self.qi, pose, cam)
        return True

    def orbit(self, azimuth_deg: float, elevation_deg: float):
        cam = self.qi.camera
        cam.Azimuth(float(azimuth_deg))
        cam.Elevation(float(elevation_deg))
        cam.OrthogonalizeViewUp()
        self.qi.reset_camera_clipping_range()

    def camera(self) -> dict:
        c = self.qi.camera
        return {"position": list(c.position), "focal_point": list(c.focal_point), "up": list(c.up),
                "view_angle": c.view_angle}

    def close(self):
        self.qi.close()
