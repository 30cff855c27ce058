"""OpenDroneMap's ground-control and image-position files: ``gcp_list.txt`` and ``geo.txt``.

``gcp_list.txt``: the first line names the CRS (``EPSG:32650``, a PROJ string, or ODM's
``WGS84 UTM 50N``); every other line is ``geo_x geo_y geo_z px py image [name] [...]``, one
click of a ground control point in one photo. A point whose line carries ``check`` (or
``checkpoint``, ``chk``) after the name is a check point: left out of georegistration and
reported apart. ``px py`` are read in gtkit's pixel convention
(COLMAP: top-left pixel centre at (0.5, 0.5), see :mod:`gtkit.conventions`). Lines sharing a
name (or, without names, the same coordinates) are clicks of one GCP.

``geo.txt``: the first line names the CRS, then ``image geo_x geo_y [geo_z [omega phi kappa
[horizontal_accuracy vertical_accuracy]]]`` per photo.

Coordinates are returned in the project's local world frame (:class:`gtkit.geo.GeoFrame`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GtkitError, Problems
from ..geo import GeoFrame, parse_crs

_ODM_UTM = re.compile(r"^\s*WGS84\s+UTM\s+(\d{1,2})\s*([NS])\s*$", re.IGNORECASE)


def parse_odm_crs(line: str, source=None) -> str:
    """An ODM CRS header line -> a CRS spec pyproj understands ('EPSG:32650', PROJ or WKT)."""
    m = _ODM_UTM.match(line)
    if m:
        zone, hemi = int(m.group(1)), m.group(2).upper()
        if not 1 <= zone <= 60:
            raise GtkitError(f"UTM zone {zone} out of range in CRS line {line!r}", source)
        return f"EPSG:{(32600 if hemi == 'N' else 32700) + zone}"
    spec = line.strip()
    parse_crs(spec, source)  # raises a clear error for an unknown CRS
    return spec


@dataclass
class GCPClick:
    image: str
    x: float
    y: float


@dataclass
class GCP:
    name: str
    xyz: np.ndarray  # local world frame
    clicks: list[GCPClick] = field(default_factory=list)
    check: bool = False  # a check point: measured, never fitted


def _data_lines(path: Path):
    """(header line number, header, [(n, line) ...]) of the file's non-blank, non-comment lines."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("file not found", path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise GtkitError(f"not a text file (byte {e.start} is not UTF-8)", path) from None
    lines = [(n, ln.strip()) for n, ln in enumerate(text.splitlines(), 1)]
    lines = [(n, s) for n, s in lines if s and not s.startswith("#")]
    if not lines:
        raise GtkitError("empty file (the first line must name the CRS)", path)
    return lines[0][0], lines[0][1], lines[1:]


def read_crs(path: str | Path) -> str:
    """The CRS named on the first line of a ``gcp_list.txt`` or ``geo.txt``."""
    _, header, _ = _data_lines(path)
    return parse_odm_crs(header, path)


class _Bad(ValueError):
    """One line's problem (collected, never shown alone)."""


def _numbers(fields: list[str], names: tuple[str, ...], finite: tuple[str, ...] | None = None) -> list[float]:
    """``fields`` as numbers (those named in ``finite``, default all, finite); a field that is not one is
    named (``geo_y 'abc' is not a number``)."""
    out = []
    for name, v in zip(names, fields):
        try:
            x = float(v)
        except ValueError:
            raise _Bad(f"{name} {v!r} is not a number") from None
        if not np.isfinite(x) and name in (names if finite is None else finite):
            raise _Bad(f"{name} is {v} (not a finite number)")
        out.append(x)
    return out


def _header_crs(path: Path, n: int, header: str, problems: Problems) -> str | None:
    try:
        return parse_odm_crs(header, path)
    except GtkitError:
        problems.add(f"line {n}", f"the first line must name the CRS (EPSG:<code>, a PROJ string or "
                                  f"'WGS84 UTM <zone><N|S>'), got {header[:40]!r}")
        return None


