"""A surveyor's GCP coordinates file, read, checked and stored in the project.

The file (CSV or whitespace separated; ``#`` starts a comment)::

    EPSG:32650                              <- optional first line: the CRS (EPSG code, PROJ, WKT,
                                               or ODM's "WGS84 UTM 50N"), as in gcp_list.txt
    name, x, y, z [, acc_h [, acc_v]] [, check]

``x y z`` are easting, northing, height in that CRS; ``acc_h`` / ``acc_v`` the point's stated 1-sigma
horizontal / vertical accuracy in metres (one value: both); a last field ``check`` (``checkpoint``,
``chk``, or a kind column ``gcp`` / ``check``) marks a check point, measured but never fitted. A
header row of column names (``name,x,y,z,...``) is skipped. The CRS is the file's first line, else
``crs`` given by the caller (``--crs``), else the project's.

Stored in the project as ``gcp/points.txt`` (the same format, in the project's CRS, written
atomically); the clicks live in ``gcp_list.txt`` as before.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError, Problems
from ..geo import GeoFrame
from .atomic import write_text
from .odm import CHECK_WORDS, parse_odm_crs

POINTS_FILE = Path("gcp") / "points.txt"
_SPLIT = re.compile(r"[,;\s]+")
_HEADER_WORDS = {"name", "id", "label", "x", "y", "z", "e", "n", "h", "easting", "northing", "height"}


@dataclass
class GCPPoint:
    name: str
    xyz: np.ndarray                # local world frame (project CRS minus origin)
    acc_h: float | None = None     # stated 1-sigma horizontal accuracy, metres
    acc_v: float | None = None     # stated 1-sigma vertical accuracy, metres
    check: bool = False            # a check point: never in the fit
    line: int = 0                  # where it came from (for messages)


def points_path(paths) -> Path:
    return Path(paths.root) / POINTS_FILE


def is_crs_line(s: str) -> bool:
    f = [x for x in _SPLIT.split(s.strip()) if x]
    if s.strip().upper().startswith(("EPSG:", "+PROJ", "PROJCS", "PROJCRS", "WGS84 UTM")):
        return True
    return len(f) == 1 and not re.fullmatch(r"[-+0-9.eE]+", f[0]) and f[0].lower() not in _HEADER_WORDS


def _float(v: str, what: str, n: int, path) -> float:
    try:
        x = float(v)
    except ValueError:
        raise GtkitError(f"line {n}: {what} {v!r} is not a number", path) from None
    if not np.isfinite(x):
        raise GtkitError(f"line {n}: {what} {v!r} is not finite", path)
    return x


def _point_row(s: str, n: int, path) -> tuple[str, list[float], list[float], bool]:
    """One line: (name, x y z, accuracies, check); GtkitError naming the line where it is bad."""
    f = [x for x in _SPLIT.split(s) if x]
    check = False
    if f and f[-1].lower() in CHECK_WORDS + ("gcp", "control"):
        check = f.pop().lower() in CHECK_WORDS
    if len(f) < 4 or len(f) > 6:
        raise GtkitError(f"line {n}: expected 'name x y z [acc_h [acc_v]] [check]', got {len(f)} fields", path)
    xyz = [_float(v, w, n, path) for v, w in zip(f[1:4], ("x", "y", "z"))]
    acc = [_float(v, "accuracy", n, path) for v in f[4:]]
    if any(a <= 0 for a in acc):
        raise GtkitError(f"line {n}: accuracy must be > 0 m, got {' '.join(f[4:])}", path)
    return f[0], xyz, acc, check


def read_points(path: str | Path, frame: GeoFrame, crs: str | None = None) -> tuple[list[GCPPoint], str]:
    """(points in ``frame``'s local world frame, the CRS they were given in). One line naming the
    file and every bad line with its problem (:class:`gtkit.errors.Problems`): a non-numeric field,
    a duplicate name, a row with too few fields; or an unknown CRS."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("file not found", path)
    rows = []
    for n, ln in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):
        s = ln.split("#", 1)[0].strip()
        if s:
            rows.append((n, s))
    if not rows:
        raise GtkitError("no GCPs in this file (expected 'name x y z' lines)", path)
    file_crs = None
    if is_crs_line(rows[0][1]):
        n, s = rows.pop(0)
        try:
            file_crs = parse_odm_crs(s.strip(), path)
        except GtkitError as e:
            raise GtkitError(f"line {n}: unknown CRS {s.strip()!r} ({str(e).split(': ', 1)[-1]})", path) from None
    spec = file_crs or crs or frame.crs_spec
    if rows and rows[0][1].split(",")[0].split()[0].lower() in _HEADER_WORDS:
        rows.pop(0)  # a header row of column names
    pts: dict[str, GCPPoint] = {}
    geo = []
    bad = Problems(path)     # every bad line at once
    for n, s in rows:
        try:
            name, xyz, acc, check = _point_row(s, n, path)
        except GtkitError as e:
            bad.add(None, str(e).split(": ", 1)[-1])
            continue
        if name in pts:
            bad.add(f"line {n}", f"duplicate GCP name {name!r} (first on line {pts[name].line})")
            continue
        acc_h = acc[0] if acc else None
        acc_v = acc[1] if len(acc) > 1 else acc_h
        pts[name] = GCPPoint(name, np.zeros(3), acc_h, acc_v, check, n)
        geo.append(xyz)
    bad.raise_if_any()
    if not pts:
        raise GtkitError("no GCPs in this file (expected 'name x y z' lines)", path)
    try:
        local = frame.from_crs(spec, np.array(geo, float))
    except Exception as e:  # pyproj: a CRS it cannot transform from
        raise GtkitError(f"cannot convert from CRS {spec!r} to the project's {frame.crs_spec}: {e}", path) from None
    if not np.all(np.isfinite(local)):
        bad = next(p for p, x in zip(pts.values(), local) if not np.all(np.isfinite(x)))
        raise GtkitError(f"line {bad.line}: GCP {bad.name!r} cannot be converted from {spec} (outside the CRS's area?)",
                         path)
    for p, x in zip(pts.values(), local):
        p.xyz = x
    return list(pts.values()), spec


