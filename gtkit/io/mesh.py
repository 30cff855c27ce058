"""Meshes: loading OBJ+MTL / PLY / GLB into gtkit's plain mesh type, and the offset sidecar.

A mesh file stores vertices as *CRS coordinates minus an offset* (like OpenDroneMap's
UTM-minus-offset OBJ). The offset and the CRS live in a sidecar JSON beside the mesh,
``<mesh file>.offset.json``::

    {"crs": "EPSG:32650", "offset": [500000.0, 4000000.0, 0.0],
     "note": "vertex + offset = coordinates in crs (metres)"}

Without a sidecar a mesh is assumed to be in the project's world frame already only when
the caller says so; see :func:`load_model`.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from .atomic import write_json
from .mesh_parts import Mesh, MeshPart  # noqa: F401 (gtkit's mesh types, named here as before)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")


def sidecar_path(mesh_path: Path) -> Path:
    return Path(str(mesh_path) + ".offset.json")


def write_offset_sidecar(mesh_path: Path, crs: str, offset) -> Path:
    return write_json(sidecar_path(mesh_path), {
        "crs": crs, "offset": [float(v) for v in offset],
        "note": "vertex + offset = coordinates in crs (metres); z is height as given"})


def read_offset_sidecar(mesh_path: Path) -> tuple[str, np.ndarray] | None:
    p = sidecar_path(Path(mesh_path))
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text())
        off = np.array(d["offset"], dtype=np.float64)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise ValueError("offset must be three finite numbers")
        return str(d["crs"]), off
    except (json.JSONDecodeError, KeyError, ValueError, TypeError) as e:
        raise GtkitError(f"invalid offset sidecar ({e})", p) from None


def _part_from_trimesh(g, name: str) -> MeshPart:
    import trimesh

    v = np.asarray(g.vertices, dtype=np.float64)
    f = np.asarray(g.faces, dtype=np.int64)
    vis = g.visual
    if isinstance(vis, trimesh.visual.texture.TextureVisuals):
        mat = vis.material
        img = getattr(mat, "image", None)
        if img is None:
            img = getattr(mat, "baseColorTexture", None)
        if img is not None and vis.uv is not None:
            tex = np.asarray(img.convert("RGB"))
            return MeshPart(v, f, uv=np.asarray(vis.uv, dtype=np.float64), texture=tex, name=name)
        rgb = getattr(mat, "diffuse", None)
        if rgb is None:
            rgb = getattr(mat, "main_color", (180, 180, 180, 255))
        return MeshPart(v, f, colors=np.tile(np.asarray(rgb)[:3].astype(np.uint8), (len(v), 1)), name=name)
    colors = None
    if getattr(vis, "kind", None) is not None and hasattr(vis, "vertex_colors"):
        colors = np.asarray(vis.vertex_colors)[:, :3].astype(np.uint8)
    if colors is None or len(colors) != len(v):
        colors = np.full((len(v), 3), 180, np.uint8)
    return MeshPart(v, f, colors=colors, name=name)


def read_mesh_file(path: str | Path) -> Mesh:
    """Load a mesh file as it is stored (no offset applied). Clear error if it is not a mesh."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise GtkitError("mesh file not found", path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise GtkitError(f"not a mesh file (expected one of {', '.join(MESH_SUFFIXES)})", path)
    try:
        with warnings.catch_warnings():  # trimesh's texture code warns on untextured parts
            warnings.simplefilter("ignore", RuntimeWarning)
            loaded = trimesh.load(str(path), process=False, maintain_order=True)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types; all mean "unreadable"
        raise GtkitError(f"not a readable mesh ({type(e).__name__}: {str(e)[:120]})", path) from None
    if isinstance(loaded, trimesh.Scene) and len(loaded.geometry) > 1 and path.suffix.lower() == ".obj":
        # trimesh 4/5 with maintain_order=True drops the uv of every OBJ object/material after the
        # first (its faces index the file's global vertex list); load multi-part OBJs without it
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            loaded = trimesh.load(str(path), process=False, maintain_order=False)
    if isinstance(loaded, trimesh.Scene):
        geoms = []
        for node in loaded.graph.nodes_geometry:
            T, gname = loaded.graph[node]
            g = loaded.geometry[gname]
            geoms.append((gname, g if np.allclose(T, np.eye(4)) else g.copy().apply_transform(T)))
    else:
        geoms = [(path.stem, loaded)]
    mesh = Mesh([_part_from_trimesh(g, n) for n, g in geoms
                 if isinstance(g, trimesh.Trimesh) and len(g.faces)])
    if not mesh.parts:
        raise GtkitError("file holds no triangles", path)
    return mesh


