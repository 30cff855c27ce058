"""The GCPs page: a surveyor's ground control points clicked in the photos, with predictions.

Left: the GCPs and check points with their state (clicked in k photos, image residual, X / Y / Z
error; a check point never enters the fit), the fit and the RMSE of both kinds, and "Import
coordinates..." (the dialog of ``gtkit gcp import``). Middle: the photos that see the selected GCP,
best first (near the photo's centre, near the camera), each with its prediction's 1-sigma in px.
Right: the photo zoomed at the prediction (dashed ring; the view spans a few sigma). One left click
places the GCP there (sub-pixel, full-resolution pixels), then the next photo opens; after the
chosen number of photos the next GCP. After each click the GCP is triangulated, the block refitted
(a shift or a Sim(3) to the clicked GCPs, or, with no GPS, a Sim(3) once 3 GCPs are clicked in 2+
photos) and every prediction updated (:func:`gtkit.gcp.marking.solve`). The table's residual and
X / Y / Z error columns and the fit line come from the georegistration step's own refit of the mapped
block to ``gcp_list.txt`` as saved (:meth:`gui.gcp_store.GcpStore.georegistration`, the function
``gtkit sfm`` runs: it records the same figures); the quick refit's figures where the project has no
mapped block yet.

Where the prediction is sure to 3 sigma <= 12 px and a checkered target's centre is found within
that (:mod:`gtkit.gcp.snap`), it is shown as "A": the A key places the GCP there. Keys (through the main window): N / P next / previous
photo, G next GCP, Delete removes the click
in this photo, Ctrl+Z / Ctrl+Shift+Z undo / redo. Every edit is in ``gcp_list.txt`` at once
(:mod:`gui.gcp_store`), where ``gtkit sfm`` / ``gtkit run`` read it.
"""
from __future__ import annotations

import logging

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QUndoCommand, QUndoStack
from PySide6.QtWidgets import (QFileDialog, QHBoxLayout, QLabel, QListWidget, QListWidgetItem, QPushButton, QSpinBox,
                               QTreeWidget, QTreeWidgetItem, QVBoxLayout, QWidget)

from gtkit.errors import GtkitError

from .gcp_store import GcpStore
from .image_view import ImageView
from .page_layout import side_and_photo
from .write_guard import WriteGuard

log = logging.getLogger(__name__)
ROLE = Qt.ItemDataRole.UserRole
SNAP_MAX_PX = 12.0     # a snapped mark is offered where 3 sigma of the prediction is within this (searched there)
MIN_HALF_PX = 40.0     # the zoomed view spans at least +-this many photo pixels around the prediction
SIGMAS_SHOWN = 4.0     # ... and at least +-this many sigma


class GcpView(ImageView):
    """An ImageView where every left click on the photo places (the markers only show)."""

    def mousePressEvent(self, e):
        if e.button() == Qt.MouseButton.LeftButton:
            pf = self.viewportTransform().inverted()[0].map(e.position())  # sub-pixel position
            if self.full_size[0] and 0 <= pf.x() <= self.full_size[0] and 0 <= pf.y() <= self.full_size[1]:
                self.clicked.emit(pf.x(), pf.y())
            return
        super().mousePressEvent(e)

    def mouseDoubleClickEvent(self, e):
        # two clicks in quick succession at one screen spot are two placements (the next photo
        # opens centred where the last one was), never a double click that places nothing
        self.mousePressEvent(e)


class SetClick(QUndoCommand):
    """Place (or move) ``gcp``'s click in ``photo``; undo restores what was there."""

    def __init__(self, store: GcpStore, gcp: str, photo: str, xy: tuple[float, float] | None):
        super().__init__(f"{'click' if xy else 'remove'} {gcp} in {photo}")
        self.store, self.gcp, self.photo, self.xy, self.prev = store, gcp, photo, xy, None

    def redo(self):
        if self.xy is None:
            self.prev = self.store.remove_click(self.gcp, self.photo)
        else:
            self.prev = self.store.set_click(self.gcp, self.photo, *self.xy)

    def undo(self):
        if self.prev is None:
            self.store.remove_click(self.gcp, self.photo)
        else:
            self.store.set_click(self.gcp, self.photo, *self.prev)


def state_text(s) -> tuple[str, str]:
    """(residual, error) columns of a GCP's state."""
    res = f"{s.residual_px:.2f}" if s.residual_px is not None else ""
    if s.error_m is not None:
        e = s.error_m
        err = f"{e[0]:+.3f} {e[1]:+.3f} {e[2]:+.3f}"
    else:
        err = "" if s.n_clicks == 0 else s.reason
    return res, err


