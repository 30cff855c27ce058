"""The Targets page: clicks or boxes on targets in zoom photos, for ``gtkit track``.

A left click on the photo places a target's foot point (the pixel under the cursor, in gtkit's
COLMAP convention, sub-pixel when zoomed in); a left drag draws a box around it instead (the
tracker then uses the box centre lifted by half the target's height, see
:mod:`gtkit.track.targets`). The label (one track per label) is taken from the label box;
drag a marker to move its target (a box moves with its centre), Delete removes the selected
one, Ctrl+Z / Ctrl+Shift+Z undo / redo, N / P step through the zoom photos; wheel zoom, right
or middle drag pan, the loupe, as on the tie-point page. Every edit is in the project's
``detections.csv`` at once (:mod:`gui.target_store`), where ``gtkit track`` reads it without
options. After ``gtkit track`` ran, each target's tracked position (``exports/tracks.csv``) is
shown beside it.
"""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

from PySide6.QtCore import QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QColor, QPen, QUndoStack
from PySide6.QtWidgets import (QComboBox, QGraphicsRectItem, QLabel, QListWidget, QListWidgetItem,
                               QPushButton, QTreeWidget, QTreeWidgetItem, QVBoxLayout, QWidget)

from gtkit.errors import GtkitError
from gtkit.track.calibrate import query_photos

from .image_view import ImageView, Marker
from .page_layout import side_and_photo
from .target_store import PLURAL, Target, TargetStore, box_target, match_result, tracked_results
from .target_undo import AddTarget, ChangeTarget, DeleteTarget
from .write_guard import WriteGuard

log = logging.getLogger(__name__)

ROLE = Qt.ItemDataRole.UserRole
DRAG_PX = 5.0   # a left press that moves this many screen pixels draws a box instead of a click


def zoom_photos(all_queries: list[str]) -> list[str]:
    """The zoom photos (``<idx>_Z``) among the query photos; all query photos if there are none."""
    z = [n for n in all_queries if n.rsplit("/", 1)[-1].rsplit(".", 1)[0].endswith("_Z")]
    return z or list(all_queries)


def label_color(label: str) -> QColor:
    h = sum((i + 1) * ord(c) for i, c in enumerate(label)) * 47 % 360
    return QColor.fromHsv(h, 220, 255)


class TargetView(ImageView):
    """An :class:`ImageView` where a left press on the photo is resolved on release: a click
    (``clicked``) or, when the cursor moved, a box (``box_drawn``, scene = photo pixels)."""

    box_drawn = Signal(float, float, float, float)

    def __init__(self, cache=None, parent=None, title: str = ""):
        super().__init__(cache, parent, title)
        self._press = None          # (screen position, photo position) of a left press on the photo
        self._rubber = QGraphicsRectItem()
        pen = QPen(QColor(255, 230, 0), 1.5, Qt.PenStyle.DashLine)
        pen.setCosmetic(True)
        self._rubber.setPen(pen)
        self._rubber.setZValue(20)
        self._rubber.hide()
        self.scene().addItem(self._rubber)
        self.boxes: dict[str, QGraphicsRectItem] = {}

    def _photo_point(self, pos) -> QPointF:
        return self.viewportTransform().inverted()[0].map(pos)  # sub-pixel position

    def _clamped(self, p: QPointF) -> QPointF:
        return QPointF(min(max(p.x(), 0.0), self.full_size[0]), min(max(p.y(), 0.0), self.full_size[1]))

    def mousePressEvent(self, e):
        if e.button() == Qt.MouseButton.LeftButton and not isinstance(self.itemAt(e.position().toPoint()), Marker):
            p = self._photo_point(e.position())
            if self.full_size[0] and 0 <= p.x() <= self.full_size[0] and 0 <= p.y() <= self.full_size[1]:
                self._press = (QPointF(e.position()), p)
            return
        super().mousePressEvent(e)

    def _dragged(self, pos) -> bool:
        d = QPointF(pos) - self._press[0]
        return max(abs(d.x()), abs(d.y())) >= DRAG_PX

    def mouseMoveEvent(self, e):
        if self._press is not None:
            if self._dragged(e.position()):
                end = self._clamped(self._photo_point(e.position()))
                self._rubber.setRect(QRectF(self._press[1], end).normalized())
                self._rubber.show()
            self._update_loupe(e.position().toPoint())
            return
        super().mouseMoveEvent(e)

    def mouseReleaseEvent(self, e):
        if self._press is not None and e.button() == Qt.MouseButton.LeftButton:
            start = self._press[1]
            dragged = self._dragged(e.position())
            self._press = None
            self._rubber.hide()
            if dragged:
                end = self._clamped(self._photo_point(e.position()))
                if abs(end.x() - start.x()) > 0 and abs(end.y() - start.y()) > 0:
                    self.box_drawn.emit(start.x(), start.y(), end.x(), end.y())
            else:
                self.clicked.emit(start.x(), start.y())
            return
        super().mouseReleaseEvent(e)

    def set_box(self, key: str, box, color: QColor, active: bool):
        r = self.boxes.get(key)
        if r is None:
            r = QGraphicsRectItem()
            r.setAcceptedMouseButtons(Qt.MouseButton.NoButton)
            r.setZValue(4)
            self.scene().addItem(r)
            self.boxes[key] = r
        pen = QPen(color, 2.5 if active else 1.5)
        pen.setCosmetic(True)
        r.setPen(pen)
        r.setRect(QRectF(QPointF(box[0], box[1]), QPointF(box[2], box[3])))

    def remove_box(self, key: str):
        r = self.boxes.pop(key, None)
        if r is not None:
            self.scene().removeItem(r)


