"""An OBJ's geometry without its textures: vertices, triangles and the model's texel size.

What a height raster (``gtkit export dsm``, ``gtkit model compare``) needs of a textured model is
its triangles; its texture images are not decoded. :func:`read_obj_geometry` reads the file in
blocks of 16 MB (``v``, ``vt`` and ``f`` lines parsed by numpy a block at a time) and keeps

* ``vertices`` (N, 3) float64 as stored (plus ``shift``), ``faces`` (M, 3) int32, 0-based;
* ``texel_size``: the median ground size of one texel over the textured triangles, the figure
  :meth:`gtkit.export.surface.MeshSurface.texel_size` computes from the loaded textures; here the
  texture sizes come from the image headers (``map_Kd`` of the MTL), not from decoded pixels.

So a 5.4 M-triangle, 650-texture OBJ takes ~0.3 GB (24 B a vertex, 12 B a triangle) instead of
its decoded textures plus trimesh's parse. Polygons are split as a fan (as trimesh does), negative
(relative) indices are resolved, and vertex colours or normals are ignored.

With ``corners=True`` it also keeps what drawing the textured model needs (the overlay scene,
the orthophoto): each corner's uv index, each triangle's material, the uv list and the MTL's
materials. :meth:`ObjGeometry.parts` then yields the model as :class:`gtkit.io.mesh.MeshPart`s,
one per material as :func:`gtkit.io.mesh.read_mesh_file` (trimesh) makes them, each texture
decoded only when its part is yielded: a renderer that uploads the parts one after another holds
one decoded texture at a time besides what it has uploaded (a further 16 B a uv and 16 B a
triangle here).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import GtkitError
from .mesh_parts import MeshPart

BLOCK_BYTES = 16 << 20
_USEMTL = re.compile(rb"^usemtl[ \t]+([^\r\n]*)\r?$", re.MULTILINE)


@dataclass
class ObjMaterial:
    """A ``newmtl`` of the MTL: its texture file (``map_Kd``) and diffuse colour (``Kd``)."""

    name: bytes
    texture: Path | None = None
    kd: tuple[float, float, float] | None = None
    defined: bool = True            # False: used by ``usemtl`` but not in any MTL


@dataclass
class ObjGeometry:
    vertices: np.ndarray            # (N, 3) float64
    faces: np.ndarray               # (M, 3) int32, 0-based
    texel_size: float | None        # median ground size of a texel (m), None when untextured
    path: Path | None = None
    # with corners=True (else None): what the textured model needs
    uv: np.ndarray | None = None             # (K, 2) float64 texture coordinates as stored (v up)
    face_uv: np.ndarray | None = None        # (M, 3) int32 uv index of each corner, -1 = none
    face_material: np.ndarray | None = None  # (M,) int32 index into materials, -1 = none
    materials: list[ObjMaterial] | None = None  # in the order of their first ``usemtl``
    vertex_extras: bool = False     # some ``v`` lines carry more than x y z (vertex colours): ignored here

    @property
    def n_triangles(self) -> int:
        return len(self.faces)

    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner of the vertices the triangles use."""
        used = np.zeros(len(self.vertices), bool)
        used[self.faces.ravel()] = True
        v = self.vertices[used] if not used.all() else self.vertices
        return np.stack([v.min(0), v.max(0)])

    def edge_length(self, chunk: int = 1_000_000) -> float:
        """Median 3-D triangle edge length (metres)."""
        e = []
        for s in range(0, len(self.faces), chunk):
            v = self.vertices[self.faces[s:s + chunk]]
            e.append(np.linalg.norm(v[:, [1, 2, 0]] - v, axis=2).ravel().astype(np.float32))
        return float(np.median(np.concatenate(e)))

    def pieces(self, max_triangles: int = 1_000_000):
        """The triangles in file order as self-contained (vertices, faces) pieces of at most
        ``max_triangles``, each with only the vertices it uses."""
        for s in range(0, len(self.faces), max_triangles):
            f = self.faces[s:s + max_triangles]
            used, inv = np.unique(f, return_inverse=True)
            yield self.vertices[used], inv.reshape(-1, 3).astype(np.int32)

    def n_parts(self) -> int:
        """How many parts :meth:`parts` yields."""
        if self.face_material is None:
            raise GtkitError("read with corners=True to draw the textured model", self.path)
        return len(np.unique(self.face_material))

    def parts(self):
        """The model as drawable :class:`~gtkit.io.mesh.MeshPart`s, as trimesh's OBJ reader
        (``group_material``) makes them: one per material, in the order of the materials' first
        use, faces in file order; a textured part has one vertex per distinct (vertex, uv) pair
        its corners use, a part without a texture (or without uv on every corner) one per vertex
        with the material's ``Kd`` colour, triangles without a material grey (180). Each texture
        is decoded (PIL, RGB) when its part is yielded and not kept here."""
        if self.face_material is None:
            raise GtkitError("read with corners=True to draw the textured model", self.path)
        order = np.argsort(self.face_material, kind="stable")
        fm = self.face_material[order]
        starts = np.flatnonzero(np.r_[True, fm[1:] != fm[:-1]])
        ends = np.r_[starts[1:], len(fm)]
        groups = sorted(zip(starts, ends), key=lambda se: (fm[se[0]] < 0, fm[se[0]]))
        nvt = max(len(self.uv), 1) if self.uv is not None else 1
        for s, e in groups:
            m = int(fm[s])
            idx = order[s:e]
            f = self.faces[idx]
            mat = self.materials[m] if m >= 0 else None
            ft = self.face_uv[idx] if self.uv is not None else None
            tex = None
            if mat is not None and mat.texture is not None and ft is not None and (ft >= 0).all():
                tex = _decode_texture(mat.texture)
            name = mat.name.decode("utf-8", "replace") if mat is not None else "no_material"
            if tex is not None:
                key = f.astype(np.int64) * nvt + ft
                u, inv = np.unique(key.ravel(), return_inverse=True)
                yield MeshPart(self.vertices[u // nvt], inv.reshape(-1, 3).astype(np.int64),
                               uv=self.uv[u % nvt], texture=tex, name=name)
            else:
                used, inv = np.unique(f.ravel(), return_inverse=True)
                yield MeshPart(self.vertices[used], inv.reshape(-1, 3).astype(np.int64),
                               colors=np.tile(_diffuse_rgb(mat), (len(used), 1)), name=name)
            del f, ft, tex


def _decode_texture(path: Path) -> np.ndarray | None:
    """(H, W, 3) uint8, row 0 = top, as trimesh hands it to :mod:`gtkit.io.mesh` (PIL, RGB);
    None when the file cannot be read (trimesh then draws the material's colour)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, ValueError):
        return None


def _diffuse_rgb(mat: "ObjMaterial | None") -> np.ndarray:
    """The colour trimesh gives a part without a texture: ``Kd`` x 255 rounded (102 grey for a
    material without ``Kd``), 180 grey for triangles without a material."""
    if mat is None or not mat.defined:
        return np.full(3, 180, np.uint8)
    if mat.kd is None:
        return np.full(3, 102, np.uint8)
    return np.clip(np.round(np.asarray(mat.kd, float) * 255), 0, 255).astype(np.uint8)


def _mtl_materials(obj: Path, mtllibs: list[bytes]) -> dict[bytes, ObjMaterial]:
    """material name -> its ``map_Kd`` file and ``Kd`` colour, from the OBJ's MTL files."""
    out: dict[bytes, ObjMaterial] = {}
    for lib in mtllibs:
        p = obj.parent / lib.decode("utf-8", "replace").strip()
        if not p.is_file():
            continue
        cur = None
        for line in p.read_bytes().splitlines():
            t = line.strip().split()
            if len(t) < 2:
                continue
            key = t[0].lower()
            if key == b"newmtl":
                cur = out.setdefault(b" ".join(t[1:]), ObjMaterial(b" ".join(t[1:])))
            elif cur is None:
                continue
            elif key == b"map_kd":
                cur.texture = p.parent / t[-1].decode("utf-8", "replace")
            elif key == b"kd" and len(t) >= 4:
                try:
                    cur.kd = tuple(float(x) for x in t[1:4])
                except ValueError:
                    pass
    return out


def _mtl_texture_sizes(obj: Path, mtllibs: list[bytes]) -> dict[bytes, tuple[int, int]]:
    """material name -> (width, height) of its ``map_Kd`` image, from the image header."""
    from PIL import Image

    sizes: dict[bytes, tuple[int, int]] = {}
    for name, mat in _mtl_materials(obj, mtllibs).items():
        if mat.texture is None:
            continue
        try:
            with Image.open(mat.texture) as im:
                sizes[name] = im.size
        except (OSError, ValueError):
            pass
    return sizes


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.v: list[np.ndarray] = []
        self.vt: list[np.ndarray] = []
        self.f: list[np.ndarray] = []     # (m, 3) vertex index, 0-based
        self.ft: list[np.ndarray] = []    # (m, 3) uv index, 0-based, -1 = none
        self.fm: list[np.ndarray] = []    # (m,) material number, -1 = none
        self.nv = 0
        self.nvt = 0
        self.mtllibs: list[bytes] = []
        self.materials: dict[bytes, int] = {}
        self.material = -1
        self.more_than_xyz = False

    # --- numbers --------------------------------------------------------------------------
    def _floats(self, lines: list[bytes], k: int) -> np.ndarray:
        """The first ``k`` numbers of each line (a block's ``v`` or ``vt`` lines, keyword cut off)."""
        tok = b" ".join(lines).split()
        n = len(lines)
        if k == 3 and len(tok) != k * n:
            self.more_than_xyz = True  # vertex colours (or w): trimesh draws those, parts() does not
        try:
            if len(tok) == k * n:
                return np.array(tok, dtype=np.float64).reshape(n, k)
            return np.array([ln.split()[:k] for ln in lines], dtype=np.float64)
        except ValueError:
            raise GtkitError(f"OBJ has an unreadable vertex line ({lines[0][:60]!r}...)", self.path) from None

    def _faces_fast(self, lines: list[bytes]):
        """Triangles with one corner format throughout and positive indices; None otherwise."""
        first = lines[0].split(None, 1)[0]
        k = first.count(b"/") + 1
        slashes = 3 * (k - 1)
        if any(ln.count(b"/") != slashes for ln in lines):  # corner formats mixed (or not triangles)
            return None
        joined = b" ".join(lines)
        if b"//" in first:
            joined = joined.replace(b"//", b"/0/")
        tok = joined.replace(b"/", b" ").split()
        n = len(lines)
        if len(tok) != 3 * k * n:
            return None
        try:
            a = np.array(tok, dtype=np.int64).reshape(n, 3, k)
        except ValueError:
            return None
        if (a[:, :, 0] <= 0).any() or (k > 1 and b"//" not in first and (a[:, :, 1] <= 0).any()):
            return None
        v = a[:, :, 0] - 1
        vt = a[:, :, 1] - 1 if k > 1 and b"//" not in first else np.full_like(v, -1)
        return v, vt

    def _faces_slow(self, lines: list[bytes], nv_at: np.ndarray, nvt_at: np.ndarray):
        """Any face lines: polygons as fans, relative indices, mixed corner formats."""
        fv, ft = [], []
        for ln, nv, nvt in zip(lines, nv_at, nvt_at):
            cs = []
            for c in ln.split():
                p = c.split(b"/")
                try:
                    i = int(p[0])
                    j = int(p[1]) if len(p) > 1 and p[1] else 0
                except ValueError:
                    raise GtkitError(f"OBJ has an unreadable face line ({ln[:60]!r})", self.path) from None
                i = i - 1 if i > 0 else nv + i
                j = (j - 1 if j > 0 else nvt + j) if j else -1
                cs.append((i, j))
            for a in range(1, len(cs) - 1):
                tri = (cs[0], cs[a], cs[a + 1])
                fv.append([c[0] for c in tri])
                ft.append([c[1] for c in tri])
        return (np.array(fv, np.int64).reshape(-1, 3), np.array(ft, np.int64).reshape(-1, 3))

    # --- a piece of the file between two ``usemtl`` lines --------------------------------------
    def segment(self, text: bytes) -> None:
        if not text:
            return
        lines = text.split(b"\n")
        vl = [ln[2:] for ln in lines if ln[:2] in (b"v ", b"v\t")]
        tl = [ln[3:] for ln in lines if ln[:3] in (b"vt ", b"vt\t")]
        fl = [ln[2:] for ln in lines if ln[:2] in (b"f ", b"f\t")]
        for ln in lines:
            if ln.startswith(b"mtllib"):
                self.mtllibs += ln.split()[1:2]
        if fl:
            fast = self._faces_fast(fl)
            if fast is None:
                # counts of v / vt lines before each face line (relative indices need them)
                kind = np.array([0 if ln[:2] in (b"v ", b"v\t") else 1 if ln[:3] in (b"vt ", b"vt\t")
                                 else 2 if ln[:2] in (b"f ", b"f\t") else 3 for ln in lines])
                nv_at = self.nv + np.cumsum(kind == 0)[kind == 2]
                nvt_at = self.nvt + np.cumsum(kind == 1)[kind == 2]
                fast = self._faces_slow(fl, nv_at, nvt_at)
            fv, ft = fast
            small = np.int32 if max(int(fv.max(initial=0)), int(ft.max(initial=0))) < 2**31 - 1 else np.int64
            self.f.append(fv.astype(small))
            self.ft.append(ft.astype(small))
            self.fm.append(np.full(len(fv), self.material, np.int32))
        if vl:
            v = self._floats(vl, 3)
            self.v.append(v)
            self.nv += len(v)
        if tl:
            t = self._floats(tl, 2)
            self.vt.append(t)
            self.nvt += len(t)

    def block(self, text: bytes) -> None:
        """Whole lines; ``usemtl`` lines switch the material of the faces after them."""
        parts = _USEMTL.split(text)
        self.segment(parts[0])
        for name, seg in zip(parts[1::2], parts[2::2]):
            name = name.strip()
            self.material = self.materials.setdefault(name, len(self.materials))
            self.segment(seg)


def triangle_texel_sizes(v: np.ndarray, uv_px: np.ndarray) -> np.ndarray:
    """sqrt(3-D area / texture area in texels) of triangles (corners ``v`` (n, 3, 3) in metres,
    ``uv_px`` (n, 3, 2) in texels), degenerate ones left out: the ground size of one texel."""
    a3 = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    d1, d2 = uv_px[:, 1] - uv_px[:, 0], uv_px[:, 2] - uv_px[:, 0]
    a2 = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    ok = (a2 > 1e-9) & (a3 > 1e-12)
    return np.sqrt(a3[ok] / a2[ok])


def _texel_size(V: np.ndarray, F: np.ndarray, FT: np.ndarray, FM: np.ndarray, VT: np.ndarray,
                sizes: np.ndarray, chunk: int = 1_000_000) -> float | None:
    """Median sqrt(3-D area / texture area in texels) over textured, non-degenerate triangles."""
    out = []
    for s in range(0, len(F), chunk):
        f, t, m = F[s:s + chunk], FT[s:s + chunk], FM[s:s + chunk]
        tex = (m >= 0) & np.all(t >= 0, axis=1)
        tex[tex] = sizes[m[tex], 0] > 0
        if not tex.any():
            continue
        f, t, m = f[tex], t[tex], m[tex]
        out.append(triangle_texel_sizes(V[f], VT[t] * sizes[m][:, None, :]))
    sizes_all = np.concatenate(out) if out else np.zeros(0)
    return float(np.median(sizes_all)) if len(sizes_all) else None


def read_obj_geometry(path: str | Path, shift=None, corners: bool = False) -> ObjGeometry:
    """The triangles of an OBJ (``shift`` added to its vertices) and its texel size; textures are
    not decoded. ``corners``: also keep the uv of each corner and the material of each triangle
    (:meth:`ObjGeometry.parts`). Raises :class:`GtkitError` for a file that is not a readable OBJ."""
    path = Path(path)
    if not path.is_file():
        raise GtkitError("mesh file not found", path)
    r = _Reader(path)
    carry = b""
    with open(path, "rb") as fh:
        while True:
            data = fh.read(BLOCK_BYTES)
            if not data:
                break
            data = carry + data
            cut = data.rfind(b"\n")
            if cut < 0:
                carry = data
                continue
            carry = data[cut + 1:]
            r.block(data[:cut + 1].replace(b"\r\n", b"\n"))
        if carry:
            r.block(carry.replace(b"\r\n", b"\n") + b"\n")
    if not r.f or not r.v:
        raise GtkitError("file holds no triangles", path)
    V = np.concatenate(r.v)
    r.v = []
    F = np.concatenate(r.f)
    r.f = []
    if F.min() < 0 or F.max() >= len(V):
        raise GtkitError(f"a face refers to a vertex that does not exist ({len(V)} vertices)", path)
    F = F.astype(np.int32 if len(V) < 2**31 else np.int64)
    if shift is not None:
        V = V + np.asarray(shift, dtype=np.float64)
    texel = None
    FT = np.concatenate(r.ft) if (r.vt and r.materials) or corners else None
    FM = np.concatenate(r.fm) if (r.vt and r.materials) or corners else None
    VT = np.concatenate(r.vt) if r.vt else None
    r.ft = r.fm = r.vt = []
    if VT is not None and r.materials:
        if FT.max() < len(VT):
            by_name = _mtl_texture_sizes(path, r.mtllibs)
            sizes = np.zeros((len(r.materials), 2), np.float64)
            for name, i in r.materials.items():
                if name in by_name:
                    sizes[i] = by_name[name]
            texel = _texel_size(V, F, FT, FM, VT, sizes)
    if not corners:
        return ObjGeometry(V, F, texel, path)
    if VT is not None and (FT.min() < -1 or FT.max() >= len(VT)):
        raise GtkitError(f"a face refers to a texture coordinate that does not exist ({len(VT)} given)", path)
    defined = _mtl_materials(path, r.mtllibs)
    mats = [defined.get(name, ObjMaterial(name, defined=False)) for name, _ in sorted(r.materials.items(), key=lambda kv: kv[1])]
    return ObjGeometry(V, F, texel, path, uv=VT, face_uv=FT.astype(np.int32) if VT is not None else None,
                       face_material=FM, materials=mats, vertex_extras=r.more_than_xyz)
