"""Target annotations in zoom photos: the in-memory list and the tracker's detections file,
kept identical after every edit.

No Qt here. The file is the one ``gtkit track`` reads by default (``detections.csv`` in the
project, :attr:`gtkit.project.Paths.detections`), in the CSV format of
:mod:`gtkit.track.targets`, written atomically by every mutating method before it returns, so
a crash or kill loses nothing a method has returned from. An existing file is read with the
tracker's own reader; a file it cannot read raises :class:`gtkit.errors.GtkitError` (one line
naming the file) and is never overwritten.

A target is a foot-point pixel (a click) or a box (a drag); the tracker reads one kind per
file, so a file holds pixels or boxes, not both (:meth:`TargetStore.kind`).
Pixels are in gtkit's (COLMAP) convention: the photo spans [0, W] x [0, H].

``tracked_results`` reads the tracker's output (``exports/tracks.csv``) back, to show each
target's 3D position next to its click.
"""
from __future__ import annotations

import copy
import csv
from dataclasses import dataclass, replace
from pathlib import Path

from gtkit.errors import GtkitError
from gtkit.track.targets import Detection, read_csv, resolve_images, write_csv

from .write_guard import save_under_lock

COMMENT = ("gtkit annotate: target clicks (x,y = foot point) or boxes in zoom photos, pixels in the COLMAP "
           "convention (the photo spans [0,W]x[0,H]); read by `gtkit track`")
PLURAL = {"pixel": "pixels", "box": "boxes"}


@dataclass
class Target:
    id: str                                        # session-local key (not in the file)
    image: str                                     # relative to images/
    x: float                                       # the pixel; for a box its centre
    y: float
    label: str = "target"
    box: tuple[float, float, float, float] | None = None
    time: float | None = None                      # kept from the file; None = the photo's EXIF time

    @property
    def kind(self) -> str:
        return "box" if self.box is not None else "pixel"

    def moved(self, dx: float, dy: float) -> "Target":
        box = None if self.box is None else (self.box[0] + dx, self.box[1] + dy, self.box[2] + dx, self.box[3] + dy)
        return replace(self, x=self.x + dx, y=self.y + dy, box=box)


def box_target(tid: str, image: str, x0: float, y0: float, x1: float, y1: float, label: str) -> Target:
    b = (min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))
    return Target(tid, image, 0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3]), label, b)


class TargetStore:
    def __init__(self, path: str | Path, query_names: list[str], on_saved=None, guard=None):
        self.path = Path(path)
        self.guard = guard  # gui.write_guard.WriteGuard: each save holds the project's lock (None: no project)
        self.targets: list[Target] = []
        self._n = 0
        if self.path.is_file() and self.path.read_text(encoding="utf-8-sig").strip():
            dets = read_csv(self.path)              # the tracker's reader: GtkitError on a bad file
            resolve_images(dets, query_names, self.path)
            self.targets = [Target(self.new_id(), d.image, d.u, d.v, d.label, d.box, d.time) for d in dets]
        elif self.path.exists() and not self.path.is_file():
            raise GtkitError("not a file (the Targets page writes detections here)", self.path)
        self.on_saved = on_saved
        self.n_writes = 0
        self._stamp = self._disk_stamp()

    # --- queries -------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.targets)

    def get(self, tid: str) -> Target | None:
        return next((t for t in self.targets if t.id == tid), None)

    def in_image(self, image: str) -> list[Target]:
        return [t for t in self.targets if t.image == image]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for t in self.targets:
            out[t.image] = out.get(t.image, 0) + 1
        return out

    def labels(self) -> list[str]:
        return sorted({t.label for t in self.targets})

    def kind(self) -> str | None:
        """'pixel' or 'box' when the file holds targets (the only kind it can take), else None."""
        return self.targets[0].kind if self.targets else None

    def _disk_stamp(self):
        try:
            st = self.path.stat()
            return st.st_mtime_ns, st.st_size, st.st_ino
        except OSError:
            return None

    def changed_on_disk(self) -> bool:
        """True when another program wrote the file since this store read or wrote it (an edit
        would overwrite that work: the page refuses edits until the annotator is reopened)."""
        return self._disk_stamp() != self._stamp

    def new_id(self) -> str:
        self._n += 1
        return f"t{self._n}"

    # --- edits (each one saved before returning) ---------------------------------------------
    def save(self) -> None:
        dets = [Detection(t.image, t.x, t.y, t.label, t.time, t.box) for t in self.targets]
        if not save_under_lock(self.guard, lambda: write_csv(self.path, dets, COMMENT)):
            return   # another writer took the project meanwhile: kept in memory, written at the next save
        self._stamp = self._disk_stamp()
        self.n_writes += 1
        if self.on_saved:
            self.on_saved(self)

    def check_kind(self, t: Target) -> None:
        k = self.kind()
        if k is not None and k != t.kind:
            raise GtkitError(f"holds {PLURAL[k]}; the tracker reads one kind per file, so a {t.kind} cannot be "
                             f"added (delete the {PLURAL[k]} first, or use another file)", self.path)

    def insert(self, t: Target, index: int | None = None) -> None:
        if self.get(t.id) is not None:
            raise ValueError(f"target {t.id} exists")
        self.check_kind(t)
        self.targets.insert(len(self.targets) if index is None else index, copy.deepcopy(t))
        self.save()

    def remove(self, tid: str) -> tuple[Target, int]:
        t = self.get(tid)
        i = self.targets.index(t)
        del self.targets[i]
        self.save()
        return copy.deepcopy(t), i

    def update(self, t: Target) -> Target:
        """Replace the target with ``t.id`` (moved, relabelled); returns the previous one."""
        i = self.targets.index(self.get(t.id))
        old = self.targets[i]
        self.targets[i] = copy.deepcopy(t)
        self.save()
        return copy.deepcopy(old)


# --- the tracker's output -------------------------------------------------------------------

def tracked_results(tracks_csv: str | Path) -> list[dict]:
    """Rows of ``exports/tracks.csv`` (:mod:`gtkit.track.tracker`), or [] when there is none or
    it cannot be read (it is only shown, never needed)."""
    from gtkit.view.scene import read_tracks_csv

    try:
        rows = read_tracks_csv(Path(tracks_csv))
    except (OSError, UnicodeDecodeError, csv.Error):
        return []
    out = []
    for r in rows:
        try:
            r["u"], r["v"] = float(r["u"]), float(r["v"])
        except (KeyError, TypeError, ValueError):
            continue
        out.append(r)
    return out


def match_result(t: Target, rows: list[dict], tol_px: float = 0.02) -> dict | None:
    """The tracker's row for this target: same photo and label, pixel within ``tol_px`` of the
    pixel or of a box's centre or bottom centre (the tracker's two foot points; it writes
    pixels with 2 decimals). None when the target changed since the tracker ran."""
    feet = [(t.x, t.y)]
    if t.box is not None:
        feet.append((0.5 * (t.box[0] + t.box[2]), t.box[3]))
    for r in rows:
        if r.get("image") == t.image and r.get("label") == t.label and any(
                abs(r["u"] - u) <= tol_px and abs(r["v"] - v) <= tol_px for u, v in feet):
            return r
    return None