class TargetPage(QWidget):
    status = Signal(str)
    session_changed = Signal()

    def __init__(self, project, cache, undo_stack: QUndoStack | None = None, parent=None, guard=None):
        super().__init__(parent)
        self.project, self.paths = project, project.paths
        self.guard = guard or WriteGuard(project.paths.root)
        self.undo = undo_stack or QUndoStack(self)
        self.all_queries = query_photos(project)
        self.photos = zoom_photos(self.all_queries)
        self.image: str | None = None
        self.active: str | None = None
        self.error: str | None = None
        self.store: TargetStore | None = None
        try:
            self.store = TargetStore(self.paths.detections, self.all_queries, guard=self.guard)
        except GtkitError as e:   # never overwrite a file we cannot read: the page stays read-only
            self.error = str(e)
            log.error("%s", e)
        self._results: list[dict] = []
        self._results_mtime = None
        self._restore_state: dict = {}

        self.view = TargetView(cache, title="zoom")
        self.title = QLabel("zoom photo")
        self.photo_list = QListWidget()
        self.label_box = QComboBox()
        self.label_box.setEditable(True)
        self.label_box.setInsertPolicy(QComboBox.InsertPolicy.NoInsert)
        for lab in dict.fromkeys(["car", "person", *(self.store.labels() if self.store else [])]):
            self.label_box.addItem(lab)
        self.label_box.setToolTip("label of new targets (one track per label)")
        self.relabel_button = QPushButton("Give the selected target this label")
        self.table = QTreeWidget()
        self.table.setHeaderLabels(["label", "kind", "x px", "y px", "tracked (x, y, z; sigma_h)"])
        self.table.setRootIsDecorated(False)
        for c, wdt in enumerate((70, 40, 60, 60)):
            self.table.setColumnWidth(c, wdt)
        self.detail = QLabel()          # the selected target and its tracked position, in full
        self.detail.setWordWrap(True)
        self.detail.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.file_label = QLabel()
        self.file_label.setWordWrap(True)
        help_ = QLabel("click = foot point, drag = box; drag a marker to move; Delete, Ctrl+Z / Ctrl+Shift+Z; "
                       "N / P = next / previous photo")
        help_.setWordWrap(True)

        side = QVBoxLayout()
        side.addWidget(QLabel("Zoom photos (N / P)"))
        side.addWidget(self.photo_list, 3)
        side.addWidget(QLabel("Label (one track per label)"))
        side.addWidget(self.label_box)
        side.addWidget(self.relabel_button)
        side.addWidget(help_)
        side.addWidget(QLabel("Targets in this photo"))
        side.addWidget(self.table, 2)
        side.addWidget(self.detail)
        side.addWidget(self.file_label)
        side_and_photo(self, side, self.title, self.view, (380, 440))

        self._fill_photo_list()
        self.photo_list.currentItemChanged.connect(
            lambda cur, _p: cur is not None and cur.data(ROLE) != self.image and self.open_image(cur.data(ROLE)))
        self.table.itemClicked.connect(lambda it, _c: self.select(it.data(0, ROLE)))
        self.relabel_button.clicked.connect(self.relabel_active)
        self.view.clicked.connect(self.place_pixel)
        self.view.box_drawn.connect(self.place_box)
        self.view.marker_pressed.connect(self.select)
        self.view.marker_moved.connect(self._marker_moved)
        self.view.view_changed.connect(self.session_changed)
        self.undo.indexChanged.connect(lambda _i: self.refresh())
        self._update_file_label()

    # --- photos ------------------------------------------------------------------------
    def _fill_photo_list(self):
        counts = self.store.counts() if self.store else {}
        names = list(dict.fromkeys(self.photos + sorted(counts)))  # photos with targets are always listed
        self.photo_list.blockSignals(True)
        cur = self.image
        self.photo_list.clear()
        for n in names:
            it = QListWidgetItem(f"{n}   [{counts[n]}]" if counts.get(n) else n)
            it.setData(ROLE, n)
            self.photo_list.addItem(it)
            if n == cur:
                self.photo_list.setCurrentItem(it)
        self.photo_list.blockSignals(False)

    def photo_names(self) -> list[str]:
        return [self.photo_list.item(i).data(ROLE) for i in range(self.photo_list.count())]

    def open_image(self, name: str | None = None, view: dict | None = None):
        names = self.photo_names()
        if name not in names:
            name = names[0] if names else None
        if name is None:
            return
        if name != self.image:
            self.image, self.active = name, None
            self.view.clear_markers()
            for k in list(self.view.boxes):
                self.view.remove_box(k)
            self.view.show_image(self.paths.images / name)
            self.title.setText(f"zoom photo: {name}")
        self._fill_photo_list()
        if view:
            self.view.set_view_state(view)
        self.refresh()
        self.session_changed.emit()

    def step(self, d: int):
        names = self.photo_names()
        if names:
            i = names.index(self.image) if self.image in names else -1
            self.open_image(names[(i + d) % len(names)])

    def ensure_shown(self):
        """Open the restored (or first) photo the first time the page is shown; later, show
        what changed meanwhile (e.g. ``gtkit track`` ran in a terminal)."""
        if self.image is None:
            st = self._restore_state
            self.open_image(st.get("image"), st.get("view"))
        else:
            self.refresh()

    # --- edits ---------------------------------------------------------------------------
    def current_label(self) -> str:
        lab = " ".join(self.label_box.currentText().split())
        return lab or "target"

    def _refuse(self, t: Target | None = None) -> bool:
        """Whether an edit must not happen (said in the status bar): the file could not be read,
        another program changed it since, another gtkit process writes the project now, or ``t`` is of
        the other kind than the file's."""
        if self.guard.blocked():
            self.status.emit(self.guard.blocked())
            return True
        if self.store is None:
            self.status.emit(f"{self.error} -- not editing it (fix or move the file, then reopen)")
            return True
        if self.store.changed_on_disk():
            self.status.emit(f"{self.store.path}: changed on disk since the annotator read it -- not overwriting "
                             "it; reopen the annotator to load it")
            return True
        if t is None:
            return False
        try:
            self.store.check_kind(t)
        except GtkitError as e:
            self.status.emit(str(e))
            return True
        return False

    def place_pixel(self, x: float, y: float):
        if self.image is None:
            return
        t = Target(self.store.new_id() if self.store else "", self.image, float(x), float(y), self.current_label())
        if self._refuse(t):
            return
        self.undo.push(AddTarget(self.store, t))
        self.active = t.id
        self.refresh()
        self.status.emit(f"{t.label} at ({x:.2f}, {y:.2f}) in {self.image} -> {self.paths.detections.name}")

    def place_box(self, x0: float, y0: float, x1: float, y1: float):
        if self.image is None:
            return
        t = box_target(self.store.new_id() if self.store else "", self.image, x0, y0, x1, y1, self.current_label())
        if self._refuse(t):
            return
        self.undo.push(AddTarget(self.store, t))
        self.active = t.id
        self.refresh()
        b = t.box
        self.status.emit(f"{t.label} box ({b[0]:.1f}, {b[1]:.1f})-({b[2]:.1f}, {b[3]:.1f}) in {self.image}")

    def move(self, tid: str, dx: float, dy: float):
        t = self.store.get(tid) if self.store else None
        if t is None or (dx == 0 and dy == 0):
            return
        if self._refuse():
            self.refresh()   # the marker goes back where the file has it
            return
        W, H = self.view.full_size
        lo = (t.box[0], t.box[1]) if t.box else (t.x, t.y)   # keep the target inside the photo
        hi = (t.box[2], t.box[3]) if t.box else (t.x, t.y)
        if W and H:
            dx, dy = min(max(dx, -lo[0]), W - hi[0]), min(max(dy, -lo[1]), H - hi[1])
        self.undo.push(ChangeTarget(self.store, t, t.moved(dx, dy), "move"))
        self.active = tid
        self.refresh()

    def _marker_moved(self, key, ox, oy, nx, ny):
        if self.store is None:
            self.refresh()
            return
        self.move(key, nx - ox, ny - oy)

    def relabel_active(self):
        t = self.store.get(self.active) if (self.store and self.active) else None
        lab = self.current_label()
        if self.label_box.findText(lab) < 0:
            self.label_box.addItem(lab)
        if t is None or t.label == lab or self._refuse():
            return
        self.undo.push(ChangeTarget(self.store, t, replace(t, label=lab), "relabel"))
        self.refresh()

    def delete_active(self):
        if self.store is None or self.active is None or self.store.get(self.active) is None or self._refuse():
            return
        self.undo.push(DeleteTarget(self.store, self.active))
        self.active = None
        self.refresh()

    def undo_(self):
        if not self._refuse():
            self.undo.undo()

    def redo_(self):
        if not self._refuse():
            self.undo.redo()

    def select(self, tid: str | None):
        self.active = tid
        t = self.store.get(tid) if (self.store and tid) else None
        if t is not None:
            self.label_box.setCurrentText(t.label)
        self.refresh()

    def deselect(self):
        self.select(None)

    # --- display -------------------------------------------------------------------------
    def results(self) -> list[dict]:
        """The tracker's rows (re-read when exports/tracks.csv changes)."""
        p = self.paths.tracks
        m = p.stat().st_mtime_ns if p.is_file() else None
        if m != self._results_mtime:
            self._results, self._results_mtime = tracked_results(p) if m else [], m
        return self._results

    @staticmethod
    def result_text(r: dict | None) -> str:
        if r is None:
            return "(not tracked yet: run gtkit track)"
        if r.get("status") != "ok":
            return f"{r.get('status')}: {r.get('message', '')}"
        s = f"{float(r['x']):.2f}, {float(r['y']):.2f}, {float(r['z']):.2f}"
        if r.get("sigma_h_m"):
            s += f"; {float(r['sigma_h_m']):.2f} m"
        return s

    @staticmethod
    def detail_text(t: Target, r: dict | None, crs: str) -> str:
        where = (f"box ({t.box[0]:.1f}, {t.box[1]:.1f})-({t.box[2]:.1f}, {t.box[3]:.1f}), centre "
                 if t.box is not None else "foot point ")
        s = f"<b>{t.label}</b>: {where}({t.x:.2f}, {t.y:.2f}) px<br>"
        if r is None:
            return s + "not tracked yet (run <tt>gtkit track</tt>)"
        if r.get("status") != "ok":
            return s + f"tracker: {r.get('status')}: {r.get('message', '')}"
        s += (f"tracked: x {float(r['x']):.2f}, y {float(r['y']):.2f}, z {float(r['z']):.2f} m ({crs})<br>"
              f"lon {r.get('lon')}, lat {r.get('lat')}")
        if r.get("sigma_h_m"):
            s += f"; sigma horizontal {float(r['sigma_h_m']):.2f} m, vertical {float(r.get('sigma_z_m') or 0):.2f} m"
        return s

    def refresh(self):
        if self.image is None:
            return
        targets = self.store.in_image(self.image) if self.store else []
        if self.active is not None and (self.store is None or self.store.get(self.active) is None):
            self.active = None
        keys = {t.id for t in targets}
        for k in [k for k in self.view.markers if k not in keys]:
            self.view.remove_marker(k)
        for k in [k for k in self.view.boxes if k not in keys]:
            self.view.remove_box(k)
        rows = self.results()
        self.table.clear()
        self.detail.setText("")
        crs = self.project.frame.crs_spec
        for t in targets:
            active = t.id == self.active
            self.view.set_marker(t.id, t.x, t.y, "active" if active else "normal", t.label,
                                 movable=self.store is not None)
            if t.box is not None:
                self.view.set_box(t.id, t.box, QColor(255, 230, 0) if active else label_color(t.label), active)
            else:
                self.view.remove_box(t.id)
            it = QTreeWidgetItem([t.label, t.kind, f"{t.x:.2f}", f"{t.y:.2f}", self.result_text(match_result(t, rows))])
            it.setData(0, ROLE, t.id)
            self.table.addTopLevelItem(it)
            if active:
                self.table.setCurrentItem(it)
                self.detail.setText(self.detail_text(t, match_result(t, rows), crs))
        self._fill_photo_list()
        self._update_file_label()

    def _update_file_label(self):
        if self.store is None:
            self.file_label.setText(f"<b>cannot read</b> {self.error}<br>(the file is left as it is; editing is off)")
            self.file_label.setStyleSheet("color: #c00000;")
            return
        n = len(self.store)
        kind = self.store.kind()
        self.file_label.setText(f"{n} target{'s' if n != 1 else ''}{f' ({PLURAL[kind]})' if kind else ''} in "
                                f"{self.paths.detections} -- saved at every edit; `gtkit track` reads it")

    # --- session ---------------------------------------------------------------------------
    def session_state(self) -> dict:
        if self.image is None:
            return dict(self._restore_state)
        return {"image": self.image, "view": self.view.view_state()}

    def restore(self, st: dict | None):
        self._restore_state = dict(st or {})

    def detections_path(self) -> Path:
        return self.paths.detections
