"""The annotator's main window: the tie-point workspace, the alignment review, the target
clicks (for ``gtkit track``), the 3D scene and the GCP clicks (``gcp_list.txt``) as tabs,
the shortcuts for every frequent action, and the session file that makes reopening resume."""
from __future__ import annotations

import logging

from PySide6.QtCore import QTimer
from PySide6.QtGui import QAction, QKeySequence, QUndoStack
from PySide6.QtWidgets import QLabel, QMainWindow, QTabWidget

from gtkit.io.poses import read_poses
from gtkit.project import Project, resolve_path
from gtkit.render.overlay import default_pose_file

from .gcp_page import GcpPage
from .images import ImageCache
from .ranking import OverlapRanker
from .review_page import ReviewPage
from .scene_page import ScenePage
from .session import load_session, save_session
from .store import TiePointStore
from .target_page import TargetPage
from .tiepoint_page import TiePointPage
from .write_guard import WriteGuard

log = logging.getLogger(__name__)

SHORTCUTS = [  # (menu, label, keys, method)
    ("Edit", "Undo", "Ctrl+Z", "undo_"), ("Edit", "Redo", "Ctrl+Shift+Z", "redo_"), ("Edit", "Redo", "Ctrl+Y", "redo_"),
    ("Edit", "Delete active tie point", "Delete", "delete_"), ("Edit", "Deselect", "Esc", "deselect_"),
    ("Pair", "Next query", "N", "next_query"), ("Pair", "Previous query", "P", "prev_query"),
    ("Pair", "Next reference", "PgDown", "next_ref"), ("Pair", "Previous reference", "PgUp", "prev_ref"),
    ("Pair", "Fit both photos", "F", "fit"), ("Pair", "Toggle loupe", "L", "toggle_loupe"),
    ("Pair", "Zoom in", "+", "zoom_in"), ("Pair", "Zoom out", "-", "zoom_out"),
    ("Suggest", "Suggest matches", "S", "suggest_"), ("Suggest", "Accept suggestion", "A", "accept_"),
    ("Suggest", "Reject suggestion", "R", "reject_"), ("Suggest", "Next suggestion", "Tab", "skip_"),
    ("Review", "Blend", "1", "mode_blend"), ("Review", "Swipe", "2", "mode_swipe"), ("Review", "Edges", "3", "mode_edges"),
    ("Review", "Checkerboard", "4", "mode_checker"), ("Review", "Accept image", "Y", "verdict_accept"),
    ("Review", "Reject image", "X", "verdict_reject"), ("Review", "Needs work", "W", "verdict_needs"),
    ("Review", "Next image", "K", "next_image"), ("Review", "Previous image", "J", "prev_image"),
    ("View", "Tie points tab", "Ctrl+1", "tab_tiepoints"), ("View", "Review tab", "Ctrl+2", "tab_review"),
    ("View", "Targets tab", "Ctrl+3", "tab_targets"), ("View", "3D scene tab", "Ctrl+4", "tab_scene"),
    ("View", "GCPs tab", "Ctrl+5", "tab_gcps"), ("GCP", "Next GCP", "G", "next_gcp"),
]
TABS = ("tiepoints", "review", "targets", "scene", "gcps")
GCP_TAB = 4


