"""Small geometry on top of pycolmap models: poses/cameras out of a model, multi-view
triangulation of clicked pixels (with outlier rejection), and robust Sim(3)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.optimize import least_squares

from ..camera import Camera
from ..pose import Pose


class RegistrationError(Exception):
    """A block or sequence that cannot be registered; ``str`` is the reason."""


# --- models ------------------------------------------------------------------------------

def model_poses(rec: pycolmap.Reconstruction) -> dict[str, Pose]:
    return {im.name: Pose.from_pycolmap(im.cam_from_world()) for im in rec.images.values() if im.has_pose}


def model_cameras(rec: pycolmap.Reconstruction) -> dict[str, Camera]:
    return {im.name: Camera.from_pycolmap(rec.cameras[im.camera_id])
            for im in rec.images.values() if im.has_pose}


def model_points(rec: pycolmap.Reconstruction) -> np.ndarray:
    return np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)


def sim3_apply(sim: pycolmap.Sim3d, xyz: np.ndarray) -> np.ndarray:
    m = sim.matrix()
    return np.asarray(xyz, float) @ m[:3, :3].T + m[:3, 3]


# --- triangulation -------------------------------------------------------------------------

def reprojection_px(xyz: np.ndarray, cams: list[Camera], poses: list[Pose], uv: np.ndarray) -> np.ndarray:
    res = np.empty(len(cams))
    for k, (c, p) in enumerate(zip(cams, poses)):
        pc = p.transform(xyz[None])
        if pc[0, 2] <= 1e-6:
            res[k] = np.inf
            continue
        proj, _ = c.project(pc)
        res[k] = np.linalg.norm(proj[0] - uv[k])
    return res


def _triangulate_all(cams, poses, uv) -> np.ndarray | None:
    A = []
    for c, p, x in zip(cams, poses, uv):
        xn = c.image_to_world(np.asarray(x, float)[None])[0]
        P = p.matrix[:3]
        A.append(xn[0] * P[2] - P[0])
        A.append(xn[1] * P[2] - P[1])
    _, _, vt = np.linalg.svd(np.asarray(A))
    X = vt[-1]
    if abs(X[3]) < 1e-12:
        return None
    X = X[:3] / X[3]

    def fun(x):
        r = []
        for c, p, u in zip(cams, poses, uv):
            pc = p.transform(x[None])
            z = max(pc[0, 2], 1e-6)
            proj = c.world_to_image(pc[:, :2] / z)[0]
            r.extend(proj - u)
        return np.asarray(r)

    return least_squares(fun, X, method="lm").x


def triangulation_angle_deg(xyz, poses: list[Pose]) -> float:
    rays = [xyz - p.center for p in poses]
    rays = [r / np.linalg.norm(r) for r in rays]
    best = 0.0
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            best = max(best, np.degrees(np.arccos(np.clip(rays[i] @ rays[j], -1, 1))))
    return float(best)


@dataclass
class Triangulated:
    xyz: np.ndarray | None
    used: np.ndarray          # bool per observation
    residuals_px: np.ndarray  # per observation (inf where behind the camera)
    angle_deg: float = 0.0
    reason: str = ""


def triangulate_clicks(cams: list[Camera], poses: list[Pose], uv: np.ndarray, max_px: float = 4.0,
                       min_angle_deg: float = 1.0) -> Triangulated:
    """Triangulate one point from clicks in >= 2 posed images. Drops the worst click while the
    largest reprojection residual exceeds ``max_px`` and >= 2 clicks remain (gross mistakes)."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    n = len(cams)
    used = np.ones(n, bool)
    if n < 2:
        return Triangulated(None, np.zeros(n, bool), np.full(n, np.inf), 0.0, "fewer than 2 clicks in posed images")
    while True:
        idx = np.flatnonzero(used)
        best = None
        if used.sum() >= 3:  # leave-one-out: the subset whose worst residual is smallest
            for drop in [None, *idx]:
                keep = [i for i in idx if i != drop]
                X = _triangulate_all([cams[i] for i in keep], [poses[i] for i in keep], uv[keep])
                if X is None:
                    continue
                r = reprojection_px(X, [cams[i] for i in keep], [poses[i] for i in keep], uv[keep]).max()
                if best is None or r < best[0] - 1e-9:
                    best = (r, X, drop)
                if drop is None and r <= max_px:
                    break
        else:
            X = _triangulate_all([cams[i] for i in idx], [poses[i] for i in idx], uv[idx])
            best = (0.0, X, None)
        X = best[1] if best else None
        if X is None:
            return Triangulated(None, used, np.full(n, np.inf), 0.0, "degenerate rays")
        res = reprojection_px(X, cams, poses, uv)
        if res[used].max() <= max_px:
            ang = triangulation_angle_deg(X, [poses[i] for i in np.flatnonzero(used)])
            if ang < min_angle_deg:
                return Triangulated(None, used, res, ang, f"rays nearly parallel ({ang:.2f} deg)")
            return Triangulated(X, used, res, ang)
        if used.sum() <= 2:
            return Triangulated(None, used, res, 0.0,
                                f"clicks disagree (reprojection {res[used].max():.1f} px > {max_px} px)")
        drop = best[2] if best[2] is not None else idx[np.argmax(res[idx])]
        used[drop] = False


# --- robust similarity ------------------------------------------------------------------------

@dataclass
class Sim3Fit:
    tgt_from_src: pycolmap.Sim3d
    inliers: np.ndarray        # bool
    residuals_m: np.ndarray    # |sim(src) - tgt| per point
    rmse_inliers_m: float
    thresholds_m: np.ndarray | None = None  # inlier threshold per point, as finally used


def robust_sim3(src: np.ndarray, tgt: np.ndarray, max_error_m, what: str = "points", *,
                adaptive=None, floors=None, groups=None) -> Sim3Fit:
    """LO-RANSAC Sim(3) tgt_from_src (gtkit.sfm.similarity: Umeyama, no coplanarity failure);
    ``max_error_m`` a threshold or one per point. Raises :class:`RegistrationError` with the reason."""
    from .similarity import collinearity, lo_ransac_similarity

    src, tgt = np.asarray(src, float).reshape(-1, 3), np.asarray(tgt, float).reshape(-1, 3)
    if len(src) < 3:
        raise RegistrationError(f"only {len(src)} usable {what} (3 or more needed)")
    if collinearity(src) < 1e-3 or collinearity(tgt) < 1e-3:
        raise RegistrationError(f"the {len(src)} usable {what} are collinear (or coincide): "
                                "a similarity transform is undetermined")
    th = np.broadcast_to(np.asarray(max_error_m, float), (len(src),)).copy()
    fit = lo_ransac_similarity(src, tgt, th,
                               adaptive=None if adaptive is None else np.asarray(adaptive, bool),
                               floors=floors, groups=groups)
    if fit is None:
        raise RegistrationError(f"Sim(3) RANSAC found no consistent transform for {len(src)} {what}")
    inl = fit.inliers
    if inl.sum() < 3:
        raise RegistrationError(f"Sim(3) has only {int(inl.sum())} inliers among {len(src)} {what} "
                                f"(threshold {float(np.median(fit.thresholds)):.2f} m)")
    if collinearity(src[inl]) < 1e-3:
        raise RegistrationError(f"the Sim(3) inliers among the {what} are collinear")
    sim = pycolmap.Sim3d(fit.sim.scale, pycolmap.Rotation3d(fit.sim.R), fit.sim.t)
    r = fit.residuals
    return Sim3Fit(sim, inl, r, float(np.sqrt(np.mean(r[inl] ** 2))), fit.thresholds)
