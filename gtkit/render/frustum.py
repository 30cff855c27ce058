"""Which boxes a perspective view can see, and the near/far planes for a view of a box: shared by
the renderer (parts outside the frustum are not drawn) and the tile streamer (tiles outside it are
not loaded). A box is dropped only when all eight corners are outside one plane of the frustum, so
the test never loses a visible box."""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..pose import Pose


def near_far(bounds: np.ndarray, pose: Pose) -> tuple[float, float]:
    """Near/far planes for a view of a box, chosen as the renderer chooses them for its mesh."""
    lo, hi = bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    z = pose.transform(corners)[:, 2]
    far = max(float(z.max()) * 1.01, 1.0)
    c = pose.center
    dist = float(np.linalg.norm(np.maximum(0, np.maximum(lo - c, c - hi))))
    near = float(np.clip(dist * 0.9, 0.05, far / 10.0))
    return near, far


def boxes_in_frustum(boxes: np.ndarray, camera: Camera, pose: Pose, margin: float = 0.05,
                     far: float | None = None) -> np.ndarray:
    """(N, 2, 3) world boxes -> (N,) bool: may the box be seen by the camera?

    ``margin`` widens the image by that fraction on every side (covers lens distortion)."""
    lo, hi = boxes[:, 0], boxes[:, 1]
    sel = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]])
    corners = np.where(sel[None, :, :] == 0, lo[:, None, :], hi[:, None, :])  # (N, 8, 3)
    pc = corners @ pose.R.T + pose.t
    x, y, z = pc[..., 0], pc[..., 1], pc[..., 2]
    W, H = camera.width, camera.height
    u0, u1 = -margin * W, (1 + margin) * W
    v0, v1 = -margin * H, (1 + margin) * H
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    # u = fx x/z + cx >= u0  <=>  fx x + (cx - u0) z >= 0 (z > 0), and so on
    planes = [z - 1e-6,
              fx * x + (cx - u0) * z, (u1 - cx) * z - fx * x,
              fy * y + (cy - v0) * z, (v1 - cy) * z - fy * y]
    if far is not None:
        planes.append(far - z)
    outside = np.zeros(len(boxes), bool)
    for d in planes:
        outside |= np.all(d < 0, axis=1)
    return ~outside


def ray_box_fraction(camera: Camera, pose: Pose, boxes: np.ndarray, grid: tuple[int, int] = (40, 30),
                     chunk: int = 16) -> float:
    """The share of a ``grid`` of the camera's pixel rays (pinhole) that meet at least one of the
    (N, 2, 3) world ``boxes`` in front of the camera: an upper bound of the share of pixels that see
    a surface inside the boxes (up to the grid's sampling), at no rendering cost.

    Boxes outside the view's frustum are skipped (no ray of the grid can meet them), the rest are
    tested largest first, ``chunk`` at a time, against the rays no box has met yet: a model of
    hundreds of overlapping part boxes (a photo-built model, a part per photo) costs about what a
    few boxes do."""
    nu, nv = grid
    u = (np.arange(nu) + 0.5) * camera.width / nu
    v = (np.arange(nv) + 0.5) * camera.height / nv
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones_like(uu)], -1)
    d = rays.reshape(-1, 3) @ pose.R          # camera -> world directions (R^T x)
    c = pose.center
    boxes = np.asarray(boxes, float).reshape(-1, 2, 3)
    boxes = boxes[boxes_in_frustum(boxes, camera, pose, margin=0.0)]
    boxes = boxes[np.argsort(-np.prod(boxes[:, 1] - boxes[:, 0], axis=1), kind="stable")]
    hit = np.zeros(len(d), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for k in range(0, len(boxes), chunk):
            todo = np.flatnonzero(~hit)
            if not len(todo):
                break
            b = boxes[k:k + chunk]
            t0 = (b[None, :, 0, :] - c) * inv[todo, None, :]
            t1 = (b[None, :, 1, :] - c) * inv[todo, None, :]
            # slab test; an axis the ray is parallel to gives NaN/inf and is decided by the others
            enter = np.nanmax(np.minimum(t0, t1), axis=2)
            leave = np.nanmin(np.maximum(t0, t1), axis=2)
            hit[todo] = (leave >= np.maximum(enter, 0.0)).any(axis=1)
    return float(hit.mean())
