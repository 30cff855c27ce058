"""GCP clicks being edited: the in-memory clicks and ``gcp_list.txt``, kept identical after every edit.

No Qt here. The coordinates come from ``gcp/points.txt`` (``gtkit gcp import``) and from an existing
``gcp_list.txt`` (:func:`gtkit.gcp.site.load_marking`); every mutating method writes ``gcp_list.txt``
atomically (:func:`gtkit.gcp.site.save_clicks`) before it returns, so a crash or kill loses nothing a
method has returned from, and ``gtkit sfm`` / ``gtkit run`` read the clicks without options. After
each edit :meth:`GcpStore.solution` re-triangulates the clicked GCPs, refits and re-predicts
(:func:`gtkit.gcp.marking.solve`, milliseconds): the predictions. :meth:`GcpStore.georegistration`
refits the block to ``gcp_list.txt`` as saved with the georegistration step's own function
(:func:`gtkit.gcp.site.georegistration_refit`: ``gtkit sfm`` records the same residuals after the click).
"""
from __future__ import annotations

from pathlib import Path

from gtkit.errors import GtkitError
from gtkit.gcp.marking import Block, Solution, load_block, solve
from gtkit.gcp.site import georegistration_refit, import_points, load_marking, save_clicks, settings_for

from .write_guard import save_under_lock


class GcpStore:
    def __init__(self, project, on_saved=None, guard=None):
        self.project = project
        self.guard = guard  # gui.write_guard.WriteGuard: each save holds the project's lock (None: not held)
        self.path: Path = project.paths.gcp_list
        self.settings = settings_for(project)
        self.on_saved = on_saved
        self.n_writes = 0
        self.block: Block | None = None
        self.block_error: str | None = None
        self._refit = None          # gtkit.sfm.georeg_step.Refit, built at the first georegistration()
        self._geo: dict | None = None
        try:
            self.block = load_block(project.paths)
        except GtkitError as e:
            self.block_error = str(e)
        self.reload()

    def reload(self):
        self.points, self.clicks = load_marking(self.project)
        self._mtime = self._stat()
        self._solution = None
        self._geo = None

    def _stat(self):
        return self.path.stat().st_mtime_ns if self.path.is_file() else None

    def changed_on_disk(self) -> bool:
        return self._stat() != self._mtime

    # --- queries -------------------------------------------------------------------------
    def __len__(self) -> int:
        return sum(len(c) for c in self.clicks.values())

    def point(self, name: str):
        return next((p for p in self.points if p.name == name), None)

    def click(self, gcp: str, photo: str) -> tuple[float, float] | None:
        return self.clicks.get(gcp, {}).get(photo)

    def solution(self) -> Solution | None:
        if self._solution is None and self.block is not None and self.points:
            self._solution = solve(self.block, self.points, self.clicks, self.settings.click_sigma_px,
                                   self.settings.max_px)
        return self._solution

    def georegistration(self) -> dict | None:
        """The georegistration step's record for the clicks as saved in ``gcp_list.txt`` (its
        ``gcp_residuals``, ``fitted_to``, RMSE: what ``gtkit sfm`` records for them); None where the
        project has no mapped reference block yet (:attr:`georegistration_why` says so)."""
        if self._geo is None:
            if self._refit is None:
                self._refit = georegistration_refit(self.project)
            self._geo = self._refit.run() if self._refit.available else None
        return self._geo

    @property
    def georegistration_why(self) -> str:
        return self._refit.why if self._refit is not None else ""

    # --- edits (each one saved before returning) ---------------------------------------------
    def save(self):
        if not save_under_lock(self.guard, lambda: save_clicks(self.project, self.points, self.clicks)):
            return   # another writer took the project meanwhile: kept in memory, written at the next save
        self._mtime = self._stat()
        self._solution = None
        self._geo = None
        self.n_writes += 1
        if self.on_saved:
            self.on_saved(self)

    def set_click(self, gcp: str, photo: str, x: float, y: float) -> tuple[float, float] | None:
        """Place or move ``gcp``'s click in ``photo``; returns the previous one (or None)."""
        prev = self.click(gcp, photo)
        self.clicks.setdefault(gcp, {})[photo] = (float(x), float(y))
        self.save()
        return prev

    def remove_click(self, gcp: str, photo: str) -> tuple[float, float] | None:
        prev = self.clicks.get(gcp, {}).pop(photo, None)
        if gcp in self.clicks and not self.clicks[gcp]:
            del self.clicks[gcp]
        self.save()
        return prev

    def import_file(self, file, crs: str | None = None) -> dict:
        """``gtkit gcp import`` from the page; clicks kept."""
        r = import_points(self.project, file, crs, self.settings)
        self.reload()
        return r