def georegistration_text(g: dict) -> tuple[str, str]:
    """(residual, error) columns of a GCP from the georegistration record's ``gcp_residuals`` entry:
    the RMS of its clicks' residuals (px) and its X / Y / Z error (m), or why it has none."""
    if g.get("status") != "ok":
        return "", g.get("reason", "")
    r = np.asarray(g.get("click_residuals_px") or [], float)
    r = r[np.isfinite(r)]
    res = f"{float(np.sqrt(np.mean(r ** 2))):.2f}" if len(r) else ""
    return res, f"{g['dx_m']:+.3f} {g['dy_m']:+.3f} {g['dz_m']:+.3f}"


def georegistration_line(geo: dict | None, why: str = "") -> str:
    """The fit line of the georegistration record (what ``gtkit sfm`` will record)."""
    if geo is None:
        return f"<b>georegistration</b>: {why or 'not yet (no mapped reference block)'}"
    if "error" in geo:
        return f"<b>georegistration</b>: {geo['error']}"
    t = (f"<b>georegistration</b> (as gtkit sfm records it): fitted to {geo.get('fitted_to') or geo.get('used')}, "
         f"RMSE {geo.get('rmse_inliers_m', float('nan')):.3f} m")
    for key, what in (("gcp_rmse_m", "GCPs"), ("checkpoint_rmse_m", "check points")):
        if geo.get(key) is not None:
            t += f"; {what} RMSE {geo[key]:.3f} m"
    return t


