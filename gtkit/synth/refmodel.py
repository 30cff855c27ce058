"""The reference model: the site as a photogrammetry package would deliver it.

It differs from the true world on purpose: the terrain is resampled on a coarser grid, trees
are coarser blobs, every vertex carries a few cm of noise, and the texture is baked at a coarser
ground sampling distance into charts with seams (terrain: top-down tiles; every wall, roof,
target and tree triangle: its own rectangle in an atlas). Colours are the same procedural
colours as the truth (no lighting baked in), evaluated at the true surface point.
"""
from __future__ import annotations

import numpy as np

from ..io.mesh import Mesh, MeshPart
from ..render.bake import bake_procedural, fill_seams
from .settings import SynthSettings
from .world import MAT_GCP, MAT_TERRAIN, MAT_TREE, World, building_polys, gcp_quads, tree_meshes

PAD = 3  # texels around every chart


def _position_noise(points: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """Noise that is a function of the (rounded) position, so coincident vertices move together."""
    keys = np.round(points, 3)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    rng = np.random.default_rng(seed)
    n = rng.normal(0, sigma, (inv.max() + 1, 3))
    return n[inv.reshape(-1)]


def _terrain_tiles(world: World, s: SynthSettings, seed: int, glsl: str, progress=None) -> list[MeshPart]:
    m = s.model
    half = world.size / 2
    n_side = int(np.ceil(world.size / (m.texture_gsd_m * (m.atlas_size - 2 * PAD))))
    edges = np.linspace(-half, half, n_side + 1)
    parts = []
    for i in range(n_side):
        for j in range(n_side):
            x0, x1, y0, y1 = edges[i], edges[i + 1], edges[j], edges[j + 1]
            nx = max(2, int(round((x1 - x0) / m.terrain_spacing_m)) + 1)
            ny = max(2, int(round((y1 - y0) / m.terrain_spacing_m)) + 1)
            X, Y = np.meshgrid(np.linspace(x0, x1, nx), np.linspace(y0, y1, ny))
            P = np.column_stack([X.ravel(), Y.ravel(), world.terrain_height(X, Y).ravel()])
            idx = np.arange(nx * ny).reshape(ny, nx)
            a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
            F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
            W = int(np.ceil((x1 - x0) / m.texture_gsd_m))
            H = int(np.ceil((y1 - y0) / m.texture_gsd_m))
            uv = np.column_stack([(P[:, 0] - x0) / (x1 - x0), (P[:, 1] - y0) / (y1 - y0)])
            rgb, mask = bake_procedural(P, F, uv, (W, H), glsl, pattern_uv=P[:, :2],
                                        material=np.full(len(P), MAT_TERRAIN))
            tex = fill_seams(rgb, mask, PAD)
            V = P + _position_noise(P, m.noise_m, seed + 1)
            parts.append(MeshPart(V, F, uv=uv, texture=tex, name=f"terrain_{i}_{j}"))
            if progress is not None:
                progress.update(1)
    return parts


def _chart(poly: np.ndarray, gsd: float) -> tuple[np.ndarray, np.ndarray]:
    """Local 2D coordinates (texels, >= PAD) of a planar polygon and its size in texels."""
    e1 = poly[1] - poly[0]
    e1 /= np.linalg.norm(e1)
    nrm = np.cross(poly[1] - poly[0], poly[-1] - poly[0])
    if np.linalg.norm(nrm) < 1e-12:
        nrm = np.array([0.0, 0.0, 1.0])
    nrm /= np.linalg.norm(nrm)
    e2 = np.cross(nrm, e1)
    loc = np.column_stack([(poly - poly[0]) @ e1, (poly - poly[0]) @ e2]) / gsd
    loc -= loc.min(0)
    size = np.ceil(loc.max(0)).astype(int) + 1 + 2 * PAD
    return loc + PAD, size


def _pack(sizes: np.ndarray, page: int) -> list[tuple[int, int, int]]:
    """Shelf packing: (page, x, y) of every rectangle (w, h), tallest first."""
    order = np.lexsort((np.arange(len(sizes)), -sizes[:, 1]))
    out = [None] * len(sizes)
    pg, x, y, shelf_h = 0, 0, 0, 0
    for k in order:
        w, h = (int(v) for v in np.minimum(sizes[k], page))
        if x + w > page:
            x, y, shelf_h = 0, y + shelf_h, 0
        if y + h > page:
            pg, x, y, shelf_h = pg + 1, 0, 0, 0
        out[k] = (pg, x, y)
        x += w
        shelf_h = max(shelf_h, h)
    return out


def _atlas_parts(polys, gsds, s: SynthSettings, seed: int, glsl: str, progress=None) -> list[MeshPart]:
    """polys: list of (true vertices (k, 3), pattern uv, material, colour); one chart each."""
    m = s.model
    charts = [_chart(p[0], g) for p, g in zip(polys, gsds)]
    sizes = np.array([c[1] for c in charts])
    # scale charts that do not fit a page
    places = _pack(sizes, m.atlas_size)
    n_pages = max(p[0] for p in places) + 1
    parts = []
    for pg in range(n_pages):
        ks = [k for k in range(len(polys)) if places[k][0] == pg]
        used_h = max(places[k][2] + sizes[k][1] for k in ks)
        W, H = m.atlas_size, int(min(m.atlas_size, used_h))
        P, UVp, C, M, UVa, F = [], [], [], [], [], []
        off = 0
        for k in ks:
            v, puv, mat, col = polys[k]
            loc, size = charts[k]
            loc = np.minimum(loc, m.atlas_size - 1)
            _, x, y = places[k]
            px = (x + loc[:, 0]) / W
            py = 1.0 - (y + loc[:, 1]) / H   # rows from the top -> v up
            P.append(v)
            UVp.append(puv)
            C.append(np.tile(np.asarray(col, float) * 255, (len(v), 1)))
            M.append(np.full(len(v), mat, float))
            UVa.append(np.column_stack([px, py]))
            F.append(np.array([[0, i, i + 1] for i in range(1, len(v) - 1)]) + off)
            off += len(v)
        P, UVp, C, M, UVa, F = (np.concatenate(a) for a in (P, UVp, C, M, UVa, F))
        rgb, mask = bake_procedural(P, F, UVa, (W, H), glsl, pattern_uv=UVp, colors=C, material=M)
        tex = fill_seams(rgb, mask, PAD)
        V = P + _position_noise(P, m.noise_m, seed + 2 + pg)
        parts.append(MeshPart(V, F, uv=UVa, texture=tex, name=f"atlas_{pg}"))
        if progress is not None:
            progress.update(1)
    return parts


def reference_model(world: World, s: SynthSettings, glsl: str, rng: np.random.Generator, progress=None) -> Mesh:
    seed = int(rng.integers(1 << 31))
    polys, gsds = [], []
    for v, uv, mat, col in building_polys(world):
        polys.append((v, uv, mat, col))
        gsds.append(s.model.texture_gsd_m)
    if len(world.gcps):
        V, UV, F = gcp_quads(world)
        for f in F.reshape(-1, 2, 3)[:, 0]:
            k = f[0]
            polys.append((V[k:k + 4], UV[k:k + 4], MAT_GCP, (0.5, 0.5, 0.5)))
            gsds.append(min(0.04, s.model.texture_gsd_m))
    if len(world.trees):
        # coarser canopies than the truth (decimation), no lumps
        V, F = tree_meshes(world.trees, 1, None)
        for f in F:
            polys.append((V[f], V[f][:, :2], MAT_TREE, (0.5, 0.5, 0.5)))
            gsds.append(s.model.tree_texture_gsd_m)
    parts = _terrain_tiles(world, s, seed, glsl, progress)
    parts += _atlas_parts(polys, gsds, s, seed, glsl, progress)
    return Mesh(parts)
