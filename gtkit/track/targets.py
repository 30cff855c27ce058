"""Target detections in zoom photos: a CSV or labelme-style JSON -> one foot-point pixel each.

CSV (header required, comma separated; ``#`` lines ignored)::

    image,x,y[,label,time]                       a pixel (the foot point itself)
    image,xmin,ymin,xmax,ymax[,label,time]       a box

``image`` is the zoom photo's name relative to ``images/`` (``queries/seq1/0003_Z.jpg``); a bare
file name is also accepted when it is unique among the project's query photos. ``time`` is
seconds (any epoch) or an ISO-8601 timestamp; without it the photo's EXIF time is used.
``label`` names the target (one track per label; default ``target``).

labelme JSON (one file, or a folder of them): ``imagePath`` names the photo; each shape of
type ``rectangle`` (two corners) or ``point`` is a detection, ``polygon`` shapes use their
bounding box; the shape's ``label`` is the target label.

Pixels follow :mod:`gtkit.conventions` (the image spans [0, W] x [0, H]; box edges as
detectors report them).

Foot point. A box is reduced to one pixel here: its centre ("centre", what the tracker uses
by default) or its bottom centre ("bottom_centre"). The image of a box-like target's 3D centre
is (up to perspective) the centre of its 2D box, because a centrally symmetric solid projects
to a centrally symmetric outline; that centre lies half the target's height above the ground,
so the tracker casts the box-centre ray on the DSM raised by half the target's height (a table
by label) and reports the ground point below the crossing. The bottom centre is the box's
lowest image point: for an upright target seen obliquely (the zoom camera looks 15-70 deg
below the horizon) it is the NEAR bottom edge, off the footprint centre by half the target's
extent along the view (about 1-2 m for a car) -- measured on the small sample site with true
poses: median 2.3 m with the bottom centre vs 0.11 m with the lifted box centre (0.08 m with
the exact foot pixel). The bottom centre remains the choice for targets of unknown height
seen from a low angle (a person's feet). A pixel detection (x, y) is taken as the foot
point itself.
"""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..io.atomic import write_text

FOOT_POINTS = ("centre", "bottom_centre")


@dataclass
class Detection:
    image: str                       # relative to images/
    u: float                         # foot point pixel
    v: float
    label: str = "target"
    time: float | None = None        # seconds; None = take it from the photo
    box: tuple[float, float, float, float] | None = None
    source: str = ""                 # "file:line" for messages

    @property
    def key(self) -> str:
        return f"{self.label}@{self.image}"


def foot_point(box, mode: str = "centre") -> tuple[float, float]:
    xmin, ymin, xmax, ymax = box
    if mode == "bottom_centre":
        return 0.5 * (xmin + xmax), ymax
    if mode == "centre":
        return 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
    raise GtkitError(f"unknown foot point {mode!r} (choose {' or '.join(FOOT_POINTS)})")


def parse_time(value: str, where: str) -> float | None:
    s = (value or "").strip()
    if not s:
        return None
    try:
        t = float(s)
        if math.isfinite(t):
            return t
    except ValueError:
        pass
    for fmt in (None, "%Y:%m:%d %H:%M:%S"):
        try:
            dt = datetime.fromisoformat(s) if fmt is None else datetime.strptime(s, fmt)
            if dt.tzinfo is None:
                dt = dt.replace(tzinfo=timezone.utc)
            return dt.timestamp()
        except ValueError:
            continue
    raise GtkitError(f"{where}: time {s!r} is neither seconds nor an ISO-8601 timestamp")


def read_csv(path: Path, foot: str = "centre") -> list[Detection]:
    path = Path(path)
    text = path.read_text(encoding="utf-8-sig")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise GtkitError("no detections (empty file)", path)
    rows = list(csv.reader(lines))
    header = [h.strip().lower() for h in rows[0]]
    if "image" not in header:
        raise GtkitError("CSV header must name an 'image' column and either x,y or xmin,ymin,xmax,ymax; "
                         f"got {','.join(header)}", path)
    box_cols = ("xmin", "ymin", "xmax", "ymax")
    is_box = all(c in header for c in box_cols)
    if not is_box and not all(c in header for c in ("x", "y")):
        raise GtkitError("CSV needs columns x,y (a pixel) or xmin,ymin,xmax,ymax (a box)", path)
    col = {h: i for i, h in enumerate(header)}
    out = []
    for n, r in enumerate(rows[1:], 2):
        where = f"{path}: line {n}"
        if len(r) < len(header):
            raise GtkitError(f"line {n}: expected {len(header)} fields, got {len(r)}", path)
        get = lambda c: r[col[c]].strip() if c in col else ""  # noqa: E731
        try:
            if is_box:
                box = tuple(float(get(c)) for c in box_cols)
                if not all(math.isfinite(b) for b in box) or box[2] < box[0] or box[3] < box[1]:
                    raise ValueError("box needs finite xmin <= xmax and ymin <= ymax")
                u, v = foot_point(box, foot)
            else:
                box = None
                u, v = float(get("x")), float(get("y"))
                if not (math.isfinite(u) and math.isfinite(v)):
                    raise ValueError("pixel must be finite")
        except ValueError as e:
            raise GtkitError(f"line {n}: {e}", path) from None
        image = get("image")
        if not image:
            raise GtkitError(f"line {n}: empty image name", path)
        out.append(Detection(image, u, v, get("label") or "target", parse_time(get("time"), where), box,
                             f"{path.name}:{n}"))
    return out


