"""Undoable target edits (QUndoCommand) over :class:`gui.target_store.TargetStore`: each redo
and undo writes the detections file, so the file follows the undo stack at every step."""
from __future__ import annotations

import copy

from PySide6.QtGui import QUndoCommand


class AddTarget(QUndoCommand):
    def __init__(self, store, target):
        super().__init__(f"add {target.kind} {target.label} in {target.image}")
        self.store, self.target = store, copy.deepcopy(target)

    def redo(self):
        self.store.insert(self.target)

    def undo(self):
        self.store.remove(self.target.id)


class DeleteTarget(QUndoCommand):
    def __init__(self, store, tid: str):
        super().__init__(f"delete {tid}")
        self.store, self.tid, self.saved = store, tid, None

    def redo(self):
        self.saved = self.store.remove(self.tid)

    def undo(self):
        t, i = self.saved
        self.store.insert(t, i)


class ChangeTarget(QUndoCommand):
    """Move or relabel: the target before and after."""

    def __init__(self, store, old, new, what: str = "move"):
        super().__init__(f"{what} {new.id}")
        self.store, self.old, self.new = store, copy.deepcopy(old), copy.deepcopy(new)

    def redo(self):
        self.store.update(self.new)

    def undo(self):
        self.store.update(self.old)
