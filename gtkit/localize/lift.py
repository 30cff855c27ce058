"""2D-3D lifting: database keypoints -> world points through the rendered depth map.

Depth is sampled bilinearly at the keypoint (pixel convention of :mod:`gtkit.conventions`:
``pixel_to_index`` gives the continuous array position, integers at pixel centres). A point is
kept only when all four neighbouring depths are valid (not background) and agree within
``max_rel_jump`` (relative), so keypoints on depth discontinuities (roof edges, the horizon) are
rejected instead of being placed between the two surfaces.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..conventions import pixel_to_index
from ..pose import Pose


def sample_depth(depth: np.ndarray, uv: np.ndarray, max_rel_jump: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear depth at pixels ``uv`` (N, 2); returns (depth, ok)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    H, W = depth.shape
    ij = pixel_to_index(uv)
    x0 = np.floor(ij[:, 0]).astype(int)
    y0 = np.floor(ij[:, 1]).astype(int)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < W) & (y0 + 1 < H)
    out = np.full(len(uv), np.nan)
    ok = np.zeros(len(uv), bool)
    if not inside.any():
        return out, ok
    xs, ys = x0[inside], y0[inside]
    fx, fy = ij[inside, 0] - xs, ij[inside, 1] - ys
    d00, d01 = depth[ys, xs], depth[ys, xs + 1]
    d10, d11 = depth[ys + 1, xs], depth[ys + 1, xs + 1]
    q = np.stack([d00, d01, d10, d11], axis=1).astype(np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(q).all(1) & (q.min(1) > 0)
        valid &= (q.max(1) - q.min(1)) <= max_rel_jump * q.min(1)
    d = (d00 * (1 - fx) * (1 - fy) + d01 * fx * (1 - fy) + d10 * (1 - fx) * fy + d11 * fx * fy)
    out[inside] = np.where(valid, d, np.nan)
    ok[inside] = valid
    return out, ok


def lift(uv: np.ndarray, depth: np.ndarray, camera: Camera, pose: Pose,
         max_rel_jump: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) for pixels ``uv`` of a rendered view, and the mask of valid ones."""
    d, ok = sample_depth(depth, uv, max_rel_jump)
    xn = camera.image_to_world(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    pc = np.concatenate([xn, np.ones((len(xn), 1))], axis=1) * d[:, None]
    X = (pc - pose.t) @ pose.R  # R^T (x_cam - t)
    return X, ok
