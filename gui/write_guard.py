"""The annotator beside a run: it saves only while no other gtkit process writes the project.

No Qt here. Every save of the annotator (tie points, GCP clicks, targets, review verdicts) holds
the project's lock (:mod:`gtkit.project_lock`) while it writes, so a ``gtkit run`` or a stage
command started meanwhile is refused in one line; while another process holds it the pages
refuse edits (:meth:`WriteGuard.blocked` says why, the main window shows it as a banner) and
write nothing, so the run never reads a file the annotator is changing under it.
"""
from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path

from gtkit.project_lock import Holder, ProjectLocked, holder, project_lock

log = logging.getLogger(__name__)


class WriteGuard:
    def __init__(self, root: str | Path, ttl_s: float = 0.5):
        self.root = Path(root)
        self.ttl_s = ttl_s            # a page asks on every click: look at the lock at most this often
        self._checked = -1e9
        self._holder: Holder | None = None
        self.refused: str | None = None   # why the last save was not written (save_under_lock)

    def holder(self) -> Holder | None:
        """The other process writing the project now (None: the annotator may save)."""
        now = time.monotonic()
        if now - self._checked > self.ttl_s:
            self._holder, self._checked = holder(self.root), now
        return self._holder

    def blocked(self) -> str | None:
        """Why an edit must not happen now, in one line (None: it may)."""
        h = self.holder()
        if h is None:
            return None
        return (f"read-only while {h.describe()} writes this project: edits are not saved; "
                "they are possible again when it ends")

    @contextlib.contextmanager
    def saving(self):
        """Hold the project's lock for one save (ProjectLocked where another process took it)."""
        self._checked = -1e9
        with project_lock(self.root, f"gtkit annotate {self.root}"):
            yield


def saving(guard: WriteGuard | None):
    """``guard.saving()``, or nothing to hold for a store used without a project (tests, tools)."""
    return guard.saving() if guard is not None else contextlib.nullcontext()


def save_under_lock(guard: WriteGuard | None, write) -> bool:
    """``write()`` holding the project's lock. False, with nothing written, where another process
    took the lock in the instant since the page looked: the edit stays in memory (the stores write
    their whole file at each save, so the next save after the writer ends writes it too) and
    ``guard.refused`` says why, for the status bar; never an exception into a Qt slot."""
    try:
        with saving(guard):
            write()
    except ProjectLocked as e:
        log.warning("not saved: %s", e)
        guard.refused = str(e)
        return False
    if guard is not None:
        guard.refused = None
    return True
