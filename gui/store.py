"""Tie points being edited: the in-memory list and the file, kept identical after every edit.

No Qt here. Every mutating method writes ``tiepoints.json`` atomically before it returns (the
foundation's :func:`gtkit.io.atomic.write_text`, the format of :mod:`gtkit.io.tiepoints`), so a crash or kill loses nothing
that a method has returned from. Undo/redo (``gui.undo``) is built from these methods.
"""
from __future__ import annotations

import copy
import json
import re
from pathlib import Path

from gtkit.io.atomic import write_text
from gtkit.io.tiepoints import FORMAT, VERSION, Observation, TiePoint, read_tiepoints

from .write_guard import save_under_lock


def tiepoints_json(tiepoints: list[TiePoint]) -> str:
    """The tie-point file's text (the format of :mod:`gtkit.io.tiepoints`), one tie point a line.

    Same content as ``write_tiepoints`` writes, serialised with the C JSON encoder: with
    thousands of tie points every click stays a few milliseconds (indented output goes through
    Python's slow pure-Python encoder)."""
    head = json.dumps({"format": FORMAT, "version": VERSION,
                       "pixel_convention": "COLMAP: the top-left pixel's centre is (0.5, 0.5)"})
    rows = ",\n  ".join(json.dumps({"id": t.id, "observations": [{"image": o.image, "x": o.x, "y": o.y}
                                                                  for o in t.observations],
                                     "source": t.source, "note": t.note}) for t in tiepoints)
    return head[:-1] + ',\n "tiepoints": [\n  ' + rows + ("\n ]}\n" if rows else "]}\n")


class TiePointStore:
    def __init__(self, path: str | Path, on_saved=None, guard=None):
        self.path = Path(path)
        self.guard = guard  # gui.write_guard.WriteGuard: each save holds the project's lock (None: no project)
        self.tiepoints: list[TiePoint] = read_tiepoints(self.path) if self.path.is_file() else []
        self._index = {t.id: t for t in self.tiepoints}
        self.on_saved = on_saved  # callback(store) after every write
        self.n_writes = 0

    # --- queries -------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.tiepoints)

    def get(self, tp_id: str) -> TiePoint | None:
        return self._index.get(tp_id)

    def observation(self, tp_id: str, image: str) -> Observation | None:
        tp = self.get(tp_id)
        return next((o for o in tp.observations if o.image == image), None) if tp else None

    def in_image(self, image: str) -> list[tuple[TiePoint, Observation]]:
        return [(t, o) for t in self.tiepoints for o in t.observations if o.image == image]

    def pair_counts(self, query: str) -> dict[str, int]:
        """reference image -> number of tie points shared with ``query``."""
        out: dict[str, int] = {}
        for t in self.tiepoints:
            imgs = t.images()
            if query in imgs:
                for i in imgs:
                    if i != query:
                        out[i] = out.get(i, 0) + 1
        return out

    def new_id(self) -> str:
        n = 0
        for t in self.tiepoints:
            m = re.fullmatch(r"tp(\d+)", t.id)
            if m:
                n = max(n, int(m.group(1)))
        return f"tp{n + 1:05d}"

    # --- edits (each one saved before returning) ------------------------------------------
    def save(self) -> None:
        if not save_under_lock(self.guard, lambda: write_text(self.path, tiepoints_json(self.tiepoints))):
            return   # another writer took the project meanwhile: kept in memory, written at the next save
        self.n_writes += 1
        if self.on_saved:
            self.on_saved(self)

    def insert(self, tp: TiePoint, index: int | None = None) -> None:
        tp = copy.deepcopy(tp)
        if tp.id in self._index:
            raise ValueError(f"tie point {tp.id} exists")
        self.tiepoints.insert(len(self.tiepoints) if index is None else index, tp)
        self._index[tp.id] = tp
        self.save()

    def remove(self, tp_id: str) -> tuple[TiePoint, int]:
        tp = self._index.pop(tp_id)
        i = self.tiepoints.index(tp)
        del self.tiepoints[i]
        self.save()
        return copy.deepcopy(tp), i

    def set_observation(self, tp_id: str, image: str, x: float, y: float) -> Observation | None:
        """Add or move ``tp_id``'s observation in ``image``; returns the previous one (or None)."""
        tp = self._index[tp_id]
        old = self.observation(tp_id, image)
        prev = copy.copy(old) if old else None
        if old:
            old.x, old.y = float(x), float(y)
        else:
            tp.observations.append(Observation(image, float(x), float(y)))
        self.save()
        return prev

    def remove_observation(self, tp_id: str, image: str) -> None:
        tp = self._index[tp_id]
        tp.observations = [o for o in tp.observations if o.image != image]
        self.save()
