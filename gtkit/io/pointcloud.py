"""Point clouds (LAS/LAZ through laspy, PLY vertices) read into the project's world frame.

For DSM-only work: a site delivered as a LiDAR or dense-matching point cloud instead of a mesh.
The CRS comes from the file (LAS/LAZ header WKT or GeoKeys), else from an offset sidecar
(``<file>.offset.json``, see :mod:`gtkit.io.mesh`), else from the caller (``crs`` / ``offset``,
the command line's ``--crs`` / ``--offset``). A file whose CRS differs from the project's is
reprojected point by point (:class:`gtkit.io.srs.SrsToWorld`); one with no CRS at all is an
error naming the file.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from .mesh import read_offset_sidecar
from .srs import SrsToWorld

POINT_SUFFIXES = (".las", ".laz", ".ply")


@dataclass
class PointCloud:
    xyz: np.ndarray                 # (N, 3) float64: world frame (read_point_cloud) or CRS coordinates (read_points)
    rgb: np.ndarray | None = None   # (N, 3) uint8
    crs: str | None = None          # the CRS the file was in (None: it states none)

    def bounds(self) -> np.ndarray:
        return np.stack([self.xyz.min(0), self.xyz.max(0)])


def ply_has_faces(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(8192).split(b"end_header")[0].decode("latin-1")
    return any(line.startswith("element face") and line.split()[-1] != "0" for line in head.splitlines())


def _read_las(path: Path) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    import laspy

    try:
        las = laspy.read(str(path))
    except Exception as e:  # noqa: BLE001 - laspy raises many types for bad files
        raise GtkitError(f"not a readable LAS/LAZ file ({type(e).__name__}: {str(e)[:120]})", path) from None
    xyz = np.stack([np.asarray(las.x, np.float64), np.asarray(las.y, np.float64), np.asarray(las.z, np.float64)], -1)
    rgb = None
    names = set(las.point_format.dimension_names)
    if {"red", "green", "blue"} <= names:
        c = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], -1).astype(np.float64)
        rgb = (c / 257.0 if c.max(initial=0) > 255 else c).round().clip(0, 255).astype(np.uint8)
    crs = None
    try:
        c = las.header.parse_crs()
        if c is not None:
            from ..geo import crs_name

            crs = crs_name(c)
    except Exception:  # noqa: BLE001 - a malformed CRS record: treat as absent, the caller decides
        crs = None
    return xyz, rgb, crs


def _read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    import trimesh

    try:
        g = trimesh.load(str(path), process=False)
    except Exception as e:  # noqa: BLE001
        raise GtkitError(f"not a readable PLY ({type(e).__name__}: {str(e)[:120]})", path) from None
    xyz = np.asarray(g.vertices, np.float64)
    rgb = None
    cols = getattr(g, "colors", None)
    if cols is None and hasattr(g, "visual"):
        cols = getattr(g.visual, "vertex_colors", None)
    if cols is not None and len(cols) == len(xyz):
        rgb = np.asarray(cols)[:, :3].astype(np.uint8)
    return xyz, rgb


def is_point_cloud(path: str | Path) -> bool:
    """LAS/LAZ, or a PLY without faces (a PLY may hold a mesh or points)."""
    path = Path(path)
    s = path.suffix.lower()
    return s in (".las", ".laz") or (s == ".ply" and not ply_has_faces(path))


def read_points(path: str | Path, offset=None) -> PointCloud:
    """LAS/LAZ/PLY points in the coordinates of the CRS the file states (``crs``, None when it
    states none): file coordinates plus the offset of the ``<file>.offset.json`` sidecar (which may
    also state the CRS), else plus ``offset``."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("point cloud not found", path)
    suffix = path.suffix.lower()
    if suffix not in POINT_SUFFIXES:
        raise GtkitError(f"not a point cloud (expected {', '.join(POINT_SUFFIXES)})", path)
    file_crs = None
    if suffix in (".las", ".laz"):
        xyz, rgb, file_crs = _read_las(path)
    else:
        xyz, rgb = _read_ply_points(path)
    if not len(xyz):
        raise GtkitError("point cloud holds no points", path)
    side = read_offset_sidecar(path)
    if side is not None:
        file_crs = file_crs or side[0]
        xyz = xyz + side[1]
    elif offset is not None:
        xyz = xyz + np.asarray(offset, np.float64)
    if not np.all(np.isfinite(xyz)):
        raise GtkitError("point cloud has NaN or infinite coordinates", path)
    return PointCloud(xyz, rgb, file_crs)


def read_point_cloud(path: str | Path, frame, crs: str | None = None, offset=None,
                     default_crs: str | None = None) -> PointCloud:
    """LAS/LAZ/PLY points in the world frame of ``frame`` (a :class:`gtkit.geo.GeoFrame`).
    The CRS is the file's; ``crs`` (the user's) must agree with it or stands in for it;
    ``default_crs`` is used only when neither states one."""
    path = Path(path)
    raw = read_points(path, offset)
    file_crs = raw.crs
    if file_crs is not None and crs is not None:
        from ..geo import parse_crs

        if not parse_crs(crs, path).equals(parse_crs(file_crs, path)):
            raise GtkitError(f"file states CRS {file_crs} but {crs} was given", path)
    use = file_crs or crs or default_crs
    if use is None:
        raise GtkitError("point cloud has no georeference (no CRS in the header or a sidecar); give --crs", path)
    to_world = SrsToWorld(use, frame, np.zeros(3), source=path)
    return PointCloud(to_world.points(raw.xyz), raw.rgb, use)