def load_model(path: str | Path, frame=None, crs: str | None = None, offset=None) -> Mesh:
    """Load a mesh into the project's world frame.

    The offset and CRS come from the sidecar, or from ``crs``/``offset`` (command line). With a
    ``frame`` (:class:`gtkit.geo.GeoFrame`), a CRS different from the project's is an error and
    the project's origin is subtracted. Without a frame the mesh is returned as stored + offset.
    """
    shift = model_shift(path, frame, crs, offset)
    mesh = read_mesh_file(path)
    return mesh if shift is None else mesh.translated(shift)


def model_parts(path: str | Path, frame=None, crs: str | None = None, offset=None):
    """The parts :func:`load_model` gives, one after another, in bounded memory for an OBJ.

    An OBJ is read by :func:`gtkit.io.obj_geometry.read_obj_geometry` (numpy, 16 MB at a time;
    each corner's uv and each triangle's material kept) and its parts are yielded one per
    material, each texture decoded when its part is yielded, so a renderer that uploads them
    (:meth:`gtkit.render.renderer.Renderer.add_parts`) never holds more than one decoded texture
    besides what it has uploaded. trimesh (:func:`load_model`) parses a multi-part OBJ twice and
    holds every texture: it passed 8 GB on a 5.4 M-triangle, 650-texture OBJ. Other formats go
    through :func:`load_model`, and so does an OBJ with vertex colours (``v x y z r g b``), which
    the numpy reader does not keep. The file is read (and its errors raised) at the call."""
    path = Path(path)
    if path.suffix.lower() == ".obj":
        from .obj_geometry import read_obj_geometry

        geom = read_obj_geometry(path, model_shift(path, frame, crs, offset), corners=True)
        if not geom.vertex_extras:
            return geom.parts()
        del geom
    return iter(load_model(path, frame, crs, offset).parts)


def model_shift(path: str | Path, frame=None, crs: str | None = None, offset=None) -> np.ndarray | None:
    """What :func:`load_model` adds to the stored vertices (None: nothing), checking the CRS."""
    path = Path(path)
    side = read_offset_sidecar(path)
    if side is not None:
        crs, offset = side
    if frame is None:
        return None if offset is None else np.asarray(offset, float)
    if crs is None:
        raise GtkitError("mesh has no georeference: write a .offset.json sidecar or give --crs and --offset",
                         path)
    from ..geo import parse_crs

    if not parse_crs(crs, path).equals(frame.crs):
        raise GtkitError(f"mesh CRS {crs} does not match the project CRS {frame.crs_spec}", path)
    return np.asarray(offset if offset is not None else (0, 0, 0), float) - np.asarray(frame.origin)


def write_obj(path: str | Path, mesh: Mesh, texture_format: str = "jpg") -> Path:
    """Write an OBJ + MTL + one texture per textured part, atomically (files renamed last)."""
    from .atomic import write_image, write_text

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mtl_name = path.with_suffix(".mtl").name
    lines = [f"mtllib {mtl_name}"]
    mtl = []
    vo = to = 0
    # textured parts first: trimesh's OBJ reader drops the uv of a textured part that follows
    # an untextured one in the same file
    ordered = sorted(mesh.parts, key=lambda p: not (p.uv is not None and p.texture is not None))
    for i, p in enumerate(ordered):
        mat = f"material_{i:03d}"
        lines.append(f"o {p.name or mat}")
        lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in p.vertices]
        if p.uv is not None and p.texture is not None:
            tex_name = f"{path.stem}_{i:03d}.{texture_format}"
            write_image(path.parent / tex_name, p.texture)
            mtl += [f"newmtl {mat}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "d 1", "illum 1", f"map_Kd {tex_name}", ""]
            lines += [f"vt {u:.6f} {v:.6f}" for u, v in p.uv]
            lines.append(f"usemtl {mat}")
            f = p.faces + 1
            lines += [f"f {a + vo}/{a + to} {b + vo}/{b + to} {c + vo}/{c + to}" for a, b, c in f]
            to += len(p.uv)
        else:
            # OBJ has no per-vertex colour with materials: a colour-only part keeps its mean
            # colour as the material's diffuse colour (use PLY for per-vertex colours)
            rgb = (p.colors.mean(0) / 255.0) if p.colors is not None else np.full(3, 0.7)
            mtl += [f"newmtl {mat}", "Kd {:.4f} {:.4f} {:.4f}".format(*rgb), ""]
            lines.append(f"usemtl {mat}")
            lines += [f"f {a + vo} {b + vo} {c + vo}" for a, b, c in p.faces + 1]
        vo += len(p.vertices)
    write_text(path.with_suffix(".mtl"), "\n".join(mtl) + "\n")
    write_text(path, "\n".join(lines) + "\n")
    return path
