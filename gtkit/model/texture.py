"""Texture from the photos: every face takes its colours from the one photo that sees it best.

Visibility comes from gtkit's moderngl renderer (the untextured surface's depth buffer seen from each
photo); a face is seen when its centre projects inside the photo, in front of it and not hidden
by nearer surface. Among the photos that see it, the face takes the one with the most texels on
it (``cos(angle) * (f / distance)^2``). The mesh is then split by photo: each part's texture is the
crop of its (undistorted) photo that its faces cover, its uv the faces' projection into it. A face
that no photo sees takes the best photo regardless of occlusion (it is inside trimmed support, so
rare). No colour balancing between photos (the photos of one flight share one exposure here).
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..io.mesh import Mesh, MeshPart
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


def choose_views(V: np.ndarray, F: np.ndarray, views: dict[str, View], vis_scale: float = 0.5,
                 progress=None) -> tuple[list[str], np.ndarray]:
    """(view names, index of the best view per face; -1 = none)."""
    from ..render.renderer import Renderer

    names = list(views)
    cen = V[F].mean(1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    best = np.full(len(F), -1, np.int64)
    best_score = np.zeros(len(F))
    any_best = np.full(len(F), -1, np.int64)
    any_score = np.zeros(len(F))
    r = Renderer(Mesh([MeshPart(V, F, colors=np.full((len(V), 3), 128, np.uint8), name="surface")]))
    try:
        for k, n in enumerate(names):
            v = views[n]
            uv, z = _project(v, cen)
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= v.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= v.height - 1)
            to_cam = v.center - cen
            dist = np.linalg.norm(to_cam, axis=1)
            cos = np.abs(np.einsum("ij,ij->i", nrm, to_cam)) / np.maximum(dist, 1e-9)
            score = np.where(inside, cos * (v.K[0, 0] / np.maximum(dist, 1e-9)) ** 2, 0.0)
            better = score > any_score
            any_best[better], any_score[better] = k, score[better]
            idx = np.flatnonzero(inside & (score > best_score))
            if len(idx):
                cam = _gtkit_camera(v, vis_scale)
                depth = r.render(cam, v.pose, with_rgb=False).depth
                s = cam.width / v.width
                px = np.clip(((uv[idx, 0] + 0.5) * s).astype(np.int64), 0, cam.width - 1)
                py = np.clip(((uv[idx, 1] + 0.5) * s).astype(np.int64), 0, cam.height - 1)
                dz = depth[py, px]
                seen = np.isfinite(dz) & (z[idx] <= dz + np.maximum(0.3, 0.01 * dz))
                idx = idx[seen]
                best[idx], best_score[idx] = k, score[idx]
            if progress is not None:
                progress.update(1)
    finally:
        r.release()
    best = np.where(best >= 0, best, any_best)
    return names, best


def textured_parts(V: np.ndarray, F: np.ndarray, views: dict[str, View], names: list[str], best: np.ndarray,
                   load_rgb, pad: int = 2) -> list[MeshPart]:
    """One textured part per photo that textures any face (``load_rgb(view)`` gives its undistorted RGB)."""
    parts = []
    for k in np.unique(best[best >= 0]):
        v = views[names[k]]
        f = F[best == k]
        used = np.unique(f)
        remap = np.full(len(V), -1, np.int64)
        remap[used] = np.arange(len(used))
        uv, _ = _project(v, V[used])
        uv = np.clip(uv, -0.5, [v.width - 0.5, v.height - 0.5])
        x0 = int(max(0, np.floor(uv[:, 0].min() + 0.5) - pad))
        y0 = int(max(0, np.floor(uv[:, 1].min() + 0.5) - pad))
        x1 = int(min(v.width, np.ceil(uv[:, 0].max() + 0.5) + pad))
        y1 = int(min(v.height, np.ceil(uv[:, 1].max() + 0.5) + pad))
        img = load_rgb(v)[y0:y1, x0:x1]
        cw, ch = x1 - x0, y1 - y0
        tuv = np.stack([(uv[:, 0] + 0.5 - x0) / cw, 1.0 - (uv[:, 1] + 0.5 - y0) / ch], 1)
        parts.append(MeshPart(V[used], remap[f], uv=tuv, texture=np.ascontiguousarray(img),
                              name=v.name.replace("/", "_").rsplit(".", 1)[0]))
    unseen = F[best < 0]
    if len(unseen):
        used = np.unique(unseen)
        remap = np.full(len(V), -1, np.int64)
        remap[used] = np.arange(len(used))
        parts.append(MeshPart(V[used], remap[unseen], colors=np.full((len(used), 3), 128, np.uint8), name="unseen"))
    return parts
