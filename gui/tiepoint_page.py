"""The tie-point workspace: a query photo and a reference photo side by side.

Left click places the active tie point's observation in that photo (a new tie point when the
active one already has one there); drag a marker to move it; Delete removes the active tie
point; Ctrl+Z / Ctrl+Shift+Z undo / redo. References are ranked by likely overlap. Suggested
correspondences (S) are accepted with A and rejected with R. Every edit is in the file at once.

After a registration the page also shows the next *guided click* (``work/register/guided_clicks.json``,
written by ``gtkit register``, :mod:`gtkit.sfm.guided_clicks`): the query photo and the area in it
(a box) whose tie point would cut its sequence's position sigma most, and where to click the same
point in a reference photo. "Next guided click" opens that pair; a suggestion counts as done once a
tie point has been added inside its box.
"""
from __future__ import annotations

import json
import logging

from PySide6.QtCore import QObject, QRectF, QRunnable, QThreadPool, Qt, Signal
from PySide6.QtGui import QColor, QPen, QUndoStack
from PySide6.QtWidgets import (QGraphicsRectItem, QHBoxLayout, QLabel, QListWidget, QListWidgetItem, QPushButton,
                               QSplitter, QTreeWidget, QTreeWidgetItem, QVBoxLayout, QWidget)

from gtkit.sfm.guided_clicks import GUIDANCE_FILE

from gtkit.io.tiepoints import Observation, TiePoint

from .image_view import ImageView
from .residuals import PosedResiduals, read_residuals, residual_file
from .suggest import suggest
from .undo import AddTiePoint, DeleteTiePoint, MoveObservation, PlaceObservation
from .write_guard import WriteGuard

log = logging.getLogger(__name__)

ROLE = Qt.ItemDataRole.UserRole


class _SuggestSignals(QObject):
    done = Signal(str, str, object)


class _SuggestJob(QRunnable):
    def __init__(self, q, r, qp, rp, signals, predict=None):
        super().__init__()
        self.q, self.r, self.qp, self.rp, self.signals, self.predict = q, r, qp, rp, signals, predict

    def run(self):
        try:
            out = suggest(self.qp, self.rp, predict=self.predict)
        except Exception as e:  # noqa: BLE001 - shown to the user, never crashes the GUI
            out = e
        self.signals.done.emit(self.q, self.r, out)