def read_gcp_list(path: str | Path, frame: GeoFrame) -> list[GCP]:
    """GCPs with their clicks, coordinates converted to ``frame``'s local world frame. Every bad line
    is named in one error (:class:`gtkit.errors.Problems`)."""
    path = Path(path)
    hn, header, rows = _data_lines(path)
    problems = Problems(path)
    crs = _header_crs(path, hn, header, problems)
    gcps: dict[str, GCP] = {}
    for n, s in rows:
        f = s.split()
        try:
            if len(f) < 6:
                raise _Bad(f"expected 'geo_x geo_y geo_z px py image [name]', got {len(f)} field{'s' if len(f) != 1 else ''}")
            vals = _numbers(f[:5], ("geo_x", "geo_y", "geo_z", "px", "py"))
        except _Bad as e:
            problems.add(f"line {n}", e)
            continue
        geo, px, py = np.array(vals[:3]), vals[3], vals[4]
        name = f[6] if len(f) > 6 else "gcp_%.3f_%.3f_%.3f" % tuple(geo)
        if crs is None:
            continue
        local = frame.from_crs(crs, geo[None])[0]
        g = gcps.get(name)
        if g is None:
            g = gcps[name] = GCP(name, local)
        elif np.linalg.norm(g.xyz - local) > 1e-3:
            problems.add(f"line {n}", f"GCP {name!r} has different coordinates than on an earlier line")
            continue
        g.clicks.append(GCPClick(f[5], px, py))
        if any(x.lower() in CHECK_WORDS for x in f[7:]):
            g.check = True
    problems.raise_if_any()
    return list(gcps.values())


CHECK_WORDS = ("check", "checkpoint", "chk")


@dataclass
class GeoEntry:
    image: str
    xyz: np.ndarray  # local world frame; z NaN when the file gives none
    accuracy: tuple[float, float] | None = None  # (horizontal, vertical) metres


_GEO_FIELDS = ("geo_x", "geo_y", "geo_z", "omega", "phi", "kappa", "horizontal_accuracy", "vertical_accuracy")


def read_geo_txt(path: str | Path, frame: GeoFrame) -> dict[str, GeoEntry]:
    """ODM ``geo.txt`` -> {image: GeoEntry} in ``frame``'s local world frame. Every bad line is
    named in one error (:class:`gtkit.errors.Problems`)."""
    path = Path(path)
    hn, header, rows = _data_lines(path)
    problems = Problems(path)
    crs = _header_crs(path, hn, header, problems)
    out = {}
    for n, s in rows:
        f = s.split()
        try:
            if len(f) < 3:
                raise _Bad(f"expected 'image geo_x geo_y [geo_z ...]', got {len(f)} field{'s' if len(f) != 1 else ''}")
            vals = _numbers(f[1:], _GEO_FIELDS, _GEO_FIELDS[:3])   # ODM's extras after the accuracies are not read
        except _Bad as e:
            problems.add(f"line {n}", e)
            continue
        if crs is None:
            continue
        z = vals[2] if len(vals) > 2 else 0.0
        local = frame.from_crs(crs, np.array([[vals[0], vals[1], z]]))[0]
        if len(vals) <= 2:
            local[2] = np.nan
        acc = (vals[6], vals[7]) if len(vals) >= 8 else None
        out[f[0]] = GeoEntry(f[0], local, acc)
    problems.raise_if_any()
    return out


def write_gcp_list(path: str | Path, frame: GeoFrame, gcps: list[GCP]) -> Path:
    """``gcps`` (coordinates in ``frame``'s local world frame, clicks in full-resolution pixels of
    gtkit's convention) as an ODM ``gcp_list.txt`` in ``frame``'s CRS, atomically: one line per click,
    ``geo_x geo_y geo_z px py image name`` and ``check`` after the name of a check point (as
    :func:`read_gcp_list` reads it back). A GCP without clicks has no line (ODM has no place for it)."""
    from .atomic import write_text

    lines = [frame.crs_spec]
    for g in gcps:
        x, y, z = frame.local_to_crs(np.asarray(g.xyz, float))
        for c in g.clicks:
            if any(ch.isspace() for ch in c.image) or any(ch.isspace() for ch in g.name):
                raise GtkitError(f"a photo or GCP name with a space cannot be written to gcp_list.txt: "
                                 f"{c.image!r} / {g.name!r}", path)
            lines.append(f"{x:.4f} {y:.4f} {z:.4f} {c.x:.3f} {c.y:.3f} {c.image} {g.name}" + (" check" if g.check else ""))
    return write_text(path, "\n".join(lines) + "\n")
