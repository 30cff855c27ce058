"""Where an export's surface comes from: the project's reference model, or a file given
explicitly (a mesh, or a LAS/LAZ/PLY point cloud) with its CRS from a sidecar, the file's
header, or the command line.

Georeference is never guessed: a file without one, or whose CRS differs from the project's,
is a one-line :class:`~gtkit.errors.GtkitError` naming the file.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..geo import GeoFrame, crs_name, parse_crs
from ..io.mesh import MESH_SUFFIXES, load_model, model_shift, read_offset_sidecar, sidecar_path
from ..io.obj_geometry import read_obj_geometry
from ..project import file_fingerprint
from ..io.pointcloud import POINT_SUFFIXES, is_point_cloud, read_points
from ..io.tiled import is_tiled
from ..model_files import REFERENCE_MODEL, reference_model  # noqa: F401  (where they were first)
from .surface import MeshSurface, ObjMeshSurface, ObjTexturedSurface, PointSurface, TiledSurface

def input_fingerprint_paths(path: Path) -> list[Path]:
    if is_tiled(path):
        meta = path / "metadata.xml" if path.is_dir() else path
        index = meta.parent / "tiles_index.json"
        return [meta, index]
    return [path, sidecar_path(path)]


def load_surface(path: str | Path, frame: GeoFrame | None = None, crs: str | None = None,
                 offset=None, textures: bool = True) -> tuple[MeshSurface | PointSurface, GeoFrame]:
    """A surface source in the world frame of ``frame``.

    Without a frame (a file outside a project) one is made from the file's CRS (or ``crs``)
    with an origin at the data's minimum corner rounded to whole metres. ``textures=False``
    (heights only: the DSM, model compare): an OBJ is read as its triangles
    (:class:`ObjMeshSurface`; its texture images are not decoded) and a tiled model is drawn a
    tile's triangles at a time. With textures (the orthophoto) an OBJ is read by the same numpy
    reader with its corners' uv (:class:`ObjTexturedSurface`), each texture decoded once when
    its part is uploaded; other meshes go through trimesh (:class:`MeshSurface`).
    """
    path = Path(path)
    if is_tiled(path) and path.exists():
        if frame is None:
            raise GtkitError("a tiled model is exported inside a project (its frame); give the project", path)
        from ..io.tiled import read_tiled

        return TiledSurface(read_tiled(path, frame)), frame
    if not path.is_file():
        raise GtkitError("input not found", path)
    suffix = path.suffix.lower()
    if suffix not in POINT_SUFFIXES and suffix not in MESH_SUFFIXES:
        raise GtkitError(f"not a mesh or point cloud (expected {', '.join(MESH_SUFFIXES + POINT_SUFFIXES)})", path)
    if is_point_cloud(path):
        cloud = read_points(path, offset=offset)
        file_crs = cloud.crs
        if file_crs is not None and crs is not None and not parse_crs(crs, path).equals(parse_crs(file_crs, path)):
            raise GtkitError(f"file states CRS {file_crs} but --crs {crs} was given", path)
        use_crs = file_crs or crs
        if use_crs is None:
            raise GtkitError("point cloud has no georeference: its header/sidecar states no CRS; give --crs", path)
        if frame is None:
            frame = GeoFrame(crs_name(parse_crs(use_crs, path)), _origin_of(cloud.xyz), source=str(path))
        elif not parse_crs(use_crs, path).equals(frame.crs):
            raise GtkitError(f"point cloud CRS {use_crs} does not match the project CRS {frame.crs_spec}", path)
        return PointSurface(frame.crs_to_local(cloud.xyz), cloud.rgb), frame
    geometry_only = not textures and suffix == ".obj"
    if textures and suffix == ".obj" and not _vertex_coloured_obj(path):
        # the orthophoto: the numpy reader keeps the corners' uv; textures decoded at upload
        if frame is None:
            side = read_offset_sidecar(path)
            use_crs = side[0] if side is not None else crs
            if use_crs is None:
                raise GtkitError("mesh has no georeference: write a .offset.json sidecar or give --crs and --offset",
                                 path)
            off = side[1] if side is not None else np.asarray(offset if offset is not None else (0, 0, 0), float)
            geom = read_obj_geometry(path, off, corners=True)
            frame = GeoFrame(crs_name(parse_crs(use_crs, path)), _origin_of(geom.bounds()), source=str(path))
            geom.vertices += -np.asarray(frame.origin)
            return ObjTexturedSurface(geom), frame
        return ObjTexturedSurface(read_obj_geometry(path, model_shift(path, frame, crs, offset), corners=True)), frame
    if frame is None:
        side = read_offset_sidecar(path)
        use_crs = side[0] if side is not None else crs
        if use_crs is None:
            raise GtkitError("mesh has no georeference: write a .offset.json sidecar or give --crs and --offset", path)
        off = side[1] if side is not None else np.asarray(offset if offset is not None else (0, 0, 0), float)
        if geometry_only:
            geom = read_obj_geometry(path, off)
            frame = GeoFrame(crs_name(parse_crs(use_crs, path)), _origin_of(geom.bounds()), source=str(path))
            geom.vertices += -np.asarray(frame.origin)
            return ObjMeshSurface(geom), frame
        raw = load_model(path, None, use_crs, off)
        frame = GeoFrame(crs_name(parse_crs(use_crs, path)), _origin_of(raw.bounds()), source=str(path))
        return MeshSurface(raw.translated(-np.asarray(frame.origin))), frame
    if geometry_only:
        return ObjMeshSurface(read_obj_geometry(path, model_shift(path, frame, crs, offset))), frame
    return MeshSurface(load_model(path, frame, crs, offset)), frame


def _vertex_coloured_obj(path: Path) -> bool:
    """Whether the first ``v`` line of an OBJ carries more than x y z (vertex colours: trimesh
    draws them, the numpy reader does not keep them). Reads until that line (the head of the file)."""
    with open(path, "rb") as fh:
        for line in fh:
            if line[:2] in (b"v ", b"v\t"):
                return len(line.split()) > 4
    return False


def _origin_of(xyz: np.ndarray) -> tuple[float, float, float]:
    lo = np.asarray(xyz).min(0)
    return tuple(float(math.floor(v)) for v in lo)


def stage_inputs(project, src: Path, crs: str | None, offset, out: Path, extra_files=()) -> dict:
    """What an export stage's output depends on besides its settings (its resume key);
    ``extra_files``: other files it reads (the reference block's poses for the DSM's gap fill)."""
    files = {str(p): file_fingerprint(p) for p in [*input_fingerprint_paths(src), *map(Path, extra_files)]}
    return {"source": str(src), "files": files,
            "crs": project.frame.crs_spec, "origin": list(project.frame.origin), "given_crs": crs,
            "given_offset": None if offset is None else list(map(float, offset)), "out": str(out)}


def run_raster_stage(project, settings, input, crs, offset, out, *, default_out: Path, stage: str,
                     make, label: str, textures: bool = True, extra_files=(), version: str | None = None) -> Path:
    """The body every raster export stage shares (DSM, orthophoto): the reference model (or
    ``input``) -> ``out`` (default ``default_out``) through ``make(source, frame, out, settings,
    name)``; skipped when the output exists and settings and inputs are unchanged. ``textures``:
    whether ``make`` needs the model's colours (see :func:`load_surface`); ``extra_files``: other
    files ``make`` reads, part of the resume key; ``version``: the method's version (a finished
    output of another version is made again)."""
    import logging

    from ..project import mark_stage_done, relative_paths, stage_done

    src = Path(input) if input is not None else reference_model(project.paths)
    out = Path(out) if out is not None else default_out
    stage_dir = project.paths.stage(stage)
    inputs = stage_inputs(project, src, crs, offset, out, extra_files)
    if version is not None:
        inputs["method_version"] = version
    if stage_done(stage_dir, settings, inputs) and out.is_file():  # stage_done first: it starts the clock and the log
        logging.getLogger(__name__).info("%s %s is up to date (settings unchanged); skipping", label, out)
        return out
    source, frame = load_surface(src, project.frame, crs, offset, textures=textures)
    # the source named in the GeoTIFF's tags and the record relative to the project (portable)
    summary = make(source, frame, out, settings, relative_paths(str(src), project.paths.root))
    mark_stage_done(stage_dir, settings, inputs, **summary)
    return out
