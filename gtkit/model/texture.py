"""Texture from the photos: every face takes its colours from the one photo that sees it best.

Visibility comes from gtkit's moderngl renderer (the untextured surface's depth buffer seen from each
photo); a face is seen when its centre projects inside the photo, in front of it and not hidden
by nearer surface. Among the photos that see it, the face takes the one with the most texels on
it (``cos(angle) * (f / distance)^2``). The mesh is then split by photo: each part's texture is the
texels of its (undistorted) photo that its faces cover, packed chart by chart into one page
(:mod:`gtkit.io.texture_atlas`), its uv the faces' projection into it. A face
that no photo sees takes the best photo regardless of occlusion (it is inside trimmed support, so
rare).

Colour balancing (:func:`colour_gains`): where two faces that share an edge take their texture from
different photos (a seam), the edge's midpoint is read in both photos; per photo and channel a gain
is solved by least squares from the median log colour ratio of every pair of photos meeting at
seams (weighted by how many seam edges they share, weakly pulled to 1 so the mean brightness
stays), and each part's texture is multiplied by its photo's gains. :func:`seam_difference`
measures the colour jump a viewer sees across the seams (texels just inside either face).
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..io.mesh import Mesh, MeshPart
from ..io.texture_atlas import pack_charts
from .views import View


def _gtkit_camera(v: View, s: float = 1.0) -> Camera:
    K = v.K
    w, h = int(round(v.width * s)), int(round(v.height * s))
    return Camera.pinhole(w, h, K[0, 0] * w / v.width, K[1, 1] * h / v.height,
                          (K[0, 2] + 0.5) * w / v.width, (K[1, 2] + 0.5) * h / v.height)


def _project(v: View, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pixel coordinates (N, 2) and camera z of world points."""
    xc = X @ v.pose.R.T + v.pose.t
    z = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([v.K[0, 0] * xc[:, 0] / z + v.K[0, 2], v.K[1, 1] * xc[:, 1] / z + v.K[1, 2]], 1)
    return uv, z