def check_inside(points: list[GCPPoint], extent: np.ndarray | None, path, margin_m: float = 200.0,
                 what: str = "the block") -> None:
    """Refuse a GCP farther than ``margin_m`` outside ``extent`` ((2, 2): min, max of x, y in the
    local frame): a wrong CRS, swapped columns or a typo. ``extent`` None: nothing to check against."""
    if extent is None:
        return
    lo, hi = np.asarray(extent[0]) - margin_m, np.asarray(extent[1]) + margin_m
    for p in points:
        if np.any(p.xyz[:2] < lo) or np.any(p.xyz[:2] > hi):
            d = float(np.max(np.r_[lo - p.xyz[:2], p.xyz[:2] - hi]))
            raise GtkitError(f"line {p.line}: GCP {p.name!r} is {d + margin_m:.0f} m outside {what} (wrong CRS, "
                             "swapped x / y, or a typo?)", path)


def write_points(path: str | Path, points: list[GCPPoint], frame: GeoFrame) -> Path:
    """``points`` in ``frame``'s CRS, in the format :func:`read_points` reads, atomically."""
    lines = [frame.crs_spec, "# name x y z acc_h acc_v kind (gtkit gcp import; CRS on the first line)"]
    for p in points:
        x, y, z = frame.local_to_crs(p.xyz)
        acc = (f" {p.acc_h:.4f} {p.acc_v if p.acc_v is not None else p.acc_h:.4f}" if p.acc_h is not None else "")
        lines.append(f"{p.name} {x:.4f} {y:.4f} {z:.4f}{acc} {'check' if p.check else 'gcp'}")
    return write_text(path, "\n".join(lines) + "\n")


def load_points(paths, frame: GeoFrame) -> list[GCPPoint]:
    """The project's imported GCP coordinates (``gcp/points.txt``); [] when none were imported."""
    p = points_path(paths)
    return read_points(p, frame)[0] if p.is_file() else []
