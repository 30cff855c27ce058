"""Annotators' verdict per image after looking at the alignment overlay: ``review.json``.

Format (``Paths.review``, written atomically after every change)::

    {"format": "gtkit-review", "version": 1,
     "images": {"queries/seq1/0001_W.jpg": {"status": "accept", "note": "", "when": "2026-11-22T01:02:03",
                                            "pose_file": "work/register/poses.txt",
                                            "misalignment_px": 0.4}}}

``status`` is one of :data:`STATUSES`. Image names are relative to ``images/``. The report
stage reads it with :func:`read_review`; the GUI writes it with :func:`set_status`. A plain
``{"image": "accept", ...}`` mapping (hand-written) is read too.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from .errors import GtkitError
from .io.atomic import write_json

FORMAT = "gtkit-review"
VERSION = 1
STATUSES = ("accept", "reject", "needs-work")


def read_review(path: str | Path) -> dict[str, dict]:
    """image name -> {"status", "note", "when", ...}; empty when the file does not exist."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise GtkitError(f"not valid JSON ({e})", path) from None
    if not isinstance(d, dict):
        raise GtkitError("not a gtkit review file (expected a JSON object)", path)
    if "format" not in d and d and all(isinstance(v, str) for v in d.values()):
        d = {"format": FORMAT, "images": {k: {"status": v} for k, v in d.items()}}  # plain {image: status}
    if d.get("format") != FORMAT:
        raise GtkitError(f"not a gtkit review file (format {d.get('format')!r})", path)
    images = d.get("images", {})
    for name, rec in images.items():
        if not isinstance(rec, dict) or rec.get("status") not in STATUSES:
            raise GtkitError(f"{name}: status must be one of {', '.join(STATUSES)}", path)
    return images


def write_review(path: str | Path, images: dict[str, dict]) -> Path:
    return write_json(path, {"format": FORMAT, "version": VERSION, "statuses": list(STATUSES),
                             "images": dict(sorted(images.items()))})


def set_status(path: str | Path, image: str, status: str | None, note: str = "", **info) -> dict[str, dict]:
    """Record (or with ``status=None`` clear) the verdict for one image; returns all verdicts."""
    if status is not None and status not in STATUSES:
        raise GtkitError(f"review status must be one of {', '.join(STATUSES)}, got {status!r}")
    images = read_review(path)
    if status is None:
        images.pop(image, None)
    else:
        images[image] = {"status": status, "note": note, "when": time.strftime("%Y-%m-%dT%H:%M:%S"), **info}
    write_review(path, images)
    return images


def summary(images: dict[str, dict]) -> dict[str, int]:
    """Counts per status (for reports)."""
    out = {s: 0 for s in STATUSES}
    for rec in images.values():
        out[rec["status"]] += 1
    return out
