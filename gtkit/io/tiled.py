"""Tiled textured OBJ models as ContextCapture / Smart3D deliver them: read lazily, and write.

Layout (what ContextCapture's "OBJ, regular tiling" export writes)::

    model/
      metadata.xml                 <ModelMetadata><SRS>EPSG:32650</SRS><SRSOrigin>x,y,z</SRSOrigin>
      Data/Tile_+000_+000/Tile_+000_+000.obj (+ .mtl + textures)
      Data/Tile_+001_+000/...
      tiles_index.json             gtkit's spatial index (optional; written by :func:`write_tiled`)

A vertex ``v`` of any tile is at ``v + SRSOrigin`` in the SRS. The SRS may be ``EPSG:n``, WKT,
a PROJ string or ``ENU:lat,lon`` (see :mod:`gtkit.io.srs`). Tiles may also sit directly under
the model folder (no ``Data/``). When a tile folder holds an LOD pyramid (``..._L18_0.obj``),
the finest level is used.

Loading is lazy: :func:`read_tiled` only builds the spatial index (each tile's bounding box,
from ``tiles_index.json`` when its recorded file sizes still match, otherwise from a fast scan
of the ``v`` lines); :meth:`TiledModel.load_tile` reads one tile into the project's world frame
when a view or a raster cell needs it.

A tile folder may repeat the SRS in its own ``metadata.xml`` (or ``<tile>.xml``) or in a gtkit
offset sidecar (``<tile>.obj.offset.json``); a tile that disagrees with the model's SRS or
origin is an error naming that file.
"""
from __future__ import annotations

import json
import logging
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from .atomic import write_image, write_json, write_text
from .mesh import Mesh, MeshPart, read_mesh_file, read_offset_sidecar
from .srs import SrsToWorld, srs_key

log = logging.getLogger(__name__)

METADATA = "metadata.xml"
INDEX = "tiles_index.json"
INDEX_VERSION = 1
_TILE_DIR = re.compile(r"^Tile_[-+]\d+_[-+]\d+")
_LOD = re.compile(r"_L(\d+)(?:_\d+)?$")
_V_LINE = re.compile(rb"^v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)", re.MULTILINE)


def is_tiled(path: Path) -> bool:
    """A tiled model is given as its folder or its ``metadata.xml``."""
    path = Path(path)
    return path.is_dir() or path.name == METADATA


# --- metadata.xml ---------------------------------------------------------------------------

