"""OpenDroneMap textured models, and single mesh files with a CRS and offset from elsewhere.

ODM writes ``odm_texturing/odm_textured_model_geo.obj`` with vertices in UTM *minus an integer
offset*, and the offset in ``odm_georeferencing/coords.txt``::

    WGS84 UTM 32N
    322263 5157982
    ...

(first line the datum and UTM zone, second line the easting and northing offset; heights are
not offset). gtkit's own offset sidecar (``<mesh>.offset.json``), when present, takes precedence.
Any single OBJ/PLY/GLB can be imported the same way with the CRS and offset given by the caller.
A CRS other than the project's is reprojected vertex by vertex (:mod:`gtkit.io.srs`).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from .mesh import Mesh, read_mesh_file, read_offset_sidecar
from .srs import SrsToWorld

ODM_MODEL = Path("odm_texturing") / "odm_textured_model_geo.obj"
ODM_COORDS = Path("odm_georeferencing") / "coords.txt"
_UTM = re.compile(r"^\s*WGS\s*-?\s*84\s+UTM\s+(\d{1,2})\s*([NS])\s*$", re.IGNORECASE)


def find_odm_model(path: str | Path) -> Path | None:
    """The textured model of an ODM project folder (or the OBJ itself); None if not ODM-shaped."""
    path = Path(path)
    if path.is_dir() and (path / ODM_MODEL).is_file():
        return path / ODM_MODEL
    if path.is_dir() and (path / ODM_MODEL.name).is_file():
        return path / ODM_MODEL.name
    if path.is_file() and path.name == ODM_MODEL.name:
        return path
    return None


def read_coords_txt(path: str | Path) -> tuple[str, np.ndarray]:
    """(CRS, offset (x, y, 0)) from ODM's ``coords.txt``."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("ODM coords.txt not found (it holds the model's UTM offset)", path)
    lines = [ln.strip() for ln in path.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    if len(lines) < 2:
        raise GtkitError("expected a CRS line and an offset line", path)
    m = _UTM.match(lines[0])
    if m:
        zone = int(m.group(1))
        if not 1 <= zone <= 60:
            raise GtkitError(f"UTM zone {zone} out of range", path)
        crs = f"EPSG:{(32600 if m.group(2).upper() == 'N' else 32700) + zone}"
    else:
        from ..geo import crs_name, parse_crs

        try:
            crs = crs_name(parse_crs(lines[0], path))
        except GtkitError:
            raise GtkitError(f"SRS cannot be understood: {lines[0][:80]!r} (expected 'WGS84 UTM <zone><N|S>' "
                             "or a CRS definition)", path) from None
    try:
        xy = [float(v) for v in lines[1].split()[:2]]
    except ValueError:
        raise GtkitError(f"offset line is not two numbers: {lines[1]!r}", path) from None
    if len(xy) != 2 or not np.all(np.isfinite(xy)):
        raise GtkitError(f"offset line is not two numbers: {lines[1]!r}", path)
    return crs, np.array([xy[0], xy[1], 0.0])


def read_georeferenced_mesh(path: str | Path, frame, crs: str | None = None, offset=None) -> tuple[Mesh, str, np.ndarray]:
    """A single mesh file in the world frame. Georeference from the sidecar, else ``crs``/``offset``.
    Returns (mesh, crs, offset) so the caller can record what was used."""
    path = Path(path)
    side = read_offset_sidecar(path)
    if side is not None:
        crs, off = side
    else:
        if crs is None:
            raise GtkitError("mesh has no georeference: write a .offset.json sidecar or give --crs (and --offset)",
                             path)
        off = np.zeros(3) if offset is None else np.asarray(offset, np.float64).reshape(3)
    to_world = SrsToWorld(crs, frame, off, source=path)
    mesh = read_mesh_file(path)
    for p in mesh.parts:
        p.vertices = to_world.points(p.vertices)
    return mesh, crs, off


def read_odm_model(path: str | Path, frame) -> tuple[Mesh, str, np.ndarray]:
    """ODM's textured model (project folder or the OBJ) in the world frame; returns (mesh, crs, offset)."""
    obj = find_odm_model(path)
    if obj is None:
        raise GtkitError(f"no {ODM_MODEL} here", path)
    if read_offset_sidecar(obj) is not None:
        return read_georeferenced_mesh(obj, frame)
    coords = obj.parent.parent / ODM_COORDS
    crs, off = read_coords_txt(coords)
    return read_georeferenced_mesh(obj, frame, crs, off)
