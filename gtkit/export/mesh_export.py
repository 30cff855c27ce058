"""The reference model as a textured mesh in the project CRS, for MeshLab, CAD and GIS tools.

Vertices are written as *CRS coordinates minus an offset* (whole metres in x/y, 0 in z, so
float32 readers keep millimetres), and the offset and CRS are written beside the mesh in
``<mesh>.offset.json`` (see :mod:`gtkit.io.mesh`): ``vertex + offset = CRS coordinates``.

Formats
    ``obj``  OBJ + MTL + one texture image per textured part (what photogrammetry tools deliver).
    ``glb``  binary glTF with the textures embedded. Axes stay x east, y north, z up (glTF's
             convention is y up: the sidecar says so; rotate on import if a viewer needs it).
    ``ply``  one binary PLY with per-vertex colours sampled from the texture (PLY has no
             standard texture reference), for point/mesh tools such as CloudCompare.

Optional decimation (``decimate`` = target triangle count) uses pymeshlab's quadric edge
collapse (the texture-preserving variant for textured parts), each part keeping its share.
"""
from __future__ import annotations

import logging
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from ..geo import crs_name
from ..io.atomic import atomic_path, write_json
from ..io.mesh import Mesh, MeshPart, load_model, read_mesh_file, sidecar_path, write_obj, write_offset_sidecar
from ..project import Project, mark_stage_done, relative_paths, settings_dict, stage_done
from .sources import reference_model, stage_inputs

log = logging.getLogger(__name__)

STAGE = "export_mesh"
FORMATS = ("obj", "ply", "glb")
MIN_PART = 100  # parts with fewer triangles are not decimated


@dataclass
class MeshExportSettings:
    format: str = "obj"            # obj | ply | glb
    decimate: int | None = None    # target number of triangles (pymeshlab); None = keep every triangle
    name: str = "model"            # file name stem inside exports/mesh/


def run(project: Project | str | Path, settings: MeshExportSettings,
        input: str | Path | None = None, crs: str | None = None, offset=None,
        out_dir: str | Path | None = None) -> Path:
    """Export the reference model (or ``input``) to ``exports/mesh/<name>.<format>`` + sidecar."""
    if settings.format not in FORMATS:
        raise GtkitError(f"unknown mesh format {settings.format!r} (choose {', '.join(FORMATS)})")
    if settings.decimate is not None and settings.decimate < 4:
        raise GtkitError(f"--decimate must be a triangle count >= 4, got {settings.decimate}")
    proj = project if isinstance(project, Project) else Project.load(project)
    src = Path(input) if input is not None else reference_model(proj.paths)
    out_dir = Path(out_dir) if out_dir is not None else proj.paths.mesh_export
    out = out_dir / f"{settings.name}.{settings.format}"
    stage_dir = proj.paths.stage(f"{STAGE}_{settings.format}")
    inputs = stage_inputs(proj, src, crs, offset, out)
    if stage_done(stage_dir, settings, inputs) and out.is_file():  # stage_done first: it starts the clock and the log
        log.info("mesh %s is up to date (settings unchanged); skipping", out)
        return out
    mesh = load_model(src, proj.frame, crs, offset)  # world frame; CRS checked against the project
    n_in = mesh.n_triangles
    if settings.decimate is not None and settings.decimate < n_in:
        mesh = decimate(mesh, settings.decimate)
    file_offset = np.array([math.floor(proj.frame.origin[0]), math.floor(proj.frame.origin[1]), 0.0])
    stored = mesh.translated(np.asarray(proj.frame.origin) - file_offset)
    write_mesh(out, stored, settings.format)
    write_offset_sidecar(out, crs_name(proj.frame.crs), file_offset)
    _annotate_sidecar(out, settings.format, relative_paths(str(src), proj.paths.root))  # relative inside the project
    mark_stage_done(stage_dir, settings, inputs, path=str(out), triangles_in=n_in, triangles_out=mesh.n_triangles,
                    offset=file_offset.tolist(), crs=crs_name(proj.frame.crs), settings_used=settings_dict(settings))
    log.info("mesh %s: %d triangles (from %d), offset %s in %s", out, mesh.n_triangles, n_in,
             file_offset.tolist(), crs_name(proj.frame.crs))
    return out


def _annotate_sidecar(out: Path, fmt: str, source: str) -> None:
    import json

    p = sidecar_path(out)
    d = json.loads(p.read_text())
    d["axes"] = "x east, y north, z up (metres)" + (" -- not glTF's y-up" if fmt == "glb" else "")
    d["source"] = source
    if not Path(source).is_absolute():
        d["source_relative_to"] = "the project folder"
    write_json(p, d)