def read_metadata(path: str | Path) -> tuple[str, np.ndarray]:
    """(SRS definition, SRSOrigin) of a ``metadata.xml``; clear errors when unusable."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("metadata.xml not found (a tiled model needs one giving its SRS)", path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise GtkitError(f"not valid XML ({e})", path) from None
    srs = (root.findtext("SRS") or "").strip()
    if not srs:
        raise GtkitError("no <SRS> element: the model's spatial reference is unknown", path)
    text = (root.findtext("SRSOrigin") or "0,0,0").strip()
    try:
        origin = np.array([float(v) for v in re.split(r"[,\s]+", text) if v], dtype=np.float64)
    except ValueError:
        raise GtkitError(f"<SRSOrigin> is not three numbers: {text!r}", path) from None
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise GtkitError(f"<SRSOrigin> is not three finite numbers: {text!r}", path)
    return srs, origin


def write_metadata(path: str | Path, srs: str, origin) -> Path:
    o = ",".join(repr(float(v)) for v in origin)
    return write_text(path, '<?xml version="1.0" encoding="utf-8"?>\n<ModelMetadata version="1">\n'
                      f"\t<!--Spatial Reference System-->\n\t<SRS>{_xml_escape(srs)}</SRS>\n"
                      f"\t<!--Origin in Spatial Reference System-->\n\t<SRSOrigin>{o}</SRSOrigin>\n"
                      "\t<Texture>\n\t\t<ColorSource>Visible</ColorSource>\n\t</Texture>\n"
                      "</ModelMetadata>\n")


def _xml_escape(s: str) -> str:
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


# --- the index -------------------------------------------------------------------------------

@dataclass
class TileInfo:
    name: str
    files: list[Path]             # OBJ files of this tile (one, or the finest LOD level's pieces)
    stored_bounds: np.ndarray     # (2, 3) as stored in the files (SRS minus SRSOrigin)
    bounds: np.ndarray            # (2, 3) in the project's world frame
    size: int                     # bytes of the OBJ files (cache key)


def find_tile_files(root: Path) -> dict[str, list[Path]]:
    """Tile name -> its OBJ files, for ``root/Data/Tile_*`` or ``root/Tile_*``."""
    base = root / "Data" if (root / "Data").is_dir() else root
    out: dict[str, list[Path]] = {}
    for d in sorted(p for p in base.iterdir() if p.is_dir() and _TILE_DIR.match(p.name)):
        objs = sorted(d.glob("*.obj"))
        if not objs:
            continue
        own = [p for p in objs if p.stem in (d.name, d.name + "_c")]
        if own:
            out[d.name] = own
            continue
        levels = {p: int(m.group(1)) for p in objs if (m := _LOD.search(p.stem))}
        if levels:
            best = max(levels.values())
            out[d.name] = [p for p, lv in levels.items() if lv == best]
        else:
            out[d.name] = objs
    return out


def scan_obj_bounds(path: Path) -> np.ndarray:
    """(2, 3) bounds of the ``v`` lines of an OBJ, without parsing faces or materials."""
    data = Path(path).read_bytes()
    vals = _V_LINE.findall(data)
    if not vals:
        raise GtkitError("OBJ file has no vertices", path)
    try:
        v = np.array(vals, dtype=np.float64)
    except ValueError:
        raise GtkitError("OBJ file has unreadable vertex lines", path) from None
    return np.stack([v.min(0), v.max(0)])


def _box_corners(b: np.ndarray) -> np.ndarray:
    return np.array([[x, y, z] for x in b[:, 0] for y in b[:, 1] for z in b[:, 2]])


class TiledModel:
    """A tiled model: its SRS mapping into the project frame and a spatial index of its tiles."""

    def __init__(self, root: Path, srs: str, srs_origin: np.ndarray, tiles: list[TileInfo], to_world: SrsToWorld):
        self.root = Path(root)
        self.srs = srs
        self.srs_origin = srs_origin
        self.tiles = {t.name: t for t in tiles}
        self.to_world = to_world

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def names(self) -> list[str]:
        return sorted(self.tiles)

    def bounds(self) -> np.ndarray:
        b = np.stack([t.bounds for t in self.tiles.values()])
        return np.stack([b[:, 0].min(0), b[:, 1].max(0)])

    def tiles_in_box(self, lo, hi) -> list[str]:
        """Tiles whose world bounding box meets the box [lo, hi] (2 or 3 coordinates)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        k = len(lo)
        return [n for n, t in sorted(self.tiles.items())
                if np.all(t.bounds[0, :k] <= hi) and np.all(t.bounds[1, :k] >= lo)]

    def load_tile(self, name: str, textures: bool = True) -> Mesh:
        """One tile as a :class:`Mesh` in the project's world frame; ``textures=False``: its
        triangles only (:func:`gtkit.io.obj_geometry.read_obj_geometry`, one part a file)."""
        t = self.tiles[name]
        parts = []
        for f in t.files:
            if not textures:
                from .obj_geometry import read_obj_geometry

                g = read_obj_geometry(f)
                parts.append(MeshPart(self.to_world.points(g.vertices), g.faces, name=f"{name}/{f.stem}"))
                continue
            m = read_mesh_file(f)
            for p in m.parts:
                p.vertices = self.to_world.points(p.vertices)
                p.name = f"{name}/{p.name}"
                parts.append(p)
        return Mesh(parts)

    def load_all(self, names=None) -> Mesh:
        """Every tile (or the named ones) as one mesh; for small models and tests."""
        parts = []
        for n in (self.names if names is None else names):
            parts += self.load_tile(n).parts
        return Mesh(parts)


def _check_tile_srs(tile_dir: Path, files: list[Path], srs: str, origin: np.ndarray, key: str) -> None:
    """Tiles that declare their own SRS must agree with the model's."""
    for meta in [tile_dir / METADATA, tile_dir / f"{tile_dir.name}.xml"]:
        if not meta.is_file():
            continue
        try:
            root = ET.parse(meta).getroot()
        except ET.ParseError as e:
            raise GtkitError(f"not valid XML ({e})", meta) from None
        if root.tag != "ModelMetadata" or root.find("SRS") is None:
            continue
        t_srs, t_origin = read_metadata(meta)
        if srs_key(t_srs) != key or not np.allclose(t_origin, origin, rtol=0, atol=1e-6):
            raise GtkitError(f"tile SRS {t_srs} origin {t_origin.tolist()} is inconsistent with the model's "
                             f"{srs} origin {origin.tolist()}", meta)
    for f in files:
        side = read_offset_sidecar(f)
        if side is None:
            continue
        s_crs, s_off = side
        if srs_key(s_crs) != key or not np.allclose(s_off, origin, rtol=0, atol=1e-6):
            raise GtkitError(f"tile SRS {s_crs} offset {s_off.tolist()} is inconsistent with the model's "
                             f"{srs} origin {origin.tolist()}", str(f) + ".offset.json")


