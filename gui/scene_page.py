"""The 3D scene tab: the project's model, reference cameras (frusta), query trajectories (prior,
pseudo-GT, localized coloured by error), tie points, GCPs with residual vectors, targets with their
tracks and lines of sight (:mod:`gtkit.view.scene`).

VTK renders offscreen in a child process (:class:`gtkit.view.process.SceneProcess`; VTK and the
annotator's own moderngl renderer must not share a process) and the tab shows the image it
returns. A pyvistaqt ``QtInteractor`` is not used: it needs a native OpenGL window in this process
(GLX under X), which Qt's offscreen platform cannot give and which would share Mesa with the review's
renderer. Left drag orbits, right drag pans, the wheel zooms; "Look through photo" puts the view at
the photo selected in the other tabs (also done when the tab is opened). The scene is built the first
time the tab is shown, so the annotator opens as fast as before."""
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
            + f"; opened in {self.open_s:.2f} s. "
            "Left drag: orbit, right drag: pan, wheel: zoom.")
        self.status.emit(f"3D scene opened in {self.open_s:.2f} s")

    def image(self) -> np.ndarray:
        """The scene as last drawn (H, W, 3) uint8."""
        return self._img

    def draw(self):
        if self.proc is None:
            return
        t = time.perf_counter()
        img = self.proc.render()
        self._img = img
        q = QImage(img.data, img.shape[1], img.shape[0], 3 * img.shape[1], QImage.Format.Format_RGB888).copy()
        self.view.setPixmap(QPixmap.fromImage(q))
        self.frame_ms.append(1000 * (time.perf_counter() - t))

    def resized(self):
        if self.proc is None or self._img is None:
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