class TiePointPage(QWidget):
    status = Signal(str)
    session_changed = Signal()

    def __init__(self, paths, store, cache, ranker, undo_stack: QUndoStack, parent=None):
        super().__init__(parent)
        self.paths, self.store, self.cache, self.ranker = paths, store, cache, ranker
        self.guard = getattr(store, "guard", None) or WriteGuard(paths.root)
        self.undo = undo_stack
        self.query: str | None = None
        self.reference: str | None = None
        self.active: str | None = None
        self.suggestions: list = []
        self.suggestion_index = 0
        # residuals after registration; recomputed for edited tie points when they come from poses
        self.posed = None if residual_file(paths) else PosedResiduals(paths)
        self.residuals = read_residuals(paths, store.tiepoints, self.posed)
        self.queries = self._list_images(paths.query_images, "queries")
        self.references = self._list_images(paths.reference_images, "reference")

        self.qview = ImageView(cache, title="query")
        self.rview = ImageView(cache, title="reference")
        self.qlabel, self.rlabel = QLabel("query"), QLabel("reference")
        self.query_list = QListWidget()
        self.ref_list = QListWidget()
        self.tp_tree = QTreeWidget()
        self.tp_tree.setHeaderLabels(["tie point", "residual px", "images"])
        self.tp_tree.setRootIsDecorated(False)
        self.tp_tree.setColumnWidth(0, 90)
        self.suggest_button = QPushButton("Suggest matches (S)")
        self.suggest_label = QLabel("")
        self._pool = QThreadPool()
        self._pool.setMaxThreadCount(1)
        self._sig = _SuggestSignals()
        self._sig.done.connect(self._on_suggestions)
        self.guide = read_guidance(paths)
        self.guide_base = {i: self._in_box(g) for i, g in enumerate(self.guide)}   # tie points in each box at start
        self.guide_current: int | None = None
        self.guide_label = QLabel("")
        self.guide_label.setWordWrap(True)
        self.guide_button = QPushButton("Next guided click (G)")
        self.guide_button.setEnabled(bool(self.guide))
        self.guide_box: QGraphicsRectItem | None = None

        side = QVBoxLayout()
        side.addWidget(QLabel("Query photos (N / P)"))
        side.addWidget(self.query_list, 2)
        side.addWidget(QLabel("References by likely overlap (PgDn / PgUp)"))
        side.addWidget(self.ref_list, 2)
        side.addWidget(QLabel("Tie points of this query, worst residual first"))
        side.addWidget(self.tp_tree, 3)
        side.addWidget(self.suggest_button)
        side.addWidget(self.suggest_label)
        side.addWidget(self.guide_button)
        side.addWidget(self.guide_label)
        left = QWidget()
        left.setLayout(side)
        left.setMaximumWidth(330)
        views = QSplitter()
        for lab, v in ((self.qlabel, self.qview), (self.rlabel, self.rview)):
            w = QWidget()
            lay = QVBoxLayout(w)
            lay.setContentsMargins(0, 0, 0, 0)
            lay.addWidget(lab)
            lay.addWidget(v, 1)
            views.addWidget(w)
        lay = QHBoxLayout(self)
        lay.addWidget(left)
        lay.addWidget(views, 1)

        for q in self.queries:
            self.query_list.addItem(q)
        self.query_list.currentTextChanged.connect(lambda t: t and t != self.query and self.set_pair(t, None))
        self.ref_list.currentItemChanged.connect(self._ref_item_changed)
        self.tp_tree.itemClicked.connect(lambda it, _c: self.jump_to(it.data(0, ROLE)))
        self.suggest_button.clicked.connect(lambda: self.compute_suggestions())
        self.guide_button.clicked.connect(lambda: self.next_guided())
        self._update_guide_label()
        self.qview.clicked.connect(lambda x, y: self.place(self.query, x, y))
        self.rview.clicked.connect(lambda x, y: self.place(self.reference, x, y))
        for v in (self.qview, self.rview):
            v.marker_pressed.connect(self._marker_pressed)
            v.view_changed.connect(self.session_changed)
        self.qview.marker_moved.connect(lambda k, *a: self._marker_moved(self.query, k, *a))
        self.rview.marker_moved.connect(lambda k, *a: self._marker_moved(self.reference, k, *a))
        self.undo.indexChanged.connect(lambda _i: self._after_edit())

    @staticmethod
    def _list_images(folder, prefix) -> list[str]:
        if not folder.is_dir():
            return []
        exts = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
        return sorted(f"{prefix}/{p.relative_to(folder).as_posix()}" for p in folder.rglob("*")
                      if p.suffix.lower() in exts)

    # --- pair --------------------------------------------------------------------------
    def set_pair(self, query: str | None, reference: str | None = None, views: dict | None = None):
        if query is None and self.queries:
            query = self.queries[0]
        if query is None:
            return
        changed_q = query != self.query
        self.query = query
        if changed_q:
            self.suggestions, self.suggestion_index = [], 0
            ranked = self.ranker.rank(query, self.references)
            counts = self.store.pair_counts(query)
            self.ref_list.blockSignals(True)
            self.ref_list.clear()
            for name, d, ov in ranked:
                txt = f"{name}   {d:.0f} m" if d != float("inf") else f"{name}   (no pose)"
                if ov is not None:
                    txt = f"{name}   {100 * ov:.0f}% · {d:.0f} m"
                if counts.get(name):
                    txt += f"   [{counts[name]} tp]"
                it = QListWidgetItem(txt)
                it.setData(ROLE, name)
                self.ref_list.addItem(it)
            self.ref_list.blockSignals(False)
            self.qview.show_image(self.paths.images / query)
            self.qlabel.setText(f"query: {query}")
            items = self.query_list.findItems(query, Qt.MatchFlag.MatchExactly)
            if items:
                self.query_list.blockSignals(True)
                self.query_list.setCurrentItem(items[0])
                self.query_list.blockSignals(False)
        names = [self.ref_list.item(i).data(ROLE) for i in range(self.ref_list.count())]
        if reference not in names:
            reference = self.reference if (not changed_q and self.reference in names) else (names[0] if names else None)
        if reference != self.reference or changed_q:
            self.reference = reference
            self.suggestions, self.suggestion_index = [], 0
            if reference:
                self.rview.show_image(self.paths.images / reference)
            self.rlabel.setText(f"reference: {reference}")
            self.ref_list.blockSignals(True)
            self.ref_list.setCurrentRow(names.index(reference) if reference in names else -1)
            self.ref_list.blockSignals(False)
        if views:
            self.qview.set_view_state(views.get("query"))
            self.rview.set_view_state(views.get("reference"))
        self.refresh()
        self._prefetch(names)
        self.session_changed.emit()

    def _prefetch(self, ranked_refs: list[str]):
        """Previews of the photos N / P / PgDn / PgUp would open, decoded in the background."""
        want = []
        if self.query in self.queries:
            i = self.queries.index(self.query)
            for q in (self.queries[(i + 1) % len(self.queries)], self.queries[(i - 1) % len(self.queries)]):
                ranked = self.ranker.rank(q, self.references)
                want += [q] + ([ranked[0][0]] if ranked else [])
        if self.reference in ranked_refs:
            i = ranked_refs.index(self.reference)
            want += [ranked_refs[(i + d) % len(ranked_refs)] for d in (1, 2, -1)]
        self.cache.prefetch(self.paths.images / n for n in dict.fromkeys(want) if n not in (self.query, self.reference))

    def _ref_item_changed(self, cur, _prev):
        if cur is not None and cur.data(ROLE) != self.reference:
            self.set_pair(self.query, cur.data(ROLE))

    def step_query(self, d: int):
        if self.queries and self.query in self.queries:
            self.set_pair(self.queries[(self.queries.index(self.query) + d) % len(self.queries)])

    def step_reference(self, d: int):
        n = self.ref_list.count()
        if n:
            self.ref_list.setCurrentRow((self.ref_list.currentRow() + d) % n)

    # --- edits -------------------------------------------------------------------------------
    def refuse(self) -> bool:
        """Whether an edit must not happen now (said in the status bar): another gtkit process
        writes the project (tiepoints.json is the registration's input)."""
        why = self.guard.blocked()
        if why:
            self.status.emit(why)
        return why is not None

    def place(self, image: str | None, x: float, y: float) -> str | None:
        """A click: the active tie point's observation in ``image``, or a new tie point."""
        if image is None or self.refuse():
            return None
        tp = self.store.get(self.active) if self.active else None
        if tp is None or any(o.image == image for o in tp.observations):
            tp_id = self.store.new_id()
        else:
            tp_id = tp.id
        self.active = tp_id
        self.undo.push(PlaceObservation(self.store, tp_id, image, x, y))
        self.status.emit(f"{tp_id}: placed in {image} at ({x:.1f}, {y:.1f}); saved")
        self.session_changed.emit()
        return tp_id

    def delete_active(self):
        if self.active and self.store.get(self.active) and not self.refuse():
            self.undo.push(DeleteTiePoint(self.store, self.active))
            self.status.emit(f"{self.active} deleted; saved")
            self.active = None
            self.refresh()

    def _marker_pressed(self, key: str):
        if key.startswith("g:"):   # the guided click's marker only shows where: click the feature itself
            return
        if key.startswith("s:"):
            self.suggestion_index = int(key[2:])
            self.refresh()
            return
        self.active = key
        self.refresh()
        self.session_changed.emit()

    def _marker_moved(self, image, key, ox, oy, nx, ny):
        if key.startswith("s:"):
            i = int(key[2:])
            s = self.suggestions[i]
            if image == self.query:
                s.xq, s.yq = nx, ny
            else:
                s.xr, s.yr = nx, ny
            return
        if self.refuse():
            self.refresh()          # the marker back where the file has it
            return
        self.undo.push(MoveObservation(self.store, key, image, (ox, oy), (nx, ny)))
        self.status.emit(f"{key}: moved in {image}; saved")

    # --- suggestions --------------------------------------------------------------------------
    def compute_suggestions(self, sync: bool = False):
        if not (self.query and self.reference):
            return
        qp, rp = str(self.paths.images / self.query), str(self.paths.images / self.reference)
        predict = self.ranker.predictor(self.query, self.reference)  # poses gate the matches
        self.suggest_label.setText("matching ...")
        if sync:
            self._on_suggestions(self.query, self.reference, suggest(qp, rp, predict=predict))
        else:
            self._pool.start(_SuggestJob(self.query, self.reference, qp, rp, self._sig, predict))

    def _on_suggestions(self, q, r, out):
        if (q, r) != (self.query, self.reference):
            return
        if isinstance(out, Exception):
            self.suggest_label.setText(f"matching failed: {out}")
            return
        self.suggestions, self.suggestion_index = list(out), 0
        self.suggest_label.setText(f"{len(out)} suggestions: A accept, R reject, Tab skip" if out else
                                   "no reliable matches for this pair: click by hand or try another reference")
        self.refresh()
        self._focus_suggestion()

    def _focus_suggestion(self):
        if self.suggestions and self.suggestion_index < len(self.suggestions):
            s = self.suggestions[self.suggestion_index]
            self.qview.centerOn(s.xq, s.yq)
            self.rview.centerOn(s.xr, s.yr)

    def accept_suggestion(self) -> str | None:
        if not self.suggestions or self.suggestion_index >= len(self.suggestions) or self.refuse():
            return None
        s = self.suggestions.pop(self.suggestion_index)
        tp = TiePoint(self.store.new_id(), [Observation(self.query, s.xq, s.yq), Observation(self.reference, s.xr, s.yr)],
                      source="suggestion")
        self.undo.push(AddTiePoint(self.store, tp))
        self.active = tp.id
        self._after_suggestion(f"accepted as {tp.id}; saved")
        return tp.id

    def reject_suggestion(self):
        if self.suggestions and self.suggestion_index < len(self.suggestions):
            self.suggestions.pop(self.suggestion_index)
            self._after_suggestion("rejected")

    def skip_suggestion(self):
        if self.suggestions:
            self.suggestion_index = (self.suggestion_index + 1) % len(self.suggestions)
            self._after_suggestion("skipped")

    def _after_suggestion(self, what: str):
        self.suggestion_index = min(self.suggestion_index, max(0, len(self.suggestions) - 1))
        self.suggest_label.setText(f"{what}; {len(self.suggestions)} suggestions left")
        self.refresh()
        self._focus_suggestion()

    def _after_edit(self):
        """After any edit (or undo/redo): fresh residual for the edited tie point, the guided-click
        label (a click inside the box completes it), then redraw."""
        self._update_guide_label()
        if self.posed is not None and self.posed.available:
            cmd = self.undo.command(self.undo.index() - 1) if self.undo.index() > 0 else None
            ids = {getattr(cmd, "tp_id", None) or getattr(getattr(cmd, "tp", None), "id", None)}
            nxt = self.undo.command(self.undo.index()) if self.undo.index() < self.undo.count() else None
            ids.add(getattr(nxt, "tp_id", None) or getattr(getattr(nxt, "tp", None), "id", None))
            for tid in ids - {None}:
                tp = self.store.get(tid)
                r = self.posed.residual(tp) if tp is not None else None
                if r is None:
                    self.residuals.pop(tid, None)
                else:  # edited since registration: its registration verdict no longer applies
                    self.residuals[tid] = r
        self.refresh()

    # --- guided clicks -------------------------------------------------------------------------
    def _in_box(self, g: dict) -> int:
        x0, y0, x1, y1 = g["box"]
        return sum(1 for _tp, o in self.store.in_image(g["photo"]) if x0 <= o.x <= x1 and y0 <= o.y <= y1)

    def guide_pending(self) -> list[int]:
        """Indices of the guided clicks not done yet (no tie point added inside the box since start)."""
        return [i for i, g in enumerate(self.guide) if self._in_box(g) <= self.guide_base[i]]

    def next_guided(self) -> dict | None:
        """Open the next pending guided click: its query photo with the box, the reference photo with
        the point to click there; None when every suggestion is done."""
        pending = self.guide_pending()
        if not pending:
            self.guide_current = None
            self._show_guide_box()
            self._update_guide_label()
            return None
        self.guide_current = pending[0]
        g = self.guide[self.guide_current]
        refs = [r["photo"] for r in g.get("reference", [])]
        self.set_pair(g["photo"], refs[0] if refs else None)
        self.qview.center_on(g["x"], g["y"])
        r = next((r for r in g.get("reference", []) if r["photo"] == self.reference), None)
        if r is not None:
            self.rview.center_on(r["x"], r["y"])
        self._show_guide_box()
        self._update_guide_label()
        return g

    def _show_guide_box(self):
        scene = self.qview.scene()
        if self.guide_box is not None:
            scene.removeItem(self.guide_box)
            self.guide_box = None
        g = self.guide[self.guide_current] if self.guide_current is not None else None
        if g is None or g["photo"] != self.query:
            return
        x0, y0, x1, y1 = g["box"]
        self.guide_box = QGraphicsRectItem(QRectF(x0, y0, x1 - x0, y1 - y0))
        pen = QPen(QColor(80, 255, 120), 2.0, Qt.PenStyle.DashLine)
        pen.setCosmetic(True)
        self.guide_box.setPen(pen)
        self.guide_box.setZValue(4)
        scene.addItem(self.guide_box)

    def _update_guide_label(self):
        if not self.guide:
            self.guide_label.setText("")
            return
        pending = self.guide_pending()
        if not pending:
            self.guide_label.setText("Guided clicks: all done; run `gtkit register` for the next ones")
            return
        i = self.guide_current if self.guide_current in pending else pending[0]
        g = self.guide[i]
        ref = ", ".join(f"{r['photo']} ({r['x']:.0f}, {r['y']:.0f})" for r in g.get("reference", [])[:2])
        self.guide_label.setText(
            f"Next guided click ({len(pending)} left): {g['sequence']}, {g['photo']} around ({g['x']:.0f}, {g['y']:.0f})"
            + (f"; the same point in {ref}" if ref else "")
            + (f". Expected sigma {g['sigma_before_m']:.3f} -> {g['sigma_after_m']:.3f} m" if g.get("sigma_after_m") else ""))

    # --- display -------------------------------------------------------------------------------
    def _label(self, tp_id: str) -> str:
        r = self.residuals.get(tp_id)
        return tp_id if r is None else f"{tp_id} {r.residual_px:.1f}px"

    def refresh(self):
        for view, image in ((self.qview, self.query), (self.rview, self.reference)):
            keep = set()
            if image:
                for tp, o in self.store.in_image(image):
                    r = self.residuals.get(tp.id)
                    kind = "active" if tp.id == self.active else ("bad" if r and (r.inlier is False or r.residual_px > 3) else "normal")
                    view.set_marker(tp.id, o.x, o.y, kind, self._label(tp.id))
                    keep.add(tp.id)
                for i, s in enumerate(self.suggestions):
                    x, y = (s.xq, s.yq) if view is self.qview else (s.xr, s.yr)
                    key = f"s:{i}"
                    view.set_marker(key, x, y, "suggestion_current" if i == self.suggestion_index else "suggestion",
                                    f"s{i}" if i == self.suggestion_index else "")
                    keep.add(key)
                g = self.guide[self.guide_current] if self.guide_current is not None else None
                if g is not None:
                    pts = [(g["photo"], g["x"], g["y"])] + [(r["photo"], r["x"], r["y"]) for r in g.get("reference", [])]
                    for name, x, y in pts:
                        if name == image:
                            view.set_marker("g:next", x, y, "suggestion", "next click", movable=False)
                            keep.add("g:next")
            for k in list(view.markers):
                if k not in keep:
                    view.remove_marker(k)
        self._fill_tree()

    def _fill_tree(self):
        if not self.query:
            self.tp_tree.clear()
            return
        rows = []
        for tp, _o in self.store.in_image(self.query):
            r = self.residuals.get(tp.id)
            rows.append((-(r.residual_px if r else -1.0), tp.id, r, len(tp.observations)))
        rows.sort()
        key = [(r[1], r[3], None if r[2] is None else r[2].residual_px) for r in rows]
        if key == getattr(self, "_tree_key", None):  # same rows: only the selection moves
            for i in range(self.tp_tree.topLevelItemCount()):
                it = self.tp_tree.topLevelItem(i)
                if it.data(0, ROLE) == self.active:
                    self.tp_tree.setCurrentItem(it)
            return
        self._tree_key = key
        self.tp_tree.setCurrentItem(None)  # else clear() re-selects item after item: quadratic
        self.tp_tree.clear()
        items = []
        for _k, tp_id, r, n in rows:
            it = QTreeWidgetItem([tp_id, "" if r is None else f"{r.residual_px:.2f}", str(n)])
            it.setData(0, ROLE, tp_id)
            items.append(it)
        self.tp_tree.addTopLevelItems(items)
        for it in items:
            if it.data(0, ROLE) == self.active:
                self.tp_tree.setCurrentItem(it)

    def jump_to(self, tp_id: str):
        """Make ``tp_id`` active, show it against one of its references, centre both views on it."""
        tp = self.store.get(tp_id)
        if tp is None:
            return
        self.active = tp_id
        others = [o.image for o in tp.observations if o.image != self.query]
        if self.reference not in others and others:
            ref = next((i for i in others if i.startswith("reference/")), others[0])
            if ref in [self.ref_list.item(i).data(ROLE) for i in range(self.ref_list.count())]:
                self.set_pair(self.query, ref)
        for view, image in ((self.qview, self.query), (self.rview, self.reference)):
            o = self.store.observation(tp_id, image)
            if o:
                view.center_on(o.x, o.y, zoom=max(view.zoom(), 2.0))
        self.refresh()
        self.session_changed.emit()

    def session_state(self) -> dict:
        return {"query": self.query, "reference": self.reference, "active": self.active,
                "views": {"query": self.qview.view_state(), "reference": self.rview.view_state()}}

    def restore(self, st: dict):
        q = st.get("query") if st.get("query") in self.queries else None
        self.set_pair(q, st.get("reference"), st.get("views"))
        if st.get("active") and self.store.get(st["active"]):
            self.active = st["active"]
            self.refresh()


def read_guidance(paths) -> list[dict]:
    """The guided clicks of ``work/register/guided_clicks.json`` in the order to click them: the
    sequences farthest above their target first, each sequence's suggestions in its order, each
    with its ``sequence`` and the sigma before it (``sigma_before_m``); sequences whose clicks would
    barely lower their sigma (``clicks_help`` false: held by their automatic ties) are left out.
    Empty without the file."""
    f = paths.stage("register") / GUIDANCE_FILE
    if not f.is_file():
        return []
    try:
        seqs = json.loads(f.read_text())["sequences"]
    except (ValueError, KeyError) as e:
        log.warning("%s unreadable (%s): no guided clicks shown", f, e)
        return []
    out = []
    for q, g in sorted(seqs.items(), key=lambda kv: -(kv[1].get("sigma_m") or 0.0) + (kv[1].get("target_m") or 0.0)):
        if not g.get("clicks_help", True):
            continue
        before = g.get("sigma_m")
        for s in g.get("suggestions", []):
            if "x" not in s:     # an unregistered sequence: photos to start in, no point yet
                continue
            out.append({**s, "sequence": q, "sigma_before_m": before})
            before = s.get("sigma_after_m", before)
    return out