def read_labelme(path: Path, foot: str = "centre") -> list[Detection]:
    path = Path(path)
    files = sorted(path.glob("*.json")) if path.is_dir() else [path]
    if not files:
        raise GtkitError("folder holds no labelme .json files", path)
    out = []
    for f in files:
        try:
            d = json.loads(f.read_text(encoding="utf-8"))
            image = str(d["imagePath"]).replace("\\", "/")
            shapes = d.get("shapes", [])
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as e:
            raise GtkitError(f"not a labelme JSON ({type(e).__name__}: {e})", f) from None
        for k, s in enumerate(shapes):
            try:
                pts = np.asarray(s["points"], dtype=np.float64).reshape(-1, 2)
                kind = s.get("shape_type") or ("point" if len(pts) == 1 else "rectangle")
                label = str(s.get("label") or "target")
            except (KeyError, TypeError, ValueError) as e:
                raise GtkitError(f"shape {k}: unreadable ({e})", f) from None
            if not np.all(np.isfinite(pts)) or not len(pts):
                raise GtkitError(f"shape {k}: no finite points", f)
            if kind == "point":
                box, (u, v) = None, pts[0]
            elif kind in ("rectangle", "polygon"):
                if len(pts) < 2:
                    raise GtkitError(f"shape {k}: a {kind} needs at least two points", f)
                box = (*pts.min(0), *pts.max(0))
                u, v = foot_point(box, foot)
            else:
                raise GtkitError(f"shape {k}: unsupported shape_type {kind!r} (rectangle, polygon, point)", f)
            t = s.get("time", d.get("time"))
            out.append(Detection(image, float(u), float(v), label,
                                 None if t is None else parse_time(str(t), str(f)),
                                 None if box is None else tuple(float(b) for b in box), f"{f.name}#{k}"))
    return out


def read_detections(path: str | Path, foot: str = "centre") -> list[Detection]:
    """Detections from a CSV, a labelme JSON, or a folder of labelme JSONs."""
    path = Path(path)
    if foot not in FOOT_POINTS:
        raise GtkitError(f"unknown foot point {foot!r} (choose {' or '.join(FOOT_POINTS)})")
    if not path.exists():
        raise GtkitError("detections file not found", path)
    if path.is_dir() or path.suffix.lower() == ".json":
        dets = read_labelme(path, foot)
    elif path.suffix.lower() in (".csv", ".txt"):
        dets = read_csv(path, foot)
    else:
        raise GtkitError("detections must be a .csv, a labelme .json or a folder of them", path)
    if not dets:
        raise GtkitError("no detections in the file", path)
    return dets


def resolve_images(dets: list[Detection], query_names: list[str], source: Path) -> None:
    """Map each detection's image to a query photo name relative to images/ (in place)."""
    known = set(query_names)
    by_base: dict[str, list[str]] = {}
    for n in query_names:
        by_base.setdefault(n.rsplit("/", 1)[-1], []).append(n)
    for d in dets:
        name = d.image.lstrip("./")
        if name.startswith("images/"):
            name = name[len("images/"):]
        if name in known:
            d.image = name
            continue
        cands = by_base.get(name.rsplit("/", 1)[-1], [])
        tail = [c for c in cands if c.endswith(name)]
        if len(tail) == 1:
            d.image = tail[0]
        elif len(tail) > 1:
            raise GtkitError(f"{d.source}: image {d.image!r} is ambiguous ({', '.join(tail[:3])}); "
                             "give its path relative to images/", source)
        else:
            raise GtkitError(f"{d.source}: image {d.image!r} is not a query photo of this project", source)


def detections_csv(dets: list[Detection], comment: str = "") -> str:
    """The CSV text :func:`read_csv` reads back to the same detections (what the annotator's
    Targets page writes). One kind per file, as the reader wants: all pixels
    (``image,x,y,label[,time]``) or all boxes (``image,xmin,ymin,xmax,ymax,label[,time]``);
    a ``time`` column only when some detection has a time. No detections: the header alone."""
    kinds = {d.box is not None for d in dets}
    if len(kinds) > 1:
        raise GtkitError("a detections CSV holds either pixels or boxes, not both")
    is_box = kinds == {True}
    has_time = any(d.time is not None for d in dets)
    buf = io.StringIO()
    for line in comment.splitlines():
        buf.write(f"# {line}\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["image", *(("xmin", "ymin", "xmax", "ymax") if is_box else ("x", "y")), "label",
                *(["time"] if has_time else [])])
    for d in dets:
        xy = d.box if is_box else (d.u, d.v)
        w.writerow([d.image, *(f"{float(v):.3f}" for v in xy), d.label or "target",
                    *([] if not has_time else ["" if d.time is None else f"{d.time:.3f}"])])
    return buf.getvalue()


def write_csv(path: str | Path, dets: list[Detection], comment: str = "") -> Path:
    """Write ``dets`` atomically as a detections CSV (:func:`detections_csv`)."""
    return write_text(path, detections_csv(dets, comment))