def read_tiled(path: str | Path, frame, index_path: str | Path | None = None,
               write_index: bool = False) -> TiledModel:
    """Open a tiled model (folder or its ``metadata.xml``) for the project ``frame``.

    Only the index is built: bounds come from ``index_path`` (default ``<model>/tiles_index.json``)
    when its recorded sizes match the files, otherwise from scanning each OBJ's vertex lines;
    with ``write_index`` the scan result is saved to ``index_path`` for the next time.
    """
    path = Path(path)
    root = path.parent if path.is_file() else path
    meta = root / METADATA
    srs, origin = read_metadata(meta)
    try:
        key = srs_key(srs)
    except GtkitError:
        raise GtkitError(f"SRS cannot be understood: {srs[:120]!r} (expected EPSG:n, WKT, a PROJ string "
                         "or ENU:lat,lon)", meta) from None
    to_world = SrsToWorld(srs, frame, origin, source=meta)
    files = find_tile_files(root)
    if not files:
        raise GtkitError("no Tile_* folders with OBJ files", root)
    index_path = Path(index_path) if index_path else root / INDEX
    cached = {}
    if index_path.is_file():
        try:
            d = json.loads(index_path.read_text())
            if d.get("version") == INDEX_VERSION:
                cached = d.get("tiles", {})
        except json.JSONDecodeError:
            cached = {}
    tiles, scanned = [], False
    for name, objs in files.items():
        _check_tile_srs(objs[0].parent, objs, srs, origin, key)
        size = sum(f.stat().st_size for f in objs)
        c = cached.get(name)
        if c and c.get("size") == size and c.get("files") == [f.name for f in objs]:
            sb = np.array(c["bounds"], dtype=np.float64)
        else:
            bs = np.stack([scan_obj_bounds(f) for f in objs])
            sb = np.stack([bs[:, 0].min(0), bs[:, 1].max(0)])
            scanned = True
        if to_world.is_translation:
            wb = sb + to_world.shift
        else:
            w = to_world.points(_box_corners(sb))
            pad = 1e-3 * max(1.0, float(np.ptp(w, 0).max()))  # the map is not exactly affine
            wb = np.stack([w.min(0) - pad, w.max(0) + pad])
        tiles.append(TileInfo(name, objs, sb, wb, size))
    if scanned and write_index:
        _write_index(index_path, srs, origin, tiles)
    return TiledModel(root, srs, origin, tiles, to_world)


def _write_index(path: Path, srs: str, origin, tiles: list[TileInfo]) -> None:
    write_json(path, {"version": INDEX_VERSION, "srs": srs, "srs_origin": [float(v) for v in origin],
                      "note": "bounds as stored in the OBJ files (add srs_origin for SRS coordinates)",
                      "tiles": {t.name: {"files": [f.name for f in t.files], "size": t.size,
                                         "bounds": t.stored_bounds.tolist()} for t in tiles}})


# --- writer ----------------------------------------------------------------------------------

def tile_name(ix: int, iy: int) -> str:
    return f"Tile_{ix:+04d}_{iy:+04d}"


def _crop_window(lo: float, hi: float, size: int, align: int, margin: int) -> tuple[int, int]:
    a = max(0, int(math.floor((lo - margin) / align)) * align)
    b = min(size, int(math.ceil((hi + margin) / align)) * align)
    if b <= a:
        a, b = max(0, min(a, size - 1)), min(size, max(a, 0) + 1)
    return a, b


def _split_part(p: MeshPart, fi: np.ndarray, texture: str, align: int, margin: int) -> MeshPart:
    """The faces ``fi`` of part ``p`` as a self-contained part (texture cropped on request)."""
    faces = p.faces[fi]
    used, inv = np.unique(faces, return_inverse=True)
    faces = inv.reshape(-1, 3)
    sub = MeshPart(p.vertices[used], faces, name=p.name)
    if p.colors is not None:
        sub.colors = p.colors[used]
    if p.material is not None:
        sub.material = p.material[used]
    if p.uv is not None and p.texture is not None:
        uv = p.uv[used].astype(np.float64)
        tex = p.texture
        if texture == "crop":
            H, W = tex.shape[:2]
            px = uv[:, 0] * W
            py = (1.0 - uv[:, 1]) * H  # from the top row
            x0, x1 = _crop_window(px.min(), px.max(), W, align, margin)
            y0, y1 = _crop_window(py.min(), py.max(), H, align, margin)
            if (x0, x1, y0, y1) != (0, W, 0, H):
                tex = tex[y0:y1, x0:x1]
                uv = np.stack([(px - x0) / (x1 - x0), 1.0 - (py - y0) / (y1 - y0)], -1)
        sub.uv, sub.texture = uv, tex
        if texture == "pack":
            from .texture_atlas import pack_charts

            sub = pack_charts(sub)
    return sub


