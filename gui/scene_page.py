"""The 3D scene tab: the project's model, reference cameras (frusta), query trajectories (prior,
pseudo-GT, localized coloured by error), GCPs with residual vectors and target tracks
(:mod:`gtkit.view.scene`).

VTK renders offscreen (EGL) into an image shown in the tab, rather than in a pyvistaqt
``QtInteractor``: that widget needs a native OpenGL window (GLX under X), which Qt's offscreen
platform cannot give and which must not follow the annotator's own EGL renderer in one process.
Left drag orbits, right drag pans, the wheel zooms; "Look through photo" puts the view at the
photo selected in the other tabs (it also happens when the tab is opened). The scene is built the
first time the tab is shown, so the annotator opens as fast as before."""
from __future__ import annotations

import time

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QImage, QPixmap
from PySide6.QtWidgets import QHBoxLayout, QLabel, QPushButton, QSizePolicy, QVBoxLayout, QWidget


class SceneView(QLabel):
    """Shows the rendered scene; mouse drags orbit and pan, the wheel zooms."""

    def __init__(self, page):
        super().__init__()
        self.page = page
        self.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Ignored)
        self.setMinimumSize(320, 240)
        self._last = None

    def mousePressEvent(self, e):
        self._last = (e.position(), e.button())

    def mouseMoveEvent(self, e):
        if self._last is None:
            return
        p0, button = self._last
        d = e.position() - p0
        self._last = (e.position(), button)
        self.page.drag(d.x(), d.y(), pan=button != Qt.MouseButton.LeftButton)

    def mouseReleaseEvent(self, e):
        self._last = None

    def wheelEvent(self, e):
        self.page.zoom(1.15 ** (e.angleDelta().y() / 120.0))

    def resizeEvent(self, e):
        super().resizeEvent(e)
        self.page.resized()


class ScenePage(QWidget):
    status = Signal(str)
    session_changed = Signal()

    def __init__(self, project, parent=None):
        super().__init__(parent)
        self.project = project
        self.scene = None
        self.plotter = None
        self.frame_ms: list[float] = []
        self.open_s: float | None = None
        self.photo: str | None = None
        self.view = SceneView(self)
        self.info = QLabel("the 3D scene is built when this tab is first shown")
        self.info.setWordWrap(True)
        bar = QHBoxLayout()
        for label, fn in (("Overview", lambda: self.overview("oblique")), ("Top", lambda: self.overview("top")),
                          ("Look through photo", lambda: self.look_through(self.photo))):
            b = QPushButton(label)
            b.clicked.connect(fn)
            bar.addWidget(b)
        bar.addStretch(1)
        lay = QVBoxLayout(self)
        lay.addLayout(bar)
        lay.addWidget(self.view, 1)
        lay.addWidget(self.info)

    # --- building and drawing ------------------------------------------------------------------
    def ensure_scene(self):
        if self.plotter is not None:
            return
        from gtkit.view.scene import build, load_scene, new_plotter, set_overview

        t0 = time.perf_counter()
        self.scene = load_scene(self.project)
        w, h = max(self.view.width(), 320), max(self.view.height(), 240)
        self.plotter = new_plotter(w, h)
        build(self.plotter, self.scene)
        set_overview(self.plotter, self.scene, "oblique")
        self.draw()
        self.open_s = time.perf_counter() - t0
        sc = self.scene
        self.info.setText(
            f"model {sc.n_triangles_shown:,} of {sc.n_triangles_model:,} triangles; {len(sc.reference)} reference cameras "
            f"({sc.reference_source}); trajectories: " + (", ".join(f"{k} {len(v)}" for k, v in sc.queries.items()) or "none")
            + (f"; colour = {sc.error_source}" if sc.error_source else "")
            + f"; {len(sc.gcps)} GCPs, {len(sc.tracks)} tracks; opened in {self.open_s:.2f} s. "
            "Left drag: orbit, right drag: pan, wheel: zoom.")
        self.status.emit(f"3D scene opened in {self.open_s:.2f} s")

    def image(self) -> np.ndarray:
        """The scene as last drawn (H, W, 3) uint8."""
        return self._img

    def draw(self):
        if self.plotter is None:
            return
        t = time.perf_counter()
        self.plotter.render()  # (pyvista's screenshot reads the last frame; it does not render)
        img = np.ascontiguousarray(self.plotter.screenshot(None, return_img=True)[..., :3])
        self._img = img
        q = QImage(img.data, img.shape[1], img.shape[0], 3 * img.shape[1], QImage.Format.Format_RGB888).copy()
        self.view.setPixmap(QPixmap.fromImage(q))
        self.frame_ms.append(1000 * (time.perf_counter() - t))

    def resized(self):
        if self.plotter is None:
            return
        w, h = self.view.width(), self.view.height()
        if w >= 64 and h >= 64 and tuple(self.plotter.window_size) != (w, h):
            self.plotter.window_size = (w, h)
            self.draw()

    # --- navigation ----------------------------------------------------------------------------
    def drag(self, dx: float, dy: float, pan: bool = False):
        if self.plotter is None:
            return
        cam = self.plotter.camera
        if pan:
            d = np.linalg.norm(np.subtract(cam.position, cam.focal_point))
            s = 2 * d * np.tan(np.radians(cam.view_angle) / 2) / max(self.view.height(), 1)
            fwd = np.subtract(cam.focal_point, cam.position)
            fwd /= np.linalg.norm(fwd)
            up = np.asarray(cam.up, float)
            right = np.cross(fwd, up)
            move = (-dx * right + dy * up) * s
            cam.position, cam.focal_point = np.add(cam.position, move), np.add(cam.focal_point, move)
        else:
            cam.Azimuth(-0.4 * dx)
            cam.Elevation(0.4 * dy)
            cam.OrthogonalizeViewUp()
        self.plotter.reset_camera_clipping_range()
        self.draw()

    def zoom(self, factor: float):
        if self.plotter is None:
            return
        self.plotter.camera.Dolly(factor)
        self.plotter.reset_camera_clipping_range()
        self.draw()

    def overview(self, which: str):
        self.ensure_scene()
        from gtkit.view.scene import set_overview

        set_overview(self.plotter, self.scene, which)
        self.draw()

    def pose_of(self, name: str | None):
        """The best pose the project has for a photo: pseudo-GT, localized, reference block, prior."""
        if not name or self.scene is None:
            return None, None
        sc = self.scene
        for kind in ("pseudo_gt", "localized", "prior"):
            if name in sc.query_poses.get(kind, {}):
                return sc.query_poses[kind][name], sc.cameras.get(name)
        if name in sc.reference:
            return sc.reference[name]
        return None, None

    def look_through(self, name: str | None):
        """Put the view at the photo's pose (the photo selected in the other tabs)."""
        self.ensure_scene()
        pose, cam = self.pose_of(name)
        if pose is None:
            self.status.emit(f"no pose for {name}" if name else "no photo selected in the other tabs")
            return False
        from gtkit.view.scene import set_photo_view

        set_photo_view(self.plotter, pose, cam)
        self.draw()
        self.status.emit(f"3D view through {name}")
        return True

    def set_photo(self, name: str | None):
        self.photo = name

    def release(self):
        if self.plotter is not None:
            self.plotter.close()
            self.plotter = None
