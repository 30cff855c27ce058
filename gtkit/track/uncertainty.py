"""Uncertainty of a target's ground point, propagated from the wide pose's covariance.

The ground point is a non-smooth function of the pose (the ray may slide off a roof onto the
street), so the propagation is by sampling, not by a Jacobian: draw poses from the pose's
Gaussian, add the rig's rotation uncertainty and the detection's pixel noise, cast every
sampled ray on the same DSM (the marcher is vectorised, so 200 samples per target cost a few
milliseconds) and take the covariance of the points that hit.

Pose covariance convention (as :class:`gtkit.pose.Pose` documents, pycolmap's): 6x6 over
(rotation vector, translation) of the world-to-camera pose, applied as
``R' = exp(dr) @ R``, ``t' = t + dt`` (a left, camera-frame perturbation). When a pose has no
covariance, a diagonal default is used: ``sigma_rot_deg`` per axis and ``sigma_pos_m`` per axis
of the camera *centre* (the settings state both).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..pose import Pose
from .raycast import cast_rays


@dataclass
class UncertaintySettings:
    samples: int = 200            # Monte-Carlo samples per target
    sigma_rot_deg: float = 0.2    # default per-axis rotation sigma of a pose without covariance
    sigma_pos_m: float = 0.5      # default per-axis camera-centre sigma of a pose without covariance
    sigma_px: float = 2.0         # detection noise of the foot point (zoom pixels, per axis)
    seed: int = 0


def pose_samples(pose: Pose, n: int, s: UncertaintySettings, rng) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) rotations and (n, 3) centres drawn around ``pose``."""
    if pose.covariance is not None:
        cov = 0.5 * (pose.covariance + pose.covariance.T)
        w, V = np.linalg.eigh(cov)
        d = rng.standard_normal((n, 6)) * np.sqrt(np.clip(w, 0, None)) @ V.T
        dR = Rotation.from_rotvec(d[:, :3]).as_matrix()
        R = dR @ pose.R
        t = pose.t + d[:, 3:]
        C = -np.einsum("nji,nj->ni", R, t)
    else:
        dr = rng.standard_normal((n, 3)) * np.radians(s.sigma_rot_deg)
        R = Rotation.from_rotvec(dr).as_matrix() @ pose.R
        C = pose.center + rng.standard_normal((n, 3)) * s.sigma_pos_m
    return R, C


def ground_point_covariance(dsm, wide: Pose, rig, zoom_cam, uv, s: UncertaintySettings,
                            rig_sigma_deg: float = 0.0) -> dict:
    """Sample the ground point of pixel ``uv`` of the zoom camera. Returns ``cov`` (3x3 or
    None), ``hit_share`` (share of samples that met the DSM) and sigmas in metres."""
    rng = np.random.default_rng(s.seed)
    n = s.samples
    Rw, Cw = pose_samples(wide, n, s, rng)
    Rzw = rig.R_zw
    if rig_sigma_deg > 0:
        Rzw = Rotation.from_rotvec(rng.standard_normal((n, 3)) * np.radians(rig_sigma_deg)).as_matrix() @ Rzw
    Rz = np.matmul(Rzw, Rw)                                   # zoom world-to-camera
    Cz = Cw + np.einsum("nji,j->ni", Rw, rig.offset)          # zoom centre = C_w + R_w^T offset
    px = np.asarray(uv, float)[None, :] + rng.standard_normal((n, 2)) * s.sigma_px
    rays_cam = zoom_cam.rays(px)
    dirs = np.einsum("nji,nj->ni", Rz, rays_cam)              # R_z^T @ ray
    hits = cast_rays(dsm, Cz, dirs)
    ok = hits.ok
    out = {"hit_share": float(ok.mean()), "cov": None, "sigma_h_m": None, "sigma_z_m": None,
           "sigma_3d_m": None}
    if ok.sum() >= 10:
        P = hits.points[ok]
        cov = np.cov(P.T)
        out.update(cov=cov, sigma_h_m=float(np.sqrt(cov[0, 0] + cov[1, 1])),
                   sigma_z_m=float(np.sqrt(cov[2, 2])), sigma_3d_m=float(np.sqrt(np.trace(cov))))
    return out
