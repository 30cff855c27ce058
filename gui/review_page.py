"""Alignment review: the reference model rendered at the image's pose over the photo (blend
slider, swipe divider, edge overlay, checkerboard), the alignment measure, and a verdict per
image (accept Y, reject X, needs work W) saved to ``review.json`` at once."""
from __future__ import annotations

import logging
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QImage
from PySide6.QtWidgets import (QButtonGroup, QComboBox, QFileDialog, QHBoxLayout, QLabel, QListWidget,
                               QListWidgetItem, QPushButton, QRadioButton, QSlider, QSpinBox, QVBoxLayout, QWidget)

from gtkit.errors import GtkitError
from gtkit.render.overlay import MODES, OverlayScene, alignment, compose, default_pose_file
from gtkit.review import STATUSES, read_review, set_status

from .image_view import ImageView
from .write_guard import WriteGuard, save_under_lock

log = logging.getLogger(__name__)
ROLE = Qt.ItemDataRole.UserRole
MARK = {"accept": "✔", "reject": "✘", "needs-work": "?", None: " "}


def to_qimage(rgb: np.ndarray) -> QImage:
    rgb = np.ascontiguousarray(rgb)
    h, w = rgb.shape[:2]
    return QImage(rgb.data, w, h, 3 * w, QImage.Format.Format_RGB888).copy()



@contextmanager
def own_gl():
    """gtkit's renderer context made current for the block: the interactive 3D tab (pyvistaqt) leaves
    Qt's OpenGL context current in this thread, and moderngl's draws into it crashed (measured: a
    segmentation fault in moderngl's render). Left current afterwards, as it always was: moderngl's
    ``__exit__`` releases the context rather than restoring the previous one (measured), and Qt makes
    its own current whenever it paints."""
    from gtkit.render.renderer import gl_context

    try:
        gl_context().__enter__()
    except GtkitError:
        pass  # no headless GL: the renderer reports it itself
    yield