class MainWindow(QMainWindow):
    def __init__(self, project_dir, poses=None, query=None, on_saved=None):
        super().__init__()
        self.project = Project.load(project_dir)
        P = self.paths = self.project.paths
        self.session = load_session(P)
        self.guard = WriteGuard(P.root)   # no saves while a gtkit run or stage writes the project
        self.store = TiePointStore(P.tiepoints, on_saved=on_saved, guard=self.guard)
        self.undo_stack = QUndoStack(self)
        self.cache = ImageCache()
        stored = self.session.get("review", {}).get("pose_file")  # relative to the project (older: absolute)
        pose_file = poses or (resolve_path(stored, P.root) if stored else None) or default_pose_file(P)
        rank_poses = {}  # registered poses where they exist (reference block, pseudo-GT), else priors
        for f in (P.stage("sfm_reference") / "poses.txt", default_pose_file(P)):
            if f is not None and f.is_file():
                rank_poses.update(read_poses(f))
        self.ranker = OverlapRanker(P, self.project.frame, rank_poses,
                                    cache_file=P.stage("annotate") / "prior_ground_points.json")
        self.tiepoints = TiePointPage(P, self.store, self.cache, self.ranker, self.undo_stack)
        self.review = ReviewPage(self.project, pose_file, guard=self.guard)
        self.target_undo = QUndoStack(self)  # the Targets page's own undo history
        self.targets = TargetPage(self.project, self.cache, self.target_undo, guard=self.guard)
        self.tabs = QTabWidget()
        self.tabs.addTab(self.tiepoints, "Tie points")
        self.tabs.addTab(self.review, "Alignment review")
        self.tabs.addTab(self.targets, "Targets")
        self.scene3d = ScenePage(self.project)  # built when first shown (gtkit.view.scene, VTK offscreen)
        self.tabs.addTab(self.scene3d, "3D scene")
        self.gcp_undo = QUndoStack(self)  # the GCP page's own undo history
        self.gcps = GcpPage(self.project, self.cache, self.gcp_undo, guard=self.guard)
        self.tabs.addTab(self.gcps, "GCPs")
        self._prev_tab = 0
        self.setCentralWidget(self.tabs)
        self.setWindowTitle(f"gtkit annotate: {self.project.name} ({P.root})")
        self.resize(1500, 900)
        for page in (self.tiepoints, self.review, self.targets, self.scene3d, self.gcps):
            page.status.connect(lambda m: self.statusBar().showMessage(m, 8000))
            page.session_changed.connect(self.schedule_session_save)
        self.tabs.currentChanged.connect(self._tab_changed)
        self._save_timer = QTimer(self)
        self._save_timer.setSingleShot(True)
        self._save_timer.setInterval(400)
        self._save_timer.timeout.connect(self.save_session)
        self._restoring = True
        self._build_menus()
        tp = dict(self.session.get("tiepoints", {}))
        if query:
            tp = {"query": query}
        self.tiepoints.restore(tp)
        self.review.restore(self.session.get("review", {}))
        self.targets.restore(self.session.get("targets", {}))
        self.gcps.restore(self.session.get("gcps", {}))
        if self.session.get("tab") in TABS[1:]:
            self.tabs.setCurrentIndex(TABS.index(self.session["tab"]))
        self._restoring = False
        self.statusBar().showMessage(f"{len(self.store)} tie points in {P.tiepoints.name}; every edit is saved at once")
        self.banner = QLabel()          # says so while another gtkit process writes the project
        self.banner.setStyleSheet("QLabel { background: #ffd54f; color: black; padding: 2px 6px; }")
        self.banner.setWordWrap(True)
        self.statusBar().addPermanentWidget(self.banner, 1)
        self._writer_timer = QTimer(self)
        self._writer_timer.setInterval(1000)
        self._writer_timer.timeout.connect(self.check_writer)
        self._writer_timer.start()
        self.check_writer()

    def check_writer(self) -> str | None:
        """Show (or clear) the read-only banner: another gtkit process writing the project."""
        why = self.guard.blocked()
        self.banner.setText(why or "")
        self.banner.setVisible(why is not None)
        title = f"gtkit annotate: {self.project.name} ({self.paths.root})"
        self.setWindowTitle(title + (" [read-only: another gtkit process writes it]" if why else ""))
        return why

    def restore_views(self):
        """Re-apply the saved zoom/centre once the window has its real size."""
        views = self.session.get("tiepoints", {}).get("views")
        if views and self.tiepoints.query == self.session.get("tiepoints", {}).get("query"):
            self.tiepoints.qview.set_view_state(views.get("query"))
            self.tiepoints.rview.set_view_state(views.get("reference"))

    # --- menus and shortcuts -------------------------------------------------------------------
    def _build_menus(self):
        menus = {}
        for menu, label, keys, method in SHORTCUTS:
            m = menus.get(menu) or self.menuBar().addMenu(menu)
            menus[menu] = m
            a = QAction(f"{label}", self)
            a.setShortcut(QKeySequence(keys))
            a.triggered.connect(getattr(self, method))
            m.addAction(a)
            self.addAction(a)

    def _on_tp(self):
        return self.tabs.currentIndex() == 0

    def _on_targets(self):
        return self.tabs.currentIndex() == 2

    def _on_gcps(self):
        return self.tabs.currentIndex() == GCP_TAB

    def _views(self):
        if self._on_gcps():
            return (self.gcps.view,)
        if self._on_tp():
            return (self.tiepoints.qview, self.tiepoints.rview)
        return (self.targets.view,) if self._on_targets() else (self.review.view,)

    def undo_(self):
        if self._on_gcps():
            self.gcps.undo_()
        elif self._on_targets():
            self.targets.undo_()
        elif not self.tiepoints.refuse():
            self.undo_stack.undo()

    def redo_(self):
        if self._on_gcps():
            self.gcps.redo_()
        elif self._on_targets():
            self.targets.redo_()
        elif not self.tiepoints.refuse():
            self.undo_stack.redo()

    def delete_(self):
        if self._on_gcps():
            self.gcps.delete_click()
        elif self._on_tp():
            self.tiepoints.delete_active()
        elif self._on_targets():
            self.targets.delete_active()

    def deselect_(self):
        if self._on_targets():
            self.targets.deselect()
            return
        self.tiepoints.active = None
        self.tiepoints.refresh()

    def next_query(self):
        if self._on_gcps():
            self.gcps.step(1)
        elif self._on_targets():
            self.targets.step(1)
        else:
            self.tiepoints.step_query(1)

    def prev_query(self):
        if self._on_gcps():
            self.gcps.step(-1)
        elif self._on_targets():
            self.targets.step(-1)
        else:
            self.tiepoints.step_query(-1)

    def next_ref(self):
        self.tiepoints.step_reference(1)

    def prev_ref(self):
        self.tiepoints.step_reference(-1)

    def fit(self):
        for v in self._views():
            v.fit()

    def toggle_loupe(self):
        for v in (self.tiepoints.qview, self.tiepoints.rview, self.targets.view, self.gcps.view):
            v.loupe_enabled = not v.loupe_enabled
            v.loupe.hide()

    def zoom_in(self):
        for v in self._views():
            v.zoom_by(1.25)

    def zoom_out(self):
        for v in self._views():
            v.zoom_by(0.8)

    def suggest_(self):
        self.tiepoints.compute_suggestions()

    def accept_(self):
        if self._on_gcps():
            self.gcps.accept_snap()
        else:
            self.tiepoints.accept_suggestion()

    def reject_(self):
        self.tiepoints.reject_suggestion()

    def skip_(self):
        self.tiepoints.skip_suggestion()

    def mode_blend(self):
        self.review.set_mode("blend")

    def mode_swipe(self):
        self.review.set_mode("swipe")

    def mode_edges(self):
        self.review.set_mode("edges")

    def mode_checker(self):
        self.review.set_mode("checker")

    def verdict_accept(self):
        if self.tabs.currentIndex() == 1:
            self.review.set_verdict("accept")

    def verdict_reject(self):
        if self.tabs.currentIndex() == 1:
            self.review.set_verdict("reject")

    def verdict_needs(self):
        if self.tabs.currentIndex() == 1:
            self.review.set_verdict("needs-work")

    def next_image(self):
        self.review.step(1)

    def prev_image(self):
        self.review.step(-1)

    def tab_tiepoints(self):
        self.tabs.setCurrentIndex(0)

    def tab_review(self):
        self.tabs.setCurrentIndex(1)

    def tab_targets(self):
        self.tabs.setCurrentIndex(2)

    def tab_scene(self):
        self.tabs.setCurrentIndex(3)

    def tab_gcps(self):
        self.tabs.setCurrentIndex(GCP_TAB)

    def next_gcp(self):
        if self._on_gcps():
            self.gcps.next_gcp()

    def selected_photo(self, tab: int) -> str | None:
        """The photo the user has open in a tab (tie points: the query; review and targets: the image)."""
        return {0: self.tiepoints.query, 1: self.review.image, 2: getattr(self.targets, "image", None),
                GCP_TAB: self.gcps.photo}.get(tab)

    def _tab_changed(self, i):
        if i == 1 and self.review.image is None:
            self.review.open_image(getattr(self.review, "_restore_image", None))
        if i == 2:
            self.targets.ensure_shown()
        if i == GCP_TAB:
            self.gcps.ensure_shown()
        if i == 3:  # the 3D view jumps to the photo selected in the tab the user came from
            photo = self.selected_photo(self._prev_tab)
            self.scene3d.set_photo(photo)
            self.scene3d.ensure_scene()
            if photo:
                self.scene3d.look_through(photo)
        self._prev_tab = i
        self.schedule_session_save()

    # --- session -------------------------------------------------------------------------------
    def session_state(self) -> dict:
        return {"format": "gtkit-annotate-session", "tab": TABS[self.tabs.currentIndex()],
                "tiepoints": self.tiepoints.session_state(), "review": self.review.session_state(),
                "targets": self.targets.session_state(), "gcps": self.gcps.session_state()}

    def schedule_session_save(self):
        if not self._restoring and not self._save_timer.isActive():
            self._save_timer.start()  # at most one write per interval, also during a burst of edits

    def save_session(self):
        save_session(self.paths, self.session_state())

    def closeEvent(self, e):
        self.save_session()
        self.cache.shutdown()
        self.tiepoints._pool.clear()
        self.tiepoints._pool.waitForDone(30000)
        self.scene3d.release()
        super().closeEvent(e)