def write_mesh(path: Path, mesh: Mesh, fmt: str) -> Path:
    """Write ``mesh`` (coordinates as they should appear in the file) as obj, ply or glb."""
    if fmt == "obj":
        # textured parts first: trimesh's OBJ reader (maintain_order=True, as gtkit.io.mesh uses it)
        # drops the uv of a textured part that follows untextured ones
        textured = [p for p in mesh.parts if p.texture is not None and p.uv is not None]
        return write_obj(path, Mesh(textured + [p for p in mesh.parts if not any(p is q for q in textured)]))
    import trimesh

    if fmt == "ply":
        verts, faces, cols, off = [], [], [], 0
        for p in mesh.parts:
            verts.append(p.vertices)
            faces.append(p.faces + off)
            cols.append(vertex_colors(p))
            off += len(p.vertices)
        tm = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces),
                             vertex_colors=np.concatenate(cols), process=False)
        with atomic_path(path) as tmp:
            tm.export(str(tmp), file_type="ply", encoding="binary")
        return path
    if fmt == "glb":
        scene = trimesh.Scene()
        for i, p in enumerate(mesh.parts):
            if p.texture is not None and p.uv is not None:
                mat = trimesh.visual.material.PBRMaterial(baseColorTexture=_jpeg_image(p.texture),
                                                          metallicFactor=0.0, roughnessFactor=1.0)
                vis = trimesh.visual.TextureVisuals(uv=p.uv, material=mat)
            else:
                vis = trimesh.visual.ColorVisuals(vertex_colors=vertex_colors(p))
            tm = trimesh.Trimesh(p.vertices, p.faces, visual=vis, process=False)
            scene.add_geometry(tm, geom_name=p.name or f"part_{i:03d}")
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(scene.export(file_type="glb"))
        return path
    raise GtkitError(f"unknown mesh format {fmt!r}", path)


def _jpeg_image(texture: np.ndarray):
    """A PIL image that trimesh embeds as JPEG (it writes PNG for anything else: 5-10x slower and
    larger for photo textures)."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(texture).save(buf, format="JPEG", quality=92)
    buf.seek(0)
    return Image.open(buf)


def vertex_colors(part: MeshPart) -> np.ndarray:
    """(N, 3) uint8 per-vertex colours: the part's own, or its texture sampled (bilinear) at the uv."""
    if part.texture is not None and part.uv is not None:
        tex = part.texture.astype(np.float32)
        th, tw = tex.shape[:2]
        u = np.clip((part.uv[:, 0] % 1.0) * tw - 0.5, 0, tw - 1)
        v = np.clip((1.0 - part.uv[:, 1] % 1.0) * th - 0.5, 0, th - 1)  # uv's v is up, row 0 is the top
        c0, r0 = np.minimum(u.astype(np.int64), tw - 2 if tw > 1 else 0), np.minimum(v.astype(np.int64), th - 2 if th > 1 else 0)
        c1, r1 = np.minimum(c0 + 1, tw - 1), np.minimum(r0 + 1, th - 1)
        fu, fv = (u - c0)[:, None], (v - r0)[:, None]
        c = ((1 - fv) * ((1 - fu) * tex[r0, c0] + fu * tex[r0, c1]) + fv * ((1 - fu) * tex[r1, c0] + fu * tex[r1, c1]))
        return np.clip(np.rint(c), 0, 255).astype(np.uint8)
    if part.colors is not None:
        return part.colors.astype(np.uint8)
    return np.full((len(part.vertices), 3), 180, np.uint8)


def decimate(mesh: Mesh, target_triangles: int) -> Mesh:
    """Quadric edge-collapse decimation with pymeshlab to about ``target_triangles`` in total.
    Parts under ``MIN_PART`` triangles (a box, a sign) are kept whole; the others share the rest
    of the budget by their size. Textured parts keep their texture and uv."""
    import pymeshlab

    small = sum(len(p.faces) for p in mesh.parts if len(p.faces) < MIN_PART)
    big = mesh.n_triangles - small
    budget = max(target_triangles - small, 4)
    parts = []
    with tempfile.TemporaryDirectory(prefix="gtkit_decimate_") as d:
        for i, p in enumerate(mesh.parts):
            want = max(MIN_PART // 2, int(round(budget * len(p.faces) / max(big, 1))))
            if len(p.faces) < MIN_PART or want >= len(p.faces):
                parts.append(p)
                continue
            centre = p.vertices.mean(0)  # decimate near the origin: pymeshlab's OBJ text keeps 4 decimals
            src = Path(d) / f"in_{i}.obj"
            local = MeshPart(p.vertices - centre, p.faces, p.uv, p.texture, p.colors, None, p.name)
            write_obj(src, Mesh([local]))
            ms = pymeshlab.MeshSet()
            ms.load_new_mesh(str(src))
            textured = p.texture is not None and p.uv is not None
            try:
                if textured:
                    ms.meshing_decimation_quadric_edge_collapse_with_texture(targetfacenum=want,
                                                                             preserveboundary=True)
                    dst = Path(d) / f"out_{i}.obj"
                else:
                    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=want, preserveboundary=True,
                                                                preservenormal=True)
                    dst = Path(d) / f"out_{i}.ply"
                ms.save_current_mesh(str(dst))
            except pymeshlab.PyMeshLabException as e:
                raise GtkitError(f"pymeshlab decimation failed on part {p.name or i}: {e}") from None
            for q in read_mesh_file(dst).parts:
                parts.append(MeshPart(q.vertices + centre, q.faces, q.uv, q.texture, q.colors, None, p.name))
    out = Mesh(parts)
    if out.n_triangles > 1.2 * target_triangles:
        log.warning("decimation stopped at %d triangles (asked %d): texture seams and small parts are kept",
                    out.n_triangles, target_triangles)
    return out
