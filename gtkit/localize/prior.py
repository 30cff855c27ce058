"""Sensor priors: the rotation prior filter for retrieval (UAVD4L eq. 3.1) and the GPS radius.

A database view survives when each of its DJI angles (yaw, pitch, roll) differs from the
query's IMU/gimbal prior by at most ``gamma_o`` degrees, angles wrapped into (-180, 180].
The database's own angles are the exact ones it was rendered with (see
:mod:`gtkit.localize.grid`); the query's come from its DJI XMP gimbal tags.

At nadir (pitch -90) yaw and roll describe the same in-plane rotation; both the database and
DJI photos write roll 0 there, so comparing the angles as given stays meaningful.
"""
from __future__ import annotations

import numpy as np

from ..conventions import wrap_deg


def angle_differences(prior_ypr, views_ypr: np.ndarray) -> np.ndarray:
    """(N, 3) absolute wrapped differences (deg) between a prior (yaw, pitch, roll) and views."""
    d = np.asarray(views_ypr, dtype=np.float64) - np.asarray(prior_ypr, dtype=np.float64)[None]
    return np.abs(wrap_deg(d))


def rotation_filter(prior_ypr, views_ypr: np.ndarray, gamma_o: float = 30.0) -> np.ndarray:
    """Boolean mask of the views within ``gamma_o`` degrees of the prior on every angle."""
    if len(views_ypr) == 0:
        return np.zeros(0, bool)
    return (angle_differences(prior_ypr, views_ypr) <= gamma_o).all(axis=1)


def gps_filter(prior_xy, view_centers: np.ndarray, radius_m: float) -> np.ndarray:
    """Boolean mask of the views whose camera centre lies within ``radius_m`` (horizontal)."""
    c = np.asarray(view_centers, dtype=np.float64)[:, :2]
    return np.linalg.norm(c - np.asarray(prior_xy, dtype=np.float64)[None, :2], axis=1) <= radius_m


def look_at_points(centers: np.ndarray, axes: np.ndarray, ground_z: float, max_dist: float = 300.0) -> np.ndarray:
    """(N, 2) horizontal points where each camera's optical axis meets the plane ``z = ground_z``.

    ``axes`` are the optical axes in the world (unit, camera +z). The ground distance is capped at
    ``max_dist`` metres (an axis near the horizon, or one pointing up, lands ``max_dist`` ahead
    along its horizontal direction; a vertical axis lands below the camera).
    """
    c = np.atleast_2d(np.asarray(centers, dtype=np.float64))
    a = np.atleast_2d(np.asarray(axes, dtype=np.float64))
    h = np.maximum(c[:, 2] - ground_z, 0.0)
    hxy = np.linalg.norm(a[:, :2], axis=1)
    down = -a[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.where(down > 1e-9, h * hxy / np.maximum(down, 1e-9), np.inf)
    dist = np.minimum(dist, max_dist)
    unit = np.where(hxy[:, None] > 1e-12, a[:, :2] / np.maximum(hxy, 1e-12)[:, None], 0.0)
    return c[:, :2] + unit * dist[:, None]


def footprint_filter(prior_look_at, views_look_at: np.ndarray, radius_m: float) -> np.ndarray:
    """Boolean mask of the views whose look-at point lies within ``radius_m`` of the prior's.

    Comparing where the cameras *look* rather than where they *are* lets a 60 m oblique query meet
    a 100 m or 150 m database view of the same ground, whose camera centres lie tens of metres apart.
    """
    d = np.asarray(views_look_at, dtype=np.float64)[:, :2] - np.asarray(prior_look_at, dtype=np.float64)[None, :2]
    return np.linalg.norm(d, axis=1) <= radius_m


def predicted_overlap(center, R, camera, view_R: np.ndarray, view_t: np.ndarray, view_camera, ground_z: float,
                      grid: tuple[int, int] = (16, 12), max_dist: float = 600.0,
                      angle_deg: tuple[float, float] | None = None) -> np.ndarray:
    """(N,) share of the ground the query would see from its prior pose that each view sees.

    The prior pose (camera ``center`` in the world, world-to-camera rotation ``R``, intrinsics
    ``camera``) casts a ``grid`` of rays onto the plane ``z = ground_z``; each view (world-to-camera
    ``view_R`` (N, 3, 3), ``view_t`` (N, 3), intrinsics ``view_camera``) scores the share of those
    ground points inside its image and in front of it. Rays above the horizon or farther than
    ``max_dist`` do not count. It predicts, from the sensors alone, the overlap that retrieval is
    judged by (the share of the query's surface a view sees); 0 for every view when no ray meets
    the ground.

    With ``angle_deg = (full, zero)`` each ground point counts only as far as the view sees it from
    the query's direction: fully when the two rays meet the point within ``full`` degrees, not at all
    beyond ``zero``, linearly between ("matchable" overlap). SIFT matches fade with the viewpoint
    change: on the medium sample (seed 5) every query whose three best views by plain overlap saw its
    ground from 23-34 deg away (far views at the database's 70 deg level, 250-430 m off) failed PnP
    (3-19 inliers of 120-320 matches); views within ~15 deg localized.
    """
    gw, gh = grid
    u = (np.arange(gw) + 0.5) * camera.width / gw
    v = (np.arange(gh) + 0.5) * camera.height / gh
    uv = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    rays = camera.rays(uv) @ np.asarray(R, dtype=np.float64)  # camera -> world directions (R^T d)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (ground_z - c[2]) / rays[:, 2]
    ok = (rays[:, 2] < -1e-6) & (s > 0) & (s <= max_dist)
    if not ok.any() or len(view_R) == 0:
        return np.zeros(len(view_R))
    P = c[None] + s[ok, None] * rays[ok]                                  # (M, 3) ground points
    pc = np.einsum("nij,mj->nmi", np.asarray(view_R, dtype=np.float64), P) + np.asarray(view_t)[:, None, :]
    uv_v, front = view_camera.project(pc)
    inside = front & view_camera.in_image(uv_v)
    if angle_deg is None:
        return inside.mean(axis=1)
    full, zero = angle_deg
    VR, Vt = np.asarray(view_R, dtype=np.float64), np.asarray(view_t, dtype=np.float64)
    centres = -np.einsum("nji,nj->ni", VR, Vt)                            # view camera centres (N, 3)
    dq = rays[ok]                                                          # unit rays of the query to P
    dv = P[None] - centres[:, None, :]
    dv /= np.linalg.norm(dv, axis=2, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.einsum("nmi,mi->nm", dv, dq), -1.0, 1.0)))
    w = np.clip((zero - ang) / max(zero - full, 1e-9), 0.0, 1.0)
    return (inside * w).mean(axis=1)
