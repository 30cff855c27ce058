"""Small geometry on top of pycolmap models: poses/cameras out of a model, multi-view
triangulation of clicked pixels (with outlier rejection), and robust Sim(3)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.optimize import least_squares

from ..camera import Camera, distort
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


def _cam_arrays(cams: list[Camera]) -> np.ndarray:
    """(n, 8): fx, fy, cx, cy, k1, k2, p1, p2 of each camera."""
    return np.array([[c.fx, c.fy, c.cx, c.cy, *c.distortion] for c in cams], float).reshape(-1, 8)


def _pixels_many(X: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points X (N, 3) seen by cameras (N, k): pixels (N, k, 2) and depth (N, k)."""
    pc = np.einsum("nkij,nj->nki", R, X) + t
    z = pc[..., 2]
    xn = pc[..., :2] / np.where(z > 1e-6, z, 1e-6)[..., None]
    xd = distort(xn, K[..., 4:])
    return np.stack([K[..., 0] * xd[..., 0] + K[..., 2], K[..., 1] * xd[..., 1] + K[..., 3]], axis=-1), z


def _solve_masked(R, t, K, uv, mask, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """One point per row from the observations ``mask`` keeps (DLT, then Gauss-Newton on the pixel
    residuals, forward-difference Jacobian), all rows at once. Returns (X (M, 3), ok (M,))."""
    w = mask.astype(float)
    xd = np.stack([(uv[..., 0] - K[..., 2]) / K[..., 0], (uv[..., 1] - K[..., 3]) / K[..., 1]], axis=-1)
    xn = xd.copy()
    with np.errstate(all="ignore"):
        for _ in range(20):  # undistorted normalised coordinates (fixed point, as Camera.image_to_world)
            xn = xn - (distort(xn, K[..., 4:]) - xd)
        P = np.concatenate([R, t[..., None]], axis=-1)
        A = np.concatenate([(xn[..., 0:1] * P[:, :, 2] - P[:, :, 0]) * w[..., None],
                            (xn[..., 1:2] * P[:, :, 2] - P[:, :, 1]) * w[..., None]], axis=1)
        finite = np.all(np.isfinite(A), axis=(1, 2))   # a click far outside a distorted view
        _, _, vt = np.linalg.svd(np.where(finite[:, None, None], A, 1.0))
        Xh = vt[:, -1]
        ok = finite & (np.abs(Xh[:, 3]) > 1e-12)
        X = Xh[:, :3] / np.where(ok, Xh[:, 3], 1.0)[:, None]
        m = len(X)
        for _ in range(iterations):
            r0 = ((_pixels_many(X, R, t, K)[0] - uv) * w[..., None]).reshape(m, -1)
            h = 1e-6 * np.maximum(1.0, np.abs(X))
            J = np.stack([(((_pixels_many(X + h[:, j:j + 1] * np.eye(3)[j], R, t, K)[0] - uv) * w[..., None]).reshape(m, -1)
                           - r0) / h[:, j:j + 1] for j in range(3)], axis=-1)
            good = np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(r0), axis=1)
            J, r0 = np.where(good[:, None, None], J, 0.0), np.where(good[:, None], r0, 0.0)
            X = X - np.einsum("nij,nj->ni", np.linalg.pinv(np.einsum("nri,nrj->nij", J, J)), np.einsum("nri,nr->ni", J, r0))
    return X, ok & np.all(np.isfinite(X), axis=1)


def _residuals_masked(X, R, t, K, uv) -> np.ndarray:
    with np.errstate(all="ignore"):
        px, z = _pixels_many(X, R, t, K)
        return np.where(z > 1e-6, np.linalg.norm(px - uv, axis=-1), np.inf)


