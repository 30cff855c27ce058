"""The 3D scene tab: the project's model, reference cameras (frusta), query trajectories (prior,
pseudo-GT, localized coloured by error), tie points, GCPs with residual vectors, targets with their
tracks and lines of sight (:mod:`gtkit.view.scene`).

Two ways to show it (:func:`gui.scene_interactive.choose`): on a hardware OpenGL, a pyvistaqt
``QtInteractor`` in the tab (:mod:`gui.scene_interactive`; VTK's own mouse handling); otherwise (CPU
rendering, Qt's offscreen platform, no pyvistaqt) VTK renders offscreen through EGL in a child
process (:class:`gtkit.view.process.SceneProcess`) and the tab shows the image it returns: left drag
orbits, right drag pans, the wheel zooms. ``GTKIT_SCENE_VIEW=interactive|image`` chooses by hand.
"Look through photo" puts the view at the photo selected in the other tabs (also done when the tab
is opened). The scene is built the first time the tab is shown, so the annotator opens as fast as
before."""
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
        self.proc = None
        self.frame_ms: list[float] = []
        self.open_s: float | None = None
        self.photo: str | None = None
        self.backend, self.backend_why = "image", ""
        self._img = None
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
        if self.proc is not None:
            return
        from gtkit.view.process import SceneProcess

        from .scene_interactive import InteractiveScene, choose

        self.backend, self.backend_why = choose()
        if self.backend == "interactive":
            try:
                self.proc = InteractiveScene(self.project.paths.root, self)
                self.layout().replaceWidget(self.view, self.proc.widget)
                self.view.hide()
            except Exception as e:  # noqa: BLE001 - any failure: the image path still works
                self.backend, self.backend_why = "image", f"the interactive view failed ({type(e).__name__}: {e})"
                self.proc = None
        if self.proc is None:
            w, h = max(self.view.width(), 320), max(self.view.height(), 240)
            self.proc = SceneProcess(self.project.paths.root, w, h)
        self.draw()
        self.open_s = self.proc.open_s + self.frame_ms[-1] / 1000
        i = self.proc.info
        self.info.setText(
            f"model {i['triangles'][1]:,} of {i['triangles'][0]:,} triangles; {i['n_reference_cameras']} reference "
            f"cameras ({i['reference_source']}); trajectories: "
            + (", ".join(f"{k} {v}" for k, v in i["trajectories"].items()) or "none")
            + (f"; colour = {i['error_source']}" if i["error_source"] else "")
            + f"; {i['n_tiepoints']} tie points ({i['n_tiepoints_flagged']} left out); {i['n_gcps']} GCPs; "
            f"{i['n_targets']} placed targets in {i['n_tracks']} tracks"
            + (f", {i['n_targets_unplaced']} clicks not placed" if i["n_targets_unplaced"] else "")
            + f"; opened in {self.open_s:.2f} s; {self.backend} view ({self.backend_why}). "
            + ("Left drag: rotate, middle drag: pan, wheel: zoom." if self.backend == "interactive"
               else "Left drag: orbit, right drag: pan, wheel: zoom."))
        self.status.emit(f"3D scene opened in {self.open_s:.2f} s")

    def view_widget(self):
        """The widget that shows the scene (the image label, or the interactive OpenGL widget)."""
        return self.proc.widget if self.backend == "interactive" and self.proc is not None else self.view

    def image(self) -> np.ndarray:
        """The scene as last drawn (H, W, 3) uint8."""
        if self.backend == "interactive" and self.proc is not None:
            return self.proc.render()
        return self._img

    def draw(self):
        if self.proc is None:
            return
        t = time.perf_counter()
        if self.backend == "interactive":
            self.proc.draw()
        else:
            img = self.proc.render()
            self._img = img
            q = QImage(img.data, img.shape[1], img.shape[0], 3 * img.shape[1], QImage.Format.Format_RGB888).copy()
            self.view.setPixmap(QPixmap.fromImage(q))
        self.frame_ms.append(1000 * (time.perf_counter() - t))

    def resized(self):
        if self.proc is None or self._img is None or self.backend != "image":
            return
        w, h = self.view.width(), self.view.height()
        if w >= 64 and h >= 64 and (self._img.shape[1], self._img.shape[0]) != (w, h):
            self.proc.size(w, h)
            self.draw()

    # --- navigation ----------------------------------------------------------------------------
    def drag(self, dx: float, dy: float, pan: bool = False):
        if self.proc is None:
            return
        if pan:
            self.proc.pan(dx, dy, self.view.height())
        else:
            self.proc.orbit(-0.4 * dx, 0.4 * dy)
        self.draw()

    def zoom(self, factor: float):
        if self.proc is None:
            return
        self.proc.dolly(factor)
        self.draw()

    def overview(self, which: str):
        self.ensure_scene()
        self.proc.overview(which)
        self.draw()

    def look_through(self, name: str | None):
        """Put the view at the photo's pose (the photo selected in the other tabs)."""
        self.ensure_scene()
        if not name or not self.proc.photo(name):
            self.status.emit(f"no pose for {name}" if name else "no photo selected in the other tabs")
            return False
        self.draw()
        self.status.emit(f"3D view through {name}")
        return True

    def set_photo(self, name: str | None):
        self.photo = name

    def release(self):
        if self.proc is not None:
            self.proc.close()
            self.proc = None
