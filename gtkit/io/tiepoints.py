"""The tie-point file (``tiepoints.json``): what annotators click and what registration reads.

Format (JSON, UTF-8; documented for other tools in docs/tiepoints.md)::

    {
      "format": "gtkit-tiepoints", "version": 1,
      "pixel_convention": "COLMAP: the top-left pixel's centre is (0.5, 0.5)",
      "tiepoints": [
        {"id": "tp0001",
         "observations": [{"image": "queries/seq1/W_0001.jpg", "x": 812.3, "y": 402.9},
                          {"image": "reference/R_0012_N.jpg", "x": 1501.0, "y": 88.4}],
         "source": "gui",            # gui | simulated | suggestion | import
         "note": ""}
      ]
    }

Image names are paths relative to the project's ``images/`` folder, with forward slashes.
A tie point needs observations in at least one query and one reference photo to tie the
blocks; ids are unique strings. Writes are atomic (temp file + rename).
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..errors import GtkitError
from .atomic import write_json

FORMAT = "gtkit-tiepoints"
VERSION = 1


@dataclass
class Observation:
    image: str
    x: float
    y: float


@dataclass
class TiePoint:
    id: str
    observations: list[Observation] = field(default_factory=list)
    source: str = "gui"
    note: str = ""

    def images(self) -> list[str]:
        return [o.image for o in self.observations]

    def in_block(self, prefix: str) -> list[Observation]:
        return [o for o in self.observations if o.image.startswith(prefix)]


def read_tiepoints(path: str | Path) -> list[TiePoint]:
    path = Path(path)
    if not path.is_file():
        raise GtkitError("tie-point file not found", path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise GtkitError(f"not valid JSON ({e})", path) from None
    if d.get("format") != FORMAT:
        raise GtkitError(f"not a gtkit tie-point file (format {d.get('format')!r})", path)
    if d.get("version", 0) > VERSION:
        raise GtkitError(f"tie-point file version {d.get('version')} is newer than this gtkit ({VERSION})", path)
    out, seen = [], set()
    for k, t in enumerate(d.get("tiepoints", [])):
        try:
            tp = TiePoint(str(t["id"]), [Observation(str(o["image"]), float(o["x"]), float(o["y"]))
                                         for o in t.get("observations", [])],
                          str(t.get("source", "gui")), str(t.get("note", "")))
        except (KeyError, TypeError, ValueError) as e:
            raise GtkitError(f"tie point #{k}: malformed ({e})", path) from None
        if tp.id in seen:
            raise GtkitError(f"duplicate tie-point id {tp.id!r}", path)
        seen.add(tp.id)
        out.append(tp)
    return out


def write_tiepoints(path: str | Path, tiepoints: list[TiePoint]) -> Path:
    return write_json(path, {
        "format": FORMAT, "version": VERSION,
        "pixel_convention": "COLMAP: the top-left pixel's centre is (0.5, 0.5)",
        "tiepoints": [asdict(t) for t in tiepoints]}, indent=1)