def triangulate_many(tracks: list[tuple[list[Camera], list[Pose], np.ndarray]], max_px: float = 4.0,
                     min_angle_deg: float = 1.0) -> list[Triangulated]:
    """:func:`triangulate_clicks` for many points at once (the joint BA's thousands of tie points):
    the same steps (all clicks; while the worst residual exceeds ``max_px``, the leave-one-out subset
    whose worst residual is smallest, then drop a click) run on every point together, vectorised."""
    n = len(tracks)
    out: list[Triangulated | None] = [None] * n
    if n == 0:
        return out
    kmax = max(len(c) for c, _, _ in tracks)
    R = np.tile(np.eye(3), (n, kmax, 1, 1))
    t = np.zeros((n, kmax, 3))
    t[..., 2] = 1.0
    K = np.tile(np.array([1.0, 1.0, 0, 0, 0, 0, 0, 0]), (n, kmax, 1))
    uv = np.zeros((n, kmax, 2))
    valid = np.zeros((n, kmax), bool)
    for i, (cams, poses, x) in enumerate(tracks):
        k = len(cams)
        if k:
            R[i, :k] = [p.R for p in poses]
            t[i, :k] = [p.t for p in poses]
            K[i, :k] = _cam_arrays(cams)
            uv[i, :k] = np.asarray(x, float).reshape(k, 2)
            valid[i, :k] = True
    used = valid.copy()
    for i in np.flatnonzero(valid.sum(1) < 2):
        out[i] = Triangulated(None, np.zeros(valid[i].sum(), bool), np.full(valid[i].sum(), np.inf), 0.0,
                              "fewer than 2 clicks in posed images")
    active = np.flatnonzero(valid.sum(1) >= 2)

    def finish(i, X, res, reason=""):
        k = valid[i].sum()
        out[i] = Triangulated(X, used[i, :k].copy(), res[:k].copy(), 0.0 if X is None else
                              triangulation_angle_deg(X, [tracks[i][1][j] for j in np.flatnonzero(used[i, :k])]), reason)
        if X is not None and out[i].angle_deg < min_angle_deg:
            out[i] = Triangulated(None, out[i].used, out[i].residuals_px, out[i].angle_deg,
                                  f"rays nearly parallel ({out[i].angle_deg:.2f} deg)")

    while len(active):
        # every point from all the clicks it still uses
        X0, ok0 = _solve_masked(R[active], t[active], K[active], uv[active], used[active])
        res0 = _residuals_masked(X0, R[active], t[active], K[active], uv[active])
        worst0 = np.where(used[active], res0, -np.inf).max(1)
        n_used = used[active].sum(1)
        best_x, best_drop, ok_best = X0.copy(), np.full(len(active), -1), ok0.copy()
        # where that is not good enough and 3+ clicks remain: each leave-one-out subset
        loo = np.flatnonzero((n_used >= 3) & ~(ok0 & (worst0 <= max_px)))
        if len(loo):
            rows, drops = [], []
            for a in loo:
                for j in np.flatnonzero(used[active[a]]):
                    rows.append(a)
                    drops.append(j)
            rows, drops = np.array(rows), np.array(drops)
            ii = active[rows]
            m = used[ii].copy()
            m[np.arange(len(rows)), drops] = False
            Xc, okc = _solve_masked(R[ii], t[ii], K[ii], uv[ii], m)
            wc = np.where(m, _residuals_masked(Xc, R[ii], t[ii], K[ii], uv[ii]), -np.inf).max(1)
            for a in loo:
                sel = np.flatnonzero(rows == a)
                best = (worst0[a], X0[a], -1) if ok0[a] else None
                for c in sel:  # in the order triangulate_clicks tries them: the first of equals wins
                    if okc[c] and (best is None or wc[c] < best[0] - 1e-9):
                        best = (wc[c], Xc[c], drops[c])
                if best is None:
                    ok_best[a] = False
                else:
                    ok_best[a], best_x[a], best_drop[a] = True, best[1], best[2]
        res = _residuals_masked(best_x, R[active], t[active], K[active], uv[active])
        still = []
        for a, i in enumerate(active):
            if not ok_best[a]:
                finish(i, None, np.full(kmax, np.inf), "degenerate rays")
                continue
            worst = res[a][used[i]].max()
            if worst <= max_px:
                finish(i, best_x[a].copy(), res[a])
            elif n_used[a] <= 2:
                finish(i, None, res[a], f"clicks disagree (reprojection {worst:.1f} px > {max_px} px)")
            else:
                j = best_drop[a] if best_drop[a] >= 0 else np.flatnonzero(used[i])[np.argmax(res[a][used[i]])]
                used[i, j] = False
                still.append(i)
        active = np.array(still, int)
    return out


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