class ReviewPage(QWidget):
    status = Signal(str)
    session_changed = Signal()

    def __init__(self, project, pose_file=None, max_side: int = 1600, parent=None, guard=None):
        super().__init__(parent)
        self.project, self.paths = project, project.paths
        self.guard = guard or WriteGuard(project.paths.root)
        self.pose_file = pose_file or default_pose_file(self.paths)
        self.max_side = max_side
        self.scene: OverlayScene | None = None
        self.image: str | None = None
        self.mode = "blend"
        self._cache = None  # (image, photo, render, valid, scale, alignment)

        self.view = ImageView(None, title="review")
        self.view.loupe_enabled = False
        self.list = QListWidget()
        self.pose_label = QLabel()
        self.pose_label.setWordWrap(True)
        choose = QPushButton("Choose pose file ...")
        choose.clicked.connect(self._choose_pose_file)
        self.mode_buttons = QButtonGroup(self)
        modes = QHBoxLayout()
        for k, m in enumerate(MODES):
            b = QRadioButton(f"{m} ({k + 1})")
            b.setChecked(m == self.mode)
            self.mode_buttons.addButton(b, k)
            modes.addWidget(b)
        self.mode_buttons.idClicked.connect(lambda k: self.set_mode(MODES[k]))
        self.slider = QSlider(Qt.Orientation.Horizontal)
        self.slider.setRange(0, 100)
        self.slider.setValue(50)
        self.slider.valueChanged.connect(lambda _v: self.redraw())
        self.slider_label = QLabel("blend: render share")
        self.tile = QSpinBox()
        self.tile.setRange(8, 512)
        self.tile.setValue(64)
        self.tile.setSuffix(" px squares")
        self.tile.valueChanged.connect(lambda _v: self.redraw())
        self.measure = QLabel("")
        self.measure.setWordWrap(True)
        self.verdict = QLabel("")
        self.note = QComboBox()
        self.note.setEditable(True)
        self.note.addItems(["", "model differs here", "pose off", "photo blurred"])
        buttons = QHBoxLayout()
        for s, key in (("accept", "Y"), ("reject", "X"), ("needs-work", "W")):
            b = QPushButton(f"{s} ({key})")
            b.clicked.connect(lambda _=False, s=s: self.set_verdict(s))
            buttons.addWidget(b)

        side = QVBoxLayout()
        side.addWidget(QLabel("Posed images (J / K)"))
        side.addWidget(self.list, 1)
        side.addWidget(self.pose_label)
        side.addWidget(choose)
        left = QWidget()
        left.setLayout(side)
        left.setMaximumWidth(330)
        right = QVBoxLayout()
        right.addLayout(modes)
        row = QHBoxLayout()
        row.addWidget(self.slider_label)
        row.addWidget(self.slider, 1)
        row.addWidget(self.tile)
        right.addLayout(row)
        right.addWidget(self.view, 1)
        right.addWidget(self.measure)
        row2 = QHBoxLayout()
        row2.addWidget(self.verdict)
        row2.addWidget(QLabel("note:"))
        row2.addWidget(self.note, 1)
        row2.addLayout(buttons)
        right.addLayout(row2)
        lay = QHBoxLayout(self)
        lay.addWidget(left)
        lay.addLayout(right, 1)
        self.list.currentItemChanged.connect(lambda cur, _p: cur is not None and self.open_image(cur.data(ROLE)))
        self._update_slider_label()

    # --- scene ----------------------------------------------------------------------------
    def ensure_scene(self) -> bool:
        """Load the model and poses once (the renderer is reused for every image)."""
        if self.scene is not None:
            return True
        if self.pose_file is None:
            self.pose_label.setText("No poses: run `gtkit register`, or choose a pose file.")
            return False
        try:
            with own_gl():
                self.scene = OverlayScene(self.project, self.pose_file)
        except GtkitError as e:
            self.pose_label.setText(str(e))
            self.status.emit(str(e))
            return False
        self.pose_label.setText(f"poses: {self.pose_file}")
        self._fill_list()
        return True

    def _choose_pose_file(self):
        f, _ = QFileDialog.getOpenFileName(self, "Pose file (name qw qx qy qz tx ty tz)", str(self.paths.root))
        if f:
            self.set_pose_file(f)

    def set_pose_file(self, f):
        self.pose_file, self.scene, self._cache = f, None, None
        if self.ensure_scene() and self.list.count():
            self.list.setCurrentRow(0)

    def _fill_list(self):
        verdicts = read_review(self.paths.review)
        self.list.blockSignals(True)
        self.list.clear()
        for name in self.scene.images():
            it = QListWidgetItem(f"{MARK[verdicts.get(name, {}).get('status')]} {name}")
            it.setData(ROLE, name)
            self.list.addItem(it)
        self.list.blockSignals(False)

    # --- showing --------------------------------------------------------------------------
    def open_image(self, name: str | None = None):
        if not self.ensure_scene():
            return
        names = self.scene.images()
        if name not in names:
            name = names[0] if names else None
        if name is None:
            return
        self.image = name
        if self._cache is None or self._cache[0] != name:
            with own_gl():
                photo, rgb, valid, s = self.scene.render(name, self.max_side)
            self._cache = (name, photo, rgb, valid, s, alignment(photo, rgb, valid, scale=s))
        a = self._cache[5]
        self.measure.setText(f"{name}: misalignment {a.misalignment_px:.2f} px (median local shift over {a.n_tiles} "
                             f"tiles), edge distance {a.edge_distance_px:.2f} px; full-resolution pixels")
        row = next((i for i in range(self.list.count()) if self.list.item(i).data(ROLE) == name), -1)
        self.list.blockSignals(True)
        self.list.setCurrentRow(row)
        self.list.blockSignals(False)
        self._show_verdict()
        self.redraw()
        self.session_changed.emit()

    def set_mode(self, mode: str):
        self.mode = mode
        self.mode_buttons.button(MODES.index(mode)).setChecked(True)
        self._update_slider_label()
        self.redraw()
        self.session_changed.emit()

    def _update_slider_label(self):
        self.slider_label.setText({"blend": "render share", "swipe": "divider"}.get(self.mode, "(unused)"))
        self.slider.setEnabled(self.mode in ("blend", "swipe"))
        self.tile.setEnabled(self.mode == "checker")

    def composite(self) -> np.ndarray | None:
        if self._cache is None:
            return None
        _n, photo, rgb, valid, _s, _a = self._cache
        v = self.slider.value() / 100.0
        return compose(self.mode, photo, rgb, valid, alpha=v, position=v, tile=self.tile.value())

    def redraw(self):
        img = self.composite()
        if img is None:
            return
        cam = self.scene.cameras[self.image]
        self.view.show_image(None, to_qimage(img), (cam.width, cam.height))

    def step(self, d: int):
        n = self.list.count()
        if n:
            self.list.setCurrentRow((max(0, self.list.currentRow()) + d) % n)

    # --- verdicts --------------------------------------------------------------------------
    def set_verdict(self, status: str):
        if not self.image:
            return
        if self.guard.blocked():      # review.json is the report stage's input
            self.status.emit(self.guard.blocked())
            return
        a = self._cache[5] if self._cache else None
        info = {"pose_file": self.stored_pose_file()}
        if a is not None and np.isfinite(a.misalignment_px):
            info["misalignment_px"] = round(a.misalignment_px, 3)
        out = {}
        if not save_under_lock(self.guard, lambda: out.update(v=set_status(self.paths.review, self.image, status,
                                                                            self.note.currentText(), **info))):
            self.status.emit(f"not saved: {self.guard.refused}")
            return
        verdicts = out["v"]
        it = self.list.currentItem()
        if it is not None:
            it.setText(f"{MARK[status]} {self.image}")
        self._show_verdict(verdicts)
        self.status.emit(f"{self.image}: {status}; saved to review.json")

    def _show_verdict(self, verdicts=None):
        verdicts = read_review(self.paths.review) if verdicts is None else verdicts
        st = verdicts.get(self.image, {}).get("status")
        self.verdict.setText(f"verdict: {st or '(none)'}")

    def session_state(self) -> dict:
        return {"image": self.image, "mode": self.mode, "slider": self.slider.value(), "tile": self.tile.value(),
                "pose_file": self.stored_pose_file()}

    def stored_pose_file(self) -> str | None:
        """The pose file as project files store it: relative to the project root when inside it
        (a copied or moved project then reviews its own poses), else absolute (an outside file)."""
        from gtkit.project import relative_paths

        return relative_paths(str(Path(self.pose_file).absolute()), self.paths.root) if self.pose_file else None

    def restore(self, st: dict):
        if st.get("slider") is not None:
            self.slider.setValue(int(st["slider"]))
        if st.get("tile"):
            self.tile.setValue(int(st["tile"]))
        if st.get("mode") in MODES:
            self.mode = st["mode"]
            self.mode_buttons.button(MODES.index(self.mode)).setChecked(True)
            self._update_slider_label()
        self._restore_image = st.get("image")


__all__ = ["ReviewPage", "STATUSES"]
