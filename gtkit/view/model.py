"""The reference model as the 3D view draws it: read fast, decimated when big, cached.

What a first open costs is mostly reading the model, so the view reads it its own way:

- OBJ + MTL (what gtkit writes, and most photogrammetry exports) with a numpy reader of the
  ``v`` / ``vt`` / ``f`` / ``usemtl`` lines; the textures are decoded at reduced size (libjpeg's DCT
  scaling through PIL's ``draft``: 1/8 for vertex colours, at most 2048 px for a textured model)
  in threads while the geometry is parsed. Other formats, and OBJ files this reader does not take
  (polygons, negative indices), go through :func:`gtkit.io.mesh.load_model`.
- A model with more than ``max_triangles`` triangles is shown as one mesh with vertex colours
  (the mean of its texture at each vertex's corners), coincident vertices merged (tile seams), and
  decimated by vertex clustering (``vtkQuadricClustering``, quadric-placed vertices on a grid
  sized for the asked triangle count: 0.2 s for 208k triangles). The result is cached in
  ``work/view/model_<key>.npz``; the key is the model files' fingerprints, so a changed model is
  read again (older caches are removed).
- A smaller model is drawn textured, as it is.
"""
from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..errors import GtkitError

CACHE_VERSION = 2
VERTEX_COLOUR_SCALE = 8       # textures decoded at 1/8 size for vertex colours (JPEG DCT scaling)
MAX_TEXTURE_PX = 2048         # a textured (not decimated) model's textures are decoded at most this big
DEFAULT_RGB = (200, 200, 200)


class _NotFast(Exception):
    """The OBJ holds something the numpy reader does not take: read it with load_model."""