class GcpPage(QWidget):
    status = Signal(str)
    session_changed = Signal()
    photo_shown = Signal(str, str)      # gcp, photo: a photo opened for a GCP (drivers wait on it)

    def __init__(self, project, cache, undo_stack: QUndoStack | None = None, parent=None, guard=None):
        super().__init__(parent)
        self.project, self.paths = project, project.paths
        self.undo = undo_stack or QUndoStack(self)
        self.guard = guard or WriteGuard(project.paths.root)
        self.store = GcpStore(project, guard=self.guard)
        self.gcp: str | None = None
        self.photo: str | None = None
        self.snap: tuple[float, float] | None = None   # the target's centre found near the prediction
        self._restore_state: dict = {}

        self.import_button = QPushButton("Import coordinates...")
        self.table = QTreeWidget()
        self.table.setHeaderLabels(["GCP", "kind", "clicks", "residual px", "error X Y Z m"])
        self.table.setRootIsDecorated(False)
        for c, w in enumerate((70, 50, 45, 70)):
            self.table.setColumnWidth(c, w)
        self.fit_label = QLabel()
        self.fit_label.setWordWrap(True)
        self.detail = QLabel()
        self.detail.setWordWrap(True)
        self.detail.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.per_gcp = QSpinBox()
        self.per_gcp.setRange(2, 50)
        self.per_gcp.setValue(5)
        self.per_gcp.setToolTip("photos to click each GCP in before the page moves to the next GCP")
        self.photo_list = QListWidget()
        self.view = GcpView(cache, title="gcp")
        self.title = QLabel("photo")
        self.file_label = QLabel()
        self.file_label.setWordWrap(True)
        help_ = QLabel("click = place the GCP here (then the next photo); A = accept the snapped target centre; N / P = next / previous photo, G = next GCP, "
                       "Delete = remove this photo's click, Ctrl+Z / Ctrl+Shift+Z; wheel zoom, right drag pan")
        help_.setWordWrap(True)

        side = QVBoxLayout()
        side.addWidget(self.import_button)
        side.addWidget(QLabel("GCPs and check points"))
        side.addWidget(self.table, 3)
        side.addWidget(self.fit_label)
        side.addWidget(self.detail)
        row = QHBoxLayout()
        row.addWidget(QLabel("photos per GCP"))
        row.addWidget(self.per_gcp)
        side.addLayout(row)
        side.addWidget(QLabel("Photos that see it (best first)"))
        side.addWidget(self.photo_list, 2)
        side.addWidget(help_)
        side.addWidget(self.file_label)
        side_and_photo(self, side, self.title, self.view, (400, 470))

        # single-letter keys (N, P, G, A) are the main window's shortcuts: lists that search by typed
        # letters must not take the keyboard focus from the photo
        for wdg in (self.table, self.photo_list, self.import_button):
            wdg.setFocusPolicy(Qt.FocusPolicy.NoFocus)
        self.import_button.clicked.connect(self.import_dialog)
        self.table.itemClicked.connect(lambda it, _c: self.select_gcp(it.data(0, ROLE)))
        self.photo_list.currentItemChanged.connect(
            lambda cur, _p: cur is not None and cur.data(ROLE) != self.photo and self.open_photo(cur.data(ROLE)))
        self.view.clicked.connect(self.place)
        self.view.view_changed.connect(self.session_changed)
        self.undo.indexChanged.connect(lambda _i: self.refresh())
        self.refresh()

    # --- what to show ------------------------------------------------------------------------
    def georegistration(self) -> dict | None:
        """The georegistration step's record for the saved clicks (None without a mapped block)."""
        try:
            return self.store.georegistration()
        except GtkitError as e:     # an unreadable gcp_list.txt or photo: said on the page, not raised
            return {"error": str(e)}

    def solution(self):
        return self.store.solution()

    def ranked_photos(self, gcp: str | None) -> list[str]:
        """The photos that see ``gcp`` (best first); with no prediction every photo of the block."""
        sol = self.solution()
        preds = [p.photo for p in sol.for_gcp(gcp)] if (sol and gcp) else []
        clicked = [n for n in sorted(self.store.clicks.get(gcp, {})) if n not in preds]
        if preds:
            return preds + clicked
        photos = self.store.block.photos if self.store.block else []
        return clicked + [n for n in photos if n not in clicked]

    def gcp_names(self) -> list[str]:
        return [p.name for p in self.store.points]

    # --- navigation -----------------------------------------------------------------------------
    def select_gcp(self, name: str | None, photo: str | None = None):
        if name not in self.gcp_names():
            return
        self.gcp = name
        photos = self.ranked_photos(name)
        if photo not in photos:
            todo = [n for n in photos if self.store.click(name, n) is None]
            photo = (todo or photos or [None])[0]
        self.photo = None
        self.refresh()
        if photo:
            self.open_photo(photo)

    def open_photo(self, photo: str | None, view: dict | None = None):
        if photo is None or self.gcp is None:
            return
        self.photo = photo
        self.snap = None
        self.view.clear_markers()
        self.view.show_image(self.paths.images / photo)
        self.title.setText(f"{self.gcp} in {photo}")
        sol = self.solution()
        pr = sol.at(self.gcp, photo) if sol else None
        if pr is not None:
            self.snap = self._snap(photo, pr)
        if view:
            self.view.set_view_state(view)
        elif pr is not None:
            half = max(MIN_HALF_PX, SIGMAS_SHOWN * pr.sigma_px if np.isfinite(pr.sigma_px) else MIN_HALF_PX)
            vp = self.view.viewport().rect()
            zoom = min(vp.width(), vp.height()) / (2.0 * half)
            fit_zoom = min(vp.width() / max(1, self.view.full_size[0]), vp.height() / max(1, self.view.full_size[1]))
            self.view.center_on(pr.x, pr.y, max(zoom, fit_zoom))
        else:
            self.view.fit()
        self.refresh()
        if self.isVisible():
            self.view.setFocus()
        self.session_changed.emit()
        self.photo_shown.emit(self.gcp, photo)

    def _snap(self, photo: str, pr) -> tuple[float, float] | None:
        """A checkered target's centre near the prediction (:func:`gtkit.gcp.snap.snap_target`)."""
        import cv2

        from gtkit.gcp.snap import snap_target

        gray = cv2.imread(str(self.paths.images / photo), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            return None
        if not np.isfinite(pr.sigma_px) or 3.0 * pr.sigma_px > SNAP_MAX_PX:
            return None   # the target may be farther than the search reaches: another corner would be found
        xy, _why = snap_target(gray, (pr.x, pr.y), float(max(3.0 * pr.sigma_px, 4.0)))
        return None if xy is None else (float(xy[0]), float(xy[1]))

    def accept_snap(self):
        """The A key: place the GCP at the snapped target centre (shown as "A" in the photo)."""
        if self.snap is None:
            self.status.emit("no snapped mark: no checkered target centre near the prediction, or the prediction is "
                             f"too uncertain (3 sigma > {SNAP_MAX_PX:.0f} px) to search: click it")
            return
        self.place(*self.snap)

    def step(self, d: int):
        photos = self.ranked_photos(self.gcp)
        if photos:
            i = photos.index(self.photo) if self.photo in photos else -1
            self.open_photo(photos[(i + d) % len(photos)])

    def next_gcp(self):
        """The next GCP (in list order, after the selected one) with fewer clicks than wanted."""
        names = self.gcp_names()
        if not names:
            return
        i = names.index(self.gcp) if self.gcp in names else -1
        order = names[i + 1:] + names[:i + 1]
        want = self.per_gcp.value()
        nxt = next((n for n in order if len(self.store.clicks.get(n, {})) < want), order[0])
        self.select_gcp(nxt)

    def ensure_shown(self):
        if self.gcp is None:
            st = self._restore_state
            names = self.gcp_names()
            g = st.get("gcp") if st.get("gcp") in names else (names[0] if names else None)
            if g:
                self.select_gcp(g, st.get("photo"))
                if st.get("view") and self.photo == st.get("photo"):
                    self.view.set_view_state(st["view"])
        else:
            self.refresh()

    # --- edits ------------------------------------------------------------------------------------
    def _refuse(self) -> bool:
        if self.guard.blocked():     # a gtkit run or stage writes the project: gcp_list.txt is its input
            self.status.emit(self.guard.blocked())
            return True
        if self.store.changed_on_disk():
            self.status.emit(f"{self.store.path}: changed on disk since the annotator read it -- not overwriting it; "
                             "reopen the annotator to load it")
            return True
        return False

    def place(self, x: float, y: float):
        if self.gcp is None or self.photo is None or self._refuse():
            return
        gcp, photo = self.gcp, self.photo
        self.undo.push(SetClick(self.store, gcp, photo, (float(x), float(y))))
        s = self.solution().states.get(gcp) if self.solution() else None
        msg = f"{gcp} at ({x:.2f}, {y:.2f}) in {photo} -> {self.store.path.name}"
        if s is not None and s.residual_px is not None:
            msg += f"; triangulated from {s.clicks_used} clicks, residual {s.residual_px:.2f} px"
        if s is not None and s.error_m is not None:
            msg += "; X/Y/Z error " + " ".join(f"{v:+.3f}" for v in s.error_m) + " m"
        self.status.emit(msg)
        self.advance()

    def advance(self):
        """After a click: the next photo of this GCP not clicked yet, or the next GCP."""
        if len(self.store.clicks.get(self.gcp, {})) >= self.per_gcp.value():
            self.next_gcp()
            return
        photos = self.ranked_photos(self.gcp)
        sol = self.solution()
        if not (sol and sol.for_gcp(self.gcp)):   # no prediction: on through the photos in their order
            i = photos.index(self.photo) if self.photo in photos else -1
            photos = photos[i + 1:] + photos[:i + 1]
        # with a prediction (from the fit, or from this GCP's own first 2 clicks): the best photo left
        todo = [n for n in photos if self.store.click(self.gcp, n) is None]
        if todo:
            self.open_photo(todo[0])
        else:
            self.next_gcp()

    def delete_click(self):
        if self.gcp and self.photo and self.store.click(self.gcp, self.photo) is not None and not self._refuse():
            self.undo.push(SetClick(self.store, self.gcp, self.photo, None))

    def undo_(self):
        if not self._refuse():
            self.undo.undo()

    def redo_(self):
        if not self._refuse():
            self.undo.redo()

    def import_dialog(self, path: str | None = None):
        if not path:
            path, _ = QFileDialog.getOpenFileName(self, "GCP coordinates (name x y z [acc_h [acc_v]] [check])",
                                                  str(self.paths.root), "GCP files (*.txt *.csv);;All files (*)")
        if not path:
            return
        try:
            r = self.store.import_file(path)
        except GtkitError as e:
            self.status.emit(str(e))
            return
        self.status.emit(f"{r['n']} GCPs imported from {path} ({len(r['check_points'])} check points)")
        self.refresh()
        if self.gcp is None:
            self.ensure_shown()

    # --- display -------------------------------------------------------------------------------
    def refresh(self):
        sol = self.solution()
        geo = self.georegistration()
        step = (geo or {}).get("gcp_residuals") or {}
        self.table.blockSignals(True)
        self.table.clear()
        for p in self.store.points:
            s = sol.states.get(p.name) if sol else None
            n = len(self.store.clicks.get(p.name, {}))
            if p.name in step:       # the georegistration's own figures, as gtkit sfm records them
                res, err = georegistration_text(step[p.name])
            else:
                res, err = state_text(s) if s else ("", "")
            it = QTreeWidgetItem([p.name, "check" if p.check else "GCP", str(n), res, err])
            it.setData(0, ROLE, p.name)
            self.table.addTopLevelItem(it)
            if p.name == self.gcp:
                self.table.setCurrentItem(it)
        self.table.blockSignals(False)
        if sol is None:
            self.fit_label.setText(self.store.block_error or "no GCPs: import their coordinates")
        else:
            parts = [f"<b>predictions</b>: {sol.fit}"]
            if geo is None or "error" in geo:
                for kind, check in (("GCPs", False), ("check points", True)):
                    r = sol.rmse_xyz_m(check)
                    if r is not None:
                        parts.append(f"{kind} RMSE X {r[0]:.3f} Y {r[1]:.3f} Z {r[2]:.3f} m ({sol.rmse_m(check):.3f} m 3D)")
            parts.append(georegistration_line(geo, self.store.georegistration_why))
            self.fit_label.setText("<br>".join(parts))
        self._fill_photos(sol)
        self._markers(sol)
        self._detail(sol)
        self.file_label.setText(f"{len(self.store)} clicks of {len(self.store.clicks)} GCPs in {self.store.path} -- "
                                "saved at every click; gtkit sfm / gtkit run read it")

    def _fill_photos(self, sol):
        self.photo_list.blockSignals(True)
        self.photo_list.clear()
        if self.gcp is not None:
            for n in self.ranked_photos(self.gcp):
                pr = sol.at(self.gcp, n) if sol else None
                c = self.store.click(self.gcp, n)
                s = sol.states.get(self.gcp) if sol else None
                txt = n.rsplit("/", 1)[-1]
                if pr is not None:
                    txt += f"   sigma {pr.sigma_px:.1f} px"
                if c is not None:
                    r = s.residuals_px.get(n) if s else None
                    txt += "   [clicked" + (f", {r:.2f} px]" if r is not None and np.isfinite(r) else "]")
                it = QListWidgetItem(txt)
                it.setData(ROLE, n)
                self.photo_list.addItem(it)
                if n == self.photo:
                    self.photo_list.setCurrentItem(it)
        self.photo_list.blockSignals(False)

    def _markers(self, sol):
        if self.photo is None:
            return
        keep = set()
        pr = sol.at(self.gcp, self.photo) if (sol and self.gcp) else None
        if pr is not None:
            self.view.set_marker("prediction", pr.x, pr.y, "suggestion", f"{self.gcp}?", movable=False)
            keep.add("prediction")
        if self.snap is not None and self.store.click(self.gcp, self.photo) is None:
            self.view.set_marker("snap", *self.snap, "suggestion_current", "A", movable=False)
            keep.add("snap")
        for g, cl in self.store.clicks.items():
            if self.photo in cl:
                x, y = cl[self.photo]
                self.view.set_marker(f"click:{g}", x, y, "active" if g == self.gcp else "normal", g, movable=False)
                keep.add(f"click:{g}")
        for k in [k for k in self.view.markers if k not in keep]:
            self.view.remove_marker(k)

    def _detail(self, sol):
        s = sol.states.get(self.gcp) if (sol and self.gcp) else None
        if s is None:
            self.detail.setText("")
            return
        kind = "check point (never in the fit)" if s.check else ("GCP, in the fit" if s.in_fit else "GCP")
        t = f"<b>{s.name}</b> ({kind}): clicked in {s.n_clicks} photos"
        if s.residual_px is not None:
            t += f", {s.clicks_used} used; image residual {s.residual_px:.2f} px RMS"
        g = ((self.georegistration() or {}).get("gcp_residuals") or {}).get(s.name)
        if g is not None and g.get("status") == "ok":
            t += (f"<br>error X {g['dx_m']:+.3f} Y {g['dy_m']:+.3f} Z {g['dz_m']:+.3f} m ({g['err_m']:.3f} m)"
                  + (", an outlier of the fit" if g.get("outlier") else "") + ", as gtkit sfm records it")
        elif s.error_m is not None:
            e = s.error_m
            t += f"<br>error X {e[0]:+.3f} Y {e[1]:+.3f} Z {e[2]:+.3f} m ({s.error_3d_m:.3f} m)"
        elif s.reason:
            t += f"<br>{s.reason}"
        self.detail.setText(t)

    # --- session ----------------------------------------------------------------------------------
    def session_state(self) -> dict:
        if self.gcp is None:
            return dict(self._restore_state)
        return {"gcp": self.gcp, "photo": self.photo, "view": self.view.view_state(),
                "per_gcp": self.per_gcp.value()}

    def restore(self, st: dict | None):
        self._restore_state = dict(st or {})
        if self._restore_state.get("per_gcp"):
            self.per_gcp.setValue(int(self._restore_state["per_gcp"]))
