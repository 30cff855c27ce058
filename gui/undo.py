"""Undoable edits (QUndoCommand): each redo/undo goes through :class:`gui.store.TiePointStore`,
so the file on disk follows the undo stack at every step."""
from __future__ import annotations

import copy

from PySide6.QtGui import QUndoCommand

from gtkit.io.tiepoints import Observation, TiePoint


class PlaceObservation(QUndoCommand):
    """Click: put ``tp_id``'s observation in ``image`` at (x, y), creating the tie point if needed."""

    def __init__(self, store, tp_id: str, image: str, x: float, y: float, source: str = "gui"):
        super().__init__(f"place {tp_id} in {image}")
        self.store, self.tp_id, self.image, self.xy, self.source = store, tp_id, image, (x, y), source
        self.created = False
        self.prev = None

    def redo(self):
        if self.store.get(self.tp_id) is None:
            self.created = True
            self.store.insert(TiePoint(self.tp_id, [Observation(self.image, *self.xy)], source=self.source))
        else:
            self.prev = self.store.set_observation(self.tp_id, self.image, *self.xy)

    def undo(self):
        if self.created:
            self.store.remove(self.tp_id)
        elif self.prev is not None:
            self.store.set_observation(self.tp_id, self.image, self.prev.x, self.prev.y)
        else:
            self.store.remove_observation(self.tp_id, self.image)


class MoveObservation(QUndoCommand):
    def __init__(self, store, tp_id: str, image: str, old: tuple[float, float], new: tuple[float, float]):
        super().__init__(f"move {tp_id} in {image}")
        self.store, self.tp_id, self.image, self.old, self.new = store, tp_id, image, old, new

    def redo(self):
        self.store.set_observation(self.tp_id, self.image, *self.new)

    def undo(self):
        self.store.set_observation(self.tp_id, self.image, *self.old)


class AddTiePoint(QUndoCommand):
    """A whole tie point at once (an accepted suggestion)."""

    def __init__(self, store, tp: TiePoint):
        super().__init__(f"add {tp.id}")
        self.store, self.tp = store, copy.deepcopy(tp)

    def redo(self):
        self.store.insert(self.tp)

    def undo(self):
        self.store.remove(self.tp.id)


class DeleteTiePoint(QUndoCommand):
    def __init__(self, store, tp_id: str):
        super().__init__(f"delete {tp_id}")
        self.store, self.tp_id = store, tp_id
        self.saved = None

    def redo(self):
        self.saved = self.store.remove(self.tp_id)

    def undo(self):
        tp, i = self.saved
        self.store.insert(tp, i)