def _decode(path: Path, max_px: int | None, scale: int) -> np.ndarray:
    """An image as (H, W, 3) uint8, row 0 = top, decoded at 1/``scale`` (or to ``max_px``) where the
    format allows (JPEG)."""
    from PIL import Image

    with Image.open(path) as im:
        w, h = im.size
        if max_px:
            scale = max(1, int(np.ceil(max(w, h) / max_px)))
        im.draft("RGB", (max(w // scale, 1), max(h // scale, 1)))
        im = im.convert("RGB")
        if max_px and max(im.size) > max_px:
            im.thumbnail((max_px, max_px))
        return np.asarray(im)


def _mtl(path: Path) -> dict[str, tuple[Path | None, tuple[int, int, int]]]:
    """Material name -> (texture file or None, diffuse colour)."""
    out, cur, tex, kd = {}, None, None, DEFAULT_RGB
    if not path.is_file():
        return out
    for line in path.read_text(errors="replace").splitlines() + ["newmtl"]:
        s = line.split()
        if not s:
            continue
        if s[0] == "newmtl":
            if cur is not None:
                out[cur] = (tex, kd)
            cur, tex, kd = (s[1] if len(s) > 1 else None), None, DEFAULT_RGB
        elif s[0] == "map_Kd" and len(s) > 1:
            tex = path.parent / s[-1].replace("\\", "/")
        elif s[0] == "Kd" and len(s) >= 4:
            kd = tuple(int(np.clip(float(v) * 255, 0, 255)) for v in s[1:4])
    return out


def _numbers(lines: list[str], dtype=float) -> np.ndarray:
    """The numbers on the lines, in order (C parsing: 0.05 s for 208k face lines); a parse error
    stops early, which the callers' size checks catch."""
    import warnings

    if not lines:
        return np.zeros(0, dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # "could not be read to its end"
        return np.fromstring(" ".join(lines).replace("/", " "), dtype=dtype, sep=" ")


def read_obj_fast(path: Path, max_triangles: int):
    """Parse an OBJ of triangles. Returns (vertices, vertex_rgb or None, uv, faces (n, 3) vertex
    indices, face_uv (n, 3) or None, parts [(first face, material)], textures {material: image},
    materials); raises _NotFast for what it does not take. Textures are decoded for vertex colours
    (1/8 size) when the model has more than ``max_triangles`` triangles, else for drawing."""
    text = path.read_text(errors="replace")
    big = text.count("\nf ") > max_triangles
    head = re.search(r"^mtllib\s+(.+?)\s*$", text, re.M)
    materials = _mtl(path.parent / head.group(1)) if head else {}
    files = {m: t for m, (t, _kd) in materials.items() if t is not None and t.is_file()}
    pool = ThreadPoolExecutor(2)  # decoding releases the GIL: the textures are decoded while we parse
    futures = {m: pool.submit(_decode, f, None if big else MAX_TEXTURE_PX, VERTEX_COLOUR_SCALE)
               for m, f in files.items()}
    try:
        v, vt, f, parts = [], [], [], []
        for line in text.split("\n"):
            c = line[:2]
            if c == "v ":
                v.append(line[2:])
            elif c == "vt":
                vt.append(line[3:])
            elif c == "f ":
                f.append(line[2:])
            elif line.startswith("usemtl"):
                parts.append((len(f), line[6:].strip()))
        if not v or not f:
            raise _NotFast("no vertices or faces")
        V = _numbers(v)
        ncol = len(v[0].split())
        if ncol not in (3, 4, 6, 7) or V.size != ncol * len(v):
            raise _NotFast("vertex lines of different lengths")
        V = V.reshape(len(v), ncol)
        rgb = None
        if ncol in (6, 7):  # v x y z r g b (colours 0..1)
            rgb = (np.clip(V[:, -3:], 0, 1) * 255).astype(np.uint8)
        V = V[:, :3]
        corners = f[0].split()
        if len(corners) != 3:
            raise _NotFast("faces that are not triangles")
        per = corners[0].split("/")
        k = len([x for x in per if x])  # numbers per corner: v, v/vt, v//vn, v/vt/vn
        F = _numbers(f, np.int64)
        if F.size != 3 * k * len(f):
            raise _NotFast("faces of different forms")
        F = F.reshape(len(f), 3, k)
        if (F <= 0).any():
            raise _NotFast("negative (relative) indices")
        faces = F[:, :, 0] - 1
        uv, fuv = None, None
        if len(per) >= 2 and per[1] and vt:
            UV = _numbers(vt)
            m = len(vt[0].split())
            if UV.size != m * len(vt):
                raise _NotFast("texture coordinate lines of different lengths")
            uv, fuv = UV.reshape(len(vt), m)[:, :2], F[:, :, 1] - 1
        if faces.max() >= len(V) or (fuv is not None and fuv.max() >= len(uv)):
            raise _NotFast("an index beyond the file's vertices")
        textures = {m: fu.result() for m, fu in futures.items()}
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return V, rgb, uv, faces, fuv, parts or [(0, "")], textures, materials


def _vertex_colours(V, rgb, uv, faces, fuv, parts, textures, materials) -> np.ndarray:
    """Per-vertex colours: the mean of each vertex's corner colours (texture at the corner's uv,
    else the material's diffuse colour, else the file's vertex colour)."""
    n = len(V)
    acc = np.zeros((n, 3))
    cnt = np.zeros(n)
    bounds = [p[0] for p in parts] + [len(faces)]
    for (s, name), e in zip(parts, bounds[1:]):
        if e <= s:
            continue
        idx = faces[s:e].ravel()
        tex = textures.get(name)
        if tex is not None and fuv is not None:
            h, w = tex.shape[:2]
            t = uv[fuv[s:e].ravel()]
            u = np.clip((t[:, 0] % 1.0 * w).astype(int), 0, w - 1)
            vv = np.clip(((1 - t[:, 1] % 1.0) * h).astype(int), 0, h - 1)
            col = tex[vv, u].astype(float)
        elif rgb is not None:
            col = rgb[idx].astype(float)
        else:
            col = np.tile(np.asarray(materials.get(name, (None, DEFAULT_RGB))[1], float), (len(idx), 1))
        for c in range(3):
            acc[:, c] += np.bincount(idx, col[:, c], minlength=n)
        cnt += np.bincount(idx, minlength=n)
    out = np.tile(np.asarray(DEFAULT_RGB, float), (n, 1))
    used = cnt > 0
    out[used] = acc[used] / cnt[used, None]
    return out.astype(np.uint8)


def _polydata(V, faces):
    import pyvista as pv

    return pv.PolyData(np.asarray(V, float), np.hstack([np.full((len(faces), 1), 3), faces]).astype(np.int64).ravel())


def decimate(V: np.ndarray, faces: np.ndarray, rgb: np.ndarray, max_triangles: int):
    """Vertex clustering to at most ``max_triangles``: coincident vertices merged first (a tiled
    model's seams would open as cracks), output vertices coloured like the nearest input vertex."""
    import pyvista as pv
    from scipy.spatial import cKDTree
    from vtkmodules.vtkFiltersCore import vtkQuadricClustering

    pd = _polydata(V, faces)
    pd.point_data["rgb"] = rgb
    pd = pd.clean(tolerance=0.0)  # exact duplicates (tile seams) merged
    U, col = np.asarray(pd.points, float), np.asarray(pd.point_data["rgb"], np.uint8)
    lo, hi = U.min(0), U.max(0)
    ext = np.maximum(hi - lo, 1e-6)
    # a 2.5D site gives about two triangles per occupied cell of its ground plan; cells as high as wide
    cell = float(np.sqrt(ext[0] * ext[1] / (max_triangles / 2.0))) * 0.85
    out = None
    for _ in range(8):
        div = np.maximum(np.ceil(ext / cell), 1).astype(int)
        q = vtkQuadricClustering()
        q.SetInputData(pd)
        q.AutoAdjustNumberOfDivisionsOff()
        q.SetNumberOfDivisions(*div.tolist())
        q.Update()
        out = pv.wrap(q.GetOutput())
        if out.n_cells <= max_triangles:
            break
        cell *= 1.1 * np.sqrt(out.n_cells / max_triangles)
    pts = np.asarray(out.points, float)
    tri = np.asarray(out.faces).reshape(-1, 4)[:, 1:] if out.n_cells else np.zeros((0, 3), np.int64)
    _d, nn = cKDTree(U).query(pts)
    return pts, tri, col[nn]


def _textured_parts(V, rgb, uv, faces, fuv, parts, textures, materials):
    """One pyvista mesh per material: textured (vertices split where the uv differs) or coloured."""
    import pyvista as pv

    out = []
    bounds = [p[0] for p in parts] + [len(faces)]
    for (s, name), e in zip(parts, bounds[1:]):
        if e <= s:
            continue
        tex = textures.get(name)
        if tex is not None and fuv is not None:
            pairs = np.stack([faces[s:e].ravel(), fuv[s:e].ravel()], 1)
            key, inv = np.unique(pairs, axis=0, return_inverse=True)
            pd = _polydata(V[key[:, 0]], inv.reshape(-1, 3))
            pd.active_texture_coordinates = np.asarray(uv[key[:, 1]], np.float32)
            out.append((pd, pv.Texture(np.ascontiguousarray(tex))))
            continue
        used, inv = np.unique(faces[s:e].ravel(), return_inverse=True)
        pd = _polydata(V[used], inv.reshape(-1, 3))
        pd.point_data["rgb"] = (rgb[used] if rgb is not None else
                                np.tile(np.asarray(materials.get(name, (None, DEFAULT_RGB))[1], np.uint8), (len(used), 1)))
        out.append((pd, None))
    return out


def _from_load_model(path: Path, frame):
    """Anything the fast reader does not take, as gtkit.io.mesh reads it (full-size textures)."""
    from ..io.mesh import load_model

    mesh = load_model(path, frame)
    V, F, C, UV, parts, textures, materials, off = [], [], [], [], [], {}, {}, 0
    for k, p in enumerate(mesh.parts):
        parts.append((sum(len(x) for x in F), f"part{k}"))
        V.append(p.vertices)
        F.append(p.faces + off)
        if p.texture is not None and p.uv is not None:
            UV.append(p.uv)
            textures[f"part{k}"] = p.texture
        else:
            UV.append(np.zeros((len(p.vertices), 2)))
        C.append(p.colors if p.colors is not None else np.tile(np.uint8(DEFAULT_RGB), (len(p.vertices), 1)))
        off += len(p.vertices)
    faces = np.concatenate(F)
    return (np.concatenate(V), np.concatenate(C).astype(np.uint8), np.concatenate(UV), faces, faces, parts,
            textures, materials)


def view_model(project, max_triangles: int):
    """The reference model as [(pyvista mesh, texture or None)], its triangle count, the count shown
    (None, 0, 0 without a model)."""
    from ..export.sources import reference_model
    from ..io.atomic import atomic_path
    from ..io.mesh import model_shift
    from ..project import file_fingerprint, settings_key

    try:
        path = Path(reference_model(project.paths))
    except GtkitError:
        return None, 0, 0
    files = sorted(f for f in path.parent.iterdir() if f.is_file()) if path.is_file() else [path]
    key = settings_key({"files": {f.name: file_fingerprint(f) for f in files}, "max_triangles": max_triangles,
                        "origin": list(project.frame.origin), "version": CACHE_VERSION})
    cache_dir = project.paths.stage("view")
    cache = cache_dir / f"model_{key}.npz"
    if cache.is_file():
        with np.load(cache) as z:
            pd = _polydata(z["vertices"].astype(np.float64), z["faces"])
            pd.point_data["rgb"] = z["rgb"]
            return [(pd, None)], int(z["n_in"]), int(len(z["faces"]))
    shift = model_shift(path, project.frame) if path.is_file() else None
    try:
        if path.suffix.lower() != ".obj":
            raise _NotFast("not an OBJ")
        data = read_obj_fast(path, max_triangles)
    except _NotFast:
        data = _from_load_model(path, project.frame)
        shift = None  # load_model put it in the world frame
    V, rgb, uv, faces, fuv, parts, textures, materials = data
    if shift is not None:
        V = V + shift
    n = len(faces)
    if n <= max_triangles:
        return _textured_parts(V, rgb, uv, faces, fuv, parts, textures, materials), n, n
    colours = _vertex_colours(V, rgb, uv, faces, fuv, parts, textures, materials)
    verts, tri, col = decimate(V, faces, colours, max_triangles)
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        for old in cache_dir.glob("model_*.npz"):
            old.unlink(missing_ok=True)
        with atomic_path(cache) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, vertices=verts.astype(np.float32), faces=tri.astype(np.int32), rgb=col, n_in=n)
    except OSError as e:  # a read-only project is shown all the same, decimated again next time
        import logging

        logging.getLogger(__name__).warning("3D view: cannot keep the model cache (%s)", e)
    pd = _polydata(verts, tri)
    pd.point_data["rgb"] = col
    return [(pd, None)], n, len(tri)


def prepare_cache(project) -> str:
    """Read and decimate the project's model for the 3D view now (after ``gtkit model build``,
    ``gtkit import model`` or ``gtkit sample create``), so the user's first ``gtkit view`` or 3D tab
    meets the cached model instead of paying the read (medium: ~3 s CPU of a ~5 s first open).
    Never fails the stage that calls it: returns one line saying what happened."""
    import time

    from .settings import ViewSettings

    t = time.perf_counter()
    try:
        model, n_in, n_shown = view_model(project, ViewSettings().max_triangles)
    except Exception as e:  # noqa: BLE001 - the 3D view reads it again at its first open
        return f"3D view cache not written ({type(e).__name__}: {e})"
    if model is None:
        return "3D view cache: no model"
    cached = n_shown < n_in
    return (f"3D view: model read{' and cached' if cached else ''} in {time.perf_counter() - t:.1f} s "
            f"({n_in} triangles{f', {n_shown} shown' if cached else ''})")