def _chunks(cen: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Faces grouped by the ``size`` square cell of their centre: (order of the faces by cell,
    start index of each cell's run in it)."""
    ij = np.floor((cen[:, :2] - cen[:, :2].min(0)) / size).astype(np.int64)
    cid = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.argsort(cid, kind="stable")
    starts = np.flatnonzero(np.r_[True, cid[order][1:] != cid[order][:-1]])
    return order, starts


def _in_frustum(v: View, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which boxes (``lo``/``hi``: (n, 3)) may hold something the view sees (conservative: a box is
    out only when all its corners are beyond one side of the view's frustum)."""
    corners = np.stack([np.stack([np.where(m & 1, hi[:, 0], lo[:, 0]), np.where(m & 2, hi[:, 1], lo[:, 1]),
                                  np.where(m & 4, hi[:, 2], lo[:, 2])], 1) for m in range(8)], 1)   # (n, 8, 3)
    xc = corners @ v.pose.R.T + v.pose.t
    x, y, z = xc[..., 0], xc[..., 1], xc[..., 2]
    fx, fy, cx, cy = v.K[0, 0], v.K[1, 1], v.K[0, 2], v.K[1, 2]
    out = (np.all(z <= 0, 1) | np.all(fx * x < (-0.5 - cx) * z, 1) | np.all(fx * x > (v.width - 0.5 - cx) * z, 1)
           | np.all(fy * y < (-0.5 - cy) * z, 1) | np.all(fy * y > (v.height - 0.5 - cy) * z, 1))
    return ~out


def choose_views(V: np.ndarray, F: np.ndarray, views: dict[str, View], vis_scale: float = 0.5,
                 progress=None, chunk_m: float = 50.0) -> tuple[list[str], np.ndarray]:
    """(view names, index of the best view per face; -1 = none).

    The surface is cut into ``chunk_m`` square chunks (one renderer part each, one shared origin:
    the same depth as the whole surface drawn at once); each photo projects and draws only the
    chunks its frustum reaches, so on a large site a photo costs what it sees, not the site."""
    from ..render.renderer import Renderer

    names = list(views)
    cen = V[F].mean(1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    best = np.full(len(F), -1, np.int64)
    best_score = np.zeros(len(F))
    any_best = np.full(len(F), -1, np.int64)
    any_score = np.zeros(len(F))
    order, starts = _chunks(cen, chunk_m)
    runs = np.split(order, starts[1:])
    lo = np.stack([V[F[r]].reshape(-1, 3).min(0) for r in runs])
    hi = np.stack([V[F[r]].reshape(-1, 3).max(0) for r in runs])
    r = Renderer()
    origin = V.mean(0)
    grey = np.full((len(V), 3), 128, np.uint8)
    ids = []
    for k, run in enumerate(runs):
        f = F[run]
        used, inv = np.unique(f, return_inverse=True)
        ids += r.add_mesh(Mesh([MeshPart(V[used], inv.reshape(-1, 3), colors=grey[used], name=f"chunk{k}")]), origin=origin)
    try:
        for k, n in enumerate(names):
            v = views[n]
            sel = np.flatnonzero(_in_frustum(v, lo, hi))
            if len(sel):
                fi = np.concatenate([runs[c] for c in sel])
                uv, z = _project(v, cen[fi])
                inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= v.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= v.height - 1)
                to_cam = v.center - cen[fi]
                dist = np.linalg.norm(to_cam, axis=1)
                cos = np.abs(np.einsum("ij,ij->i", nrm[fi], to_cam)) / np.maximum(dist, 1e-9)
                score = np.where(inside, cos * (v.K[0, 0] / np.maximum(dist, 1e-9)) ** 2, 0.0)
                better = score > any_score[fi]
                any_best[fi[better]], any_score[fi[better]] = k, score[better]
                loc = np.flatnonzero(inside & (score > best_score[fi]))
                if len(loc):
                    cam = _gtkit_camera(v, vis_scale)
                    depth = r.render(cam, v.pose, with_rgb=False, parts=[ids[c] for c in sel]).depth
                    s = cam.width / v.width
                    px = np.clip(((uv[loc, 0] + 0.5) * s).astype(np.int64), 0, cam.width - 1)
                    py = np.clip(((uv[loc, 1] + 0.5) * s).astype(np.int64), 0, cam.height - 1)
                    dz = depth[py, px]
                    seen = np.isfinite(dz) & (z[loc] <= dz + np.maximum(0.3, 0.01 * dz))
                    idx = fi[loc[seen]]
                    best[idx], best_score[idx] = k, score[loc[seen]]
            if progress is not None:
                progress.update(1)
    finally:
        r.release()
    best = np.where(best >= 0, best, any_best)
    return names, best


def seam_edges(F: np.ndarray, best: np.ndarray, max_edges: int | None = None, seed: int = 0) -> np.ndarray:
    """(n, 4) int: vertex i, vertex j, face A, face B of the edges whose two faces take their texture
    from different photos (both seen); at most ``max_edges`` (a fixed random subset)."""
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    f = np.tile(np.arange(len(F)), 3)
    e.sort(axis=1)
    key = e[:, 0].astype(np.int64) * (int(F.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    key, e, f = key[order], e[order], f[order]
    same = np.flatnonzero(key[1:] == key[:-1])           # manifold edges: the two faces are consecutive
    fa, fb = f[same], f[same + 1]
    seam = (best[fa] != best[fb]) & (best[fa] >= 0) & (best[fb] >= 0)
    out = np.stack([e[same, 0], e[same, 1], fa, fb], 1)[seam]
    if max_edges is not None and len(out) > max_edges:
        out = out[np.sort(np.random.default_rng(seed).choice(len(out), max_edges, replace=False))]
    return out


def _sample(views: dict[str, View], names: list[str], load_rgb, which: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(n, 3) float colours of world points ``X[i]`` in view ``which[i]`` (bilinear; NaN outside), each
    photo loaded once."""
    import cv2

    out = np.full((len(X), 3), np.nan)
    for k in np.unique(which):
        idx = np.flatnonzero(which == k)
        v = views[names[k]]
        uv, z = _project(v, X[idx])
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= v.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= v.height - 1)
        if not ok.any():
            continue
        img = load_rgb(v).astype(np.float32)
        m = uv[ok].astype(np.float32)
        w = 4096                                   # the map as rows of 4096 (OpenCV's maps stay < 32767 a side)
        pad = -len(m) % w
        m = np.concatenate([m, np.zeros((pad, 2), np.float32)]).reshape(-1, w, 2)
        out[idx[ok]] = cv2.remap(img, np.ascontiguousarray(m[..., 0]), np.ascontiguousarray(m[..., 1]), cv2.INTER_LINEAR).reshape(-1, 3)[:ok.sum()]
    return out


def seam_colours(V: np.ndarray, F: np.ndarray, views: dict[str, View], names: list[str], best: np.ndarray, load_rgb,
                 max_edges: int = 200_000, inset: float = 0.25) -> dict:
    """Colours at the seams, each photo read once: for every seam edge (photos ``a`` and ``b`` of its
    two faces) its midpoint in both photos (``mid_a``, ``mid_b``: the same surface point, for the
    gains) and the texel ``inset`` of the way from the midpoint to each face's centre, each in its
    own photo (``in_a``, ``in_b``: what a viewer sees on either side of the seam)."""
    se = seam_edges(F, best, max_edges)
    mid = 0.5 * (V[se[:, 0]] + V[se[:, 1]])
    pa = mid + inset * (V[F[se[:, 2]]].mean(1) - mid)
    pb = mid + inset * (V[F[se[:, 3]]].mean(1) - mid)
    a, b = best[se[:, 2]], best[se[:, 3]]
    c = _sample(views, names, load_rgb, np.concatenate([a, b, a, b]), np.concatenate([mid, mid, pa, pb]))
    n = len(se)
    return {"a": a, "b": b, "mid_a": c[:n], "mid_b": c[n:2 * n], "in_a": c[2 * n:3 * n], "in_b": c[3 * n:]}


def usable_seam_edges(sc: dict) -> np.ndarray:
    """Which seam edges of :func:`seam_colours` carry a colour in both photos that is neither dark
    nor clipped (every channel finite and within (8, 250)): the ones :func:`colour_gains` uses."""
    ca, cb = sc["mid_a"], sc["mid_b"]
    return np.all(np.isfinite(ca) & np.isfinite(cb) & (ca > 8) & (cb > 8) & (ca < 250) & (cb < 250), axis=1)


def colour_gains(sc: dict, n_photos: int, min_edges: int = 20, reg: float = 0.05) -> np.ndarray:
    """(n_photos, 3) per-photo, per-channel gains that even out the seams' colours (from
    :func:`seam_colours`; 1 where a photo meets no other at enough seam edges)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import lsqr

    gains = np.ones((n_photos, 3))
    a, b, ca, cb = sc["a"], sc["b"], sc["mid_a"], sc["mid_b"]
    ok = usable_seam_edges(sc)
    a, b, ca, cb = a[ok], b[ok], ca[ok], cb[ok]
    if not len(a):
        return gains
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    r = np.log(cb) - np.log(ca)                 # g_a c_a = g_b c_b: x_a - x_b = log(c_b / c_a)
    r[a > b] *= -1                              # as x_lo - x_hi = log(c_hi / c_lo)
    pair = lo.astype(np.int64) * n_photos + hi
    up, inv, cnt = np.unique(pair, return_inverse=True, return_counts=True)
    use = np.flatnonzero(cnt >= min_edges)
    if not len(use):
        return gains
    order = np.argsort(inv, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(cnt)])
    med = np.array([np.median(r[order[bounds[i]:bounds[i + 1]]], axis=0) for i in use])
    pl, ph = up[use] // n_photos, up[use] % n_photos
    w = np.sqrt(np.minimum(cnt[use], 400)).astype(np.float64)
    n_p = len(use)
    rows = np.concatenate([np.arange(n_p), np.arange(n_p), n_p + np.arange(n_photos)])
    cols = np.concatenate([pl, ph, np.arange(n_photos)])
    vals = np.concatenate([w, -w, np.full(n_photos, reg)])
    A = coo_matrix((vals, (rows, cols)), shape=(n_p + n_photos, n_photos)).tocsr()
    for c in range(3):
        x = lsqr(A, np.concatenate([w * med[:, c], np.zeros(n_photos)]), atol=1e-10, btol=1e-10)[0]
        gains[:, c] = np.exp(np.clip(x, np.log(0.5), np.log(2.0)))
    return gains


def seam_difference(sc: dict, gains: np.ndarray | None = None) -> float:
    """Median |colour difference| (mean over RGB, 0-255) across the seams as the textures show it
    (``in_a`` vs ``in_b`` of :func:`seam_colours`, times the photos' gains)."""
    ca, cb = sc["in_a"], sc["in_b"]
    if gains is not None:
        ca, cb = np.clip(ca * gains[sc["a"]], 0, 255), np.clip(cb * gains[sc["b"]], 0, 255)
    d = np.abs(ca - cb).mean(1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else float("nan")


def textured_parts(V: np.ndarray, F: np.ndarray, views: dict[str, View], names: list[str], best: np.ndarray,
                   load_rgb, pad: int = 2, gains: np.ndarray | None = None) -> list[MeshPart]:
    """One textured part per photo that textures any face (``load_rgb(view)`` gives its undistorted RGB;
    ``gains`` (per photo, per channel) multiply its texture). Each part's texture is a page of the
    charts its faces use (:func:`gtkit.io.texture_atlas.pack_charts`), not the box around them,
    which is nearly the whole photo when the faces a photo sees best are scattered over it."""
    parts = []
    order = np.argsort(best, kind="stable")                  # faces grouped by photo (one pass, not one a photo)
    keys = best[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], len(order)]):
        k = int(keys[a])
        if k < 0:
            continue
        v = views[names[k]]
        used, local = np.unique(F[order[a:b]], return_inverse=True)
        local = local.reshape(-1, 3)
        uv, _ = _project(v, V[used])
        uv = np.clip(uv, -0.5, [v.width - 0.5, v.height - 0.5])
        x0 = int(max(0, np.floor(uv[:, 0].min() + 0.5) - pad))
        y0 = int(max(0, np.floor(uv[:, 1].min() + 0.5) - pad))
        x1 = int(min(v.width, np.ceil(uv[:, 0].max() + 0.5) + pad))
        y1 = int(min(v.height, np.ceil(uv[:, 1].max() + 0.5) + pad))
        img = load_rgb(v)[y0:y1, x0:x1].copy()          # not a view: the whole photo is not kept
        if gains is not None and not np.allclose(gains[k], 1.0):
            img = np.clip(img * gains[k] + 0.5, 0, 255).astype(np.uint8)
        cw, ch = x1 - x0, y1 - y0
        tuv = np.stack([(uv[:, 0] + 0.5 - x0) / cw, 1.0 - (uv[:, 1] + 0.5 - y0) / ch], 1)
        parts.append(pack_charts(MeshPart(V[used], local, uv=tuv, texture=np.ascontiguousarray(img),
                                          name=v.name.replace("/", "_").rsplit(".", 1)[0])))
    unseen = F[best < 0]
    if len(unseen):
        used = np.unique(unseen)
        remap = np.full(len(V), -1, np.int64)
        remap[used] = np.arange(len(used))
        parts.append(MeshPart(V[used], remap[unseen], colors=np.full((len(used), 3), 128, np.uint8), name="unseen"))
    return parts