def _fmt_rows(a: np.ndarray, prefix: str) -> list[str]:
    return [prefix + " ".join(repr(float(x)) for x in row) for row in a]


def _write_obj_file(path: Path, parts: list[MeshPart], texture_format: str, tag: str) -> None:
    """One OBJ (+ MTL) for parts that are all textured or uniformly coloured (materials), or
    all per-vertex coloured (no materials: trimesh drops vertex colours once a material exists)."""
    per_vertex = all(p.uv is None or p.texture is None for p in parts) and any(
        p.colors is not None and len(np.unique(p.colors, axis=0)) > 1 for p in parts)
    lines, mtl = ([] if per_vertex else [f"mtllib {path.stem}.mtl"]), []
    # textured parts first: trimesh's OBJ reader handles faces with vt then faces without, not the reverse
    parts = sorted(parts, key=lambda p: not (p.uv is not None and p.texture is not None))
    vo = to = 0
    for i, p in enumerate(parts):
        mat = f"{tag}_m{i:02d}"
        lines.append(f"o {mat}")
        if per_vertex:
            c = np.asarray(p.colors if p.colors is not None else np.full((len(p.vertices), 3), 180), np.float64) / 255
            lines += [f"v {x!r} {y!r} {z!r} {r:.9f} {g:.9f} {b:.9f}"
                      for (x, y, z), (r, g, b) in zip(p.vertices.tolist(), c.tolist())]
            lines += [f"f {a + vo} {b + vo} {c + vo}" for a, b, c in (p.faces + 1).tolist()]
            vo += len(p.vertices)
            continue
        lines += _fmt_rows(p.vertices, "v ")
        if p.uv is not None and p.texture is not None:
            tex_name = f"{mat}.{texture_format}"
            write_image(path.parent / tex_name, p.texture)
            mtl += [f"newmtl {mat}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "d 1", "illum 1", f"map_Kd {tex_name}", ""]
            lines += _fmt_rows(p.uv, "vt ")
            lines.append(f"usemtl {mat}")
            f = p.faces + 1
            lines += [f"f {a + vo}/{a + to} {b + vo}/{b + to} {c + vo}/{c + to}" for a, b, c in f.tolist()]
            to += len(p.uv)
        else:
            rgb = (np.asarray(p.colors[0], np.float64) / 255 if p.colors is not None and len(p.colors)
                   else np.full(3, 180 / 255))
            mtl += [f"newmtl {mat}", "Kd " + " ".join(f"{c:.9f}" for c in rgb), ""]
            lines.append(f"usemtl {mat}")
            lines += [f"f {a + vo} {b + vo} {c + vo}" for a, b, c in (p.faces + 1).tolist()]
        vo += len(p.vertices)
    if mtl:
        write_text(path.with_suffix(".mtl"), "\n".join(mtl) + "\n")
    write_text(path, "\n".join(lines) + "\n")


def _write_tile(tile_dir: Path, name: str, parts: list[MeshPart], texture_format: str) -> list[Path]:
    """``<name>.obj`` for textured / uniformly coloured parts, ``<name>_c.obj`` for per-vertex colours."""
    tile_dir.mkdir(parents=True, exist_ok=True)

    def per_vertex(p):
        return (p.uv is None or p.texture is None) and p.colors is not None and len(np.unique(p.colors, axis=0)) > 1

    out = []
    for suffix, group in (("", [p for p in parts if not per_vertex(p)]), ("_c", [p for p in parts if per_vertex(p)])):
        if group:
            path = tile_dir / f"{name}{suffix}.obj"
            _write_obj_file(path, group, texture_format, f"{name}{suffix}")
            out.append(path)
    return out


def write_tiled(mesh: Mesh, out_dir: str | Path, crs: str, offset=(0.0, 0.0, 0.0), tile_size: float = 100.0,
                *, texture: str = "crop", texture_format: str = "png", align: int = 64, margin: int = 64,
                grid_origin=(0.0, 0.0)) -> Path:
    """Split ``mesh`` into ``Tile_+XXX_+YYY`` OBJ tiles under ``out_dir`` with ``metadata.xml``.

    ``mesh`` vertices + ``offset`` are coordinates in ``crs`` (for a mesh in a project's world
    frame: ``crs = frame.crs_spec``, ``offset = frame.origin``); the tiles store the vertices
    unchanged (printed with round-trip precision) and ``SRSOrigin = offset``. Each triangle goes
    to the tile holding its centroid, on a grid of ``tile_size`` metres from ``grid_origin``
    (stored coordinates). ``texture="crop"`` gives each tile only the part of each texture its
    triangles use (aligned to ``align`` texels, ``margin`` texels of context), so a tile's memory
    is its own; ``"share"`` keeps whole textures (more memory and disk); ``"pack"`` gives each tile
    a page of just the charts its triangles use (:func:`gtkit.io.texture_atlas.pack_charts`: for
    textures whose faces are scattered, as a photo-built model's are).

    Fidelity (measured, see tests/test_import_tiled.py and the issue-9 report): geometry and depth
    render bit-identically in both modes (with ``TileStreamer``'s shared upload origin); colours are
    bit-identical with ``"share"``. With ``"crop"`` colours are bit-identical too when the
    renderer samples with anisotropy 1 (checked, trilinear, magnified and minified); with the
    renderer's 8x anisotropic filtering, Mesa llvmpipe samples non-power-of-two textures in a
    size-dependent way, so some pixels differ (99.9 % identical on power-of-two source textures,
    ~96-98 % on the sample site's 1000 px texture, up to a few tens of grey levels on
    high-frequency texture). Textures are written losslessly (PNG) unless ``texture_format``
    says otherwise.
    Returns the output folder.
    """
    if texture not in ("crop", "share", "pack"):
        raise GtkitError(f"texture mode must be 'crop', 'share' or 'pack', got {texture!r}")
    if not (tile_size > 0):
        raise GtkitError(f"tile size must be positive, got {tile_size}")
    from ..geo import parse_crs

    parse_crs(crs)
    out = Path(out_dir)
    data = out / "Data"
    data.mkdir(parents=True, exist_ok=True)
    g = np.asarray(grid_origin, dtype=np.float64)
    groups: dict[tuple[int, int], list[MeshPart]] = {}
    for p in mesh.parts:
        if not len(p.faces):
            continue
        cen = p.vertices[p.faces].mean(1)
        ij = np.floor((cen[:, :2] - g) / tile_size).astype(np.int64)
        keys, inv = np.unique(ij, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        for k, key in enumerate(keys):
            fi = np.nonzero(inv == k)[0]
            groups.setdefault((int(key[0]), int(key[1])), []).append(_split_part(p, fi, texture, align, margin))
    tiles = []
    for (ix, iy), parts in sorted(groups.items()):
        name = tile_name(ix, iy)
        if abs(ix) > 999 or abs(iy) > 999:
            raise GtkitError(f"tile index {ix},{iy} needs more than 3 digits: use a larger tile size")
        objs = _write_tile(data / name, name, parts, texture_format)
        v = np.concatenate([p.vertices for p in parts])
        tiles.append(TileInfo(name, objs, np.stack([v.min(0), v.max(0)]), None, sum(f.stat().st_size for f in objs)))
    _write_index(out / INDEX, crs, offset, tiles)
    write_metadata(out / METADATA, crs, offset)
    return out


def tile_model_file(mesh_path: str | Path, out_dir: str | Path, frame=None, tile_size: float = 100.0, **kw) -> Path:
    """Write a georeferenced mesh file (``<mesh>.offset.json`` sidecar, e.g. a sample site's
    ``model/reference.obj``) as a tiled model. With a project ``frame`` the tiles are in the
    project's CRS with ``SRSOrigin`` = its origin; without one, in the sidecar's CRS and offset."""
    from .mesh import load_model

    mesh_path = Path(mesh_path)
    if frame is not None:
        return write_tiled(load_model(mesh_path, frame), out_dir, frame.crs_spec, frame.origin, tile_size, **kw)
    side = read_offset_sidecar(mesh_path)
    if side is None:
        raise GtkitError("mesh has no offset sidecar: its CRS is unknown", mesh_path)
    crs, off = side
    return write_tiled(read_mesh_file(mesh_path), out_dir, crs, off, tile_size, **kw)
