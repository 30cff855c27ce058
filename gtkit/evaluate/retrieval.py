"""Retrieval against truth: overlap between a query and a database view, R@k and P@k.

Overlap (UAVD4L §5.1): the query's visible surface is taken from its depth rendered at the
*true* pose with the reference model; those points are projected into the database view and a
point counts as seen when it falls inside the view and agrees with the view's own rendered depth
(within ``rel_tol``, so occluded points do not count). Overlap = seen / visible query points.
A retrieved view is correct when the overlap exceeds 50%.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..conventions import index_to_pixel
from ..pose import Pose


def surface_points(camera: Camera, pose: Pose, depth: np.ndarray, step: int = 4) -> np.ndarray:
    """World points of every ``step``-th pixel with valid depth (N, 3)."""
    ii, jj = np.mgrid[0:depth.shape[0]:step, 0:depth.shape[1]:step]
    d = depth[ii, jj].astype(np.float64)
    ok = np.isfinite(d)
    uv = index_to_pixel(np.stack([jj[ok], ii[ok]], axis=-1).astype(np.float64))
    xn = camera.image_to_world(uv)
    pc = np.concatenate([xn, np.ones((len(xn), 1))], axis=1) * d[ok][:, None]
    return (pc - pose.t) @ pose.R


def seen_fraction(points: np.ndarray, camera: Camera, pose: Pose, depth: np.ndarray | None,
                  rel_tol: float = 0.05) -> float:
    """Share of world ``points`` that the view (camera, pose, rendered depth) sees."""
    if len(points) == 0 or depth is None:
        return 0.0
    pc = pose.transform(points)
    uv, front = camera.project(pc)
    H, W = depth.shape
    j = np.floor(uv[:, 0]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, int)
    i = np.floor(uv[:, 1]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, int)
    inside = front & (j >= 0) & (j < W) & (i >= 0) & (i < H)
    seen = np.zeros(len(points), bool)
    d = depth[i[inside], j[inside]]
    z = pc[inside, 2]
    with np.errstate(invalid="ignore"):
        seen[inside] = np.isfinite(d) & (np.abs(d - z) <= rel_tol * z)
    return float(seen.mean())


def retrieval_metrics(retrieved: dict[str, list[str]], correct: dict[tuple[str, str], bool],
                      ks=(1, 3), precision_k: int = 3) -> dict[str, float]:
    """R@k: share of queries with a correct view among the first k; P@k: mean share of correct
    views among the first k (absent ranks count as wrong). Queries with nothing retrieved fail."""
    n = max(len(retrieved), 1)
    out = {}
    for k in ks:
        out[f"retrieval_R{k}"] = sum(any(correct.get((q, v), False) for v in vs[:k])
                                     for q, vs in retrieved.items()) / n
    out[f"retrieval_P{precision_k}"] = sum(sum(correct.get((q, v), False) for v in vs[:precision_k]) / precision_k
                                           for q, vs in retrieved.items()) / n
    return out
