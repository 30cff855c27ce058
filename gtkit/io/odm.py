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

from ..errors import GtkitError
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
    path = Path(path)
    if not path.is_file():
        raise GtkitError("file not found", path)
    lines = [(n, ln.strip()) for n, ln in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)]
    lines = [(n, s) for n, s in lines if s and not s.startswith("#")]
    if not lines:
        raise GtkitError("empty file (the first line must name the CRS)", path)
    return lines[0][1], lines[1:]


def read_crs(path: str | Path) -> str:
    """The CRS named on the first line of a ``gcp_list.txt`` or ``geo.txt``."""
    header, _ = _data_lines(path)
    return parse_odm_crs(header, path)


def read_gcp_list(path: str | Path, frame: GeoFrame) -> list[GCP]:
    """GCPs with their clicks, coordinates converted to ``frame``'s local world frame."""
    path = Path(path)
    header, rows = _data_lines(path)
    crs = parse_odm_crs(header, path)
    gcps: dict[str, GCP] = {}
    for n, s in rows:
        f = s.split()
        if len(f) < 6:
            raise GtkitError(f"line {n}: expected 'geo_x geo_y geo_z px py image [name]', got {len(f)} fields", path)
        try:
            geo = np.array([float(v) for v in f[:3]])
            px, py = float(f[3]), float(f[4])
        except ValueError as e:
            raise GtkitError(f"line {n}: {e}", path) from None
        if not (np.all(np.isfinite(geo)) and np.isfinite(px) and np.isfinite(py)):
            raise GtkitError(f"line {n}: non-finite value", path)
        name = f[6] if len(f) > 6 else "gcp_%.3f_%.3f_%.3f" % tuple(geo)
        local = frame.from_crs(crs, geo[None])[0]
        g = gcps.get(name)
        if g is None:
            g = gcps[name] = GCP(name, local)
        elif np.linalg.norm(g.xyz - local) > 1e-3:
            raise GtkitError(f"line {n}: GCP {name!r} has different coordinates than on an earlier line", path)
        g.clicks.append(GCPClick(f[5], px, py))
        if any(x.lower() in CHECK_WORDS for x in f[7:]):
            g.check = True
    return list(gcps.values())


CHECK_WORDS = ("check", "checkpoint", "chk")


@dataclass
class GeoEntry:
    image: str
    xyz: np.ndarray  # local world frame; z NaN when the file gives none
    accuracy: tuple[float, float] | None = None  # (horizontal, vertical) metres


def read_geo_txt(path: str | Path, frame: GeoFrame) -> dict[str, GeoEntry]:
    """ODM ``geo.txt`` -> {image: GeoEntry} in ``frame``'s local world frame."""
    path = Path(path)
    header, rows = _data_lines(path)
    crs = parse_odm_crs(header, path)
    out = {}
    for n, s in rows:
        f = s.split()
        if len(f) < 3:
            raise GtkitError(f"line {n}: expected 'image geo_x geo_y [geo_z ...]'", path)
        try:
            vals = [float(v) for v in f[1:]]
        except ValueError as e:
            raise GtkitError(f"line {n}: {e}", path) from None
        z = vals[2] if len(vals) > 2 else 0.0
        local = frame.from_crs(crs, np.array([[vals[0], vals[1], z]]))[0]
        if len(vals) <= 2:
            local[2] = np.nan
        acc = (vals[6], vals[7]) if len(vals) >= 8 else None
        out[f[0]] = GeoEntry(f[0], local, acc)
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
