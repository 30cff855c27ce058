"""Placing a query block by its clicked tie points: each tie point placed in the reference block and
in the query block (triangulated from its clicks, or one click lifted with the block's depth), then a
robust Sim(3) between the two; and whether a clicked Sim(3) rests on too little to go unchecked."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ...camera import Camera
from ...io.tiepoints import TiePoint
from ...pose import Pose
from ..geometry import RegistrationError, model_cameras, model_poses, robust_sim3, sim3_apply, triangulate_clicks
from .settings import BootstrapSettings, RegisterSettings


@dataclass
class TieStatus:
    id: str
    ref_xyz: np.ndarray | None = None
    query_xyz: np.ndarray | None = None
    ref_used: list[str] = field(default_factory=list)
    query_used: list[str] = field(default_factory=list)
    dropped_clicks: list[dict] = field(default_factory=list)
    query_from_depth: bool = False
    sim3_residual_m: float | None = None
    inlier: bool = False
    reason: str = ""
    mistake: bool = False      # a gross click mistake was detected (dropped click or Sim(3) outlier)

    def as_dict(self) -> dict:
        return {"id": self.id, "inlier": self.inlier, "reason": self.reason,
                "sim3_residual_m": self.sim3_residual_m, "ref_clicks_used": self.ref_used,
                "query_clicks_used": self.query_used, "dropped_clicks": self.dropped_clicks,
                "query_position_from_model_depth": self.query_from_depth}


def depth_from_model(rec: pycolmap.Reconstruction, name: str, uv: np.ndarray, k: int = 8,
                     max_px: float = 120.0) -> np.ndarray | None:
    """A clicked pixel of a one-click tie point lifted to 3D on the local surface of the block's
    own 3D points observed near the click: a plane through the ``k`` nearest (in the image) where
    they span one, else their median depth; None when there are too few."""
    im = rec.find_image_with_name(name)
    if im is None or not im.has_pose:
        return None
    pts = [(p2.xy, rec.points3D[p2.point3D_id].xyz) for p2 in im.points2D if p2.has_point3D()]
    if len(pts) < 3:
        return None
    xy = np.array([p[0] for p in pts])
    d = np.linalg.norm(xy - uv, axis=1)
    near = np.argsort(d)[:k]
    near = near[d[near] <= max_px]
    if len(near) < 3:
        return None
    pose = Pose.from_pycolmap(im.cam_from_world())
    cam = Camera.from_pycolmap(rec.cameras[im.camera_id])
    Xc = pose.transform(np.array([pts[i][1] for i in near]))          # camera frame
    ray = np.append(cam.image_to_world(uv[None])[0], 1.0)               # z = 1
    depth = float(np.median(Xc[:, 2]))
    c = Xc.mean(0)
    _, sv, vt = np.linalg.svd(Xc - c)
    n = vt[-1]
    if len(near) >= 4 and sv[1] > 0.2 * sv[0] and abs(n @ ray) > 1e-6:
        t = float(n @ c / (n @ ray))                                    # ray-plane intersection
        if 0.5 * Xc[:, 2].min() < t < 2.0 * Xc[:, 2].max():
            depth = t
    return pose.R.T @ (ray * depth - pose.t)


def _triangulate(tp_obs, poses, cams, max_px):
    obs = [o for o in tp_obs if o.image in poses]
    tri = triangulate_clicks([cams[o.image] for o in obs], [poses[o.image] for o in obs],
                             np.array([[o.x, o.y] for o in obs]).reshape(-1, 2), max_px=max_px)
    used = [o for o, u in zip(obs, tri.used) if u]
    dropped = [{"image": o.image, "x": o.x, "y": o.y, "residual_px": float(r)}
               for o, u, r in zip(obs, tri.used, tri.residuals_px) if not u]
    return tri, obs, used, dropped


def _place(obs, poses, cams, rec, max_px):
    """A tie point's position in one block from its clicks there: triangulated (>= 2 clicks, mistakes
    dropped) or lifted with the block's depth (1 click). Returns (xyz|None, used, dropped, reason, how)."""
    obs = [o for o in obs if o.image in poses]
    if not obs:
        return None, [], [], "no clicks in registered photos", ""
    if len(obs) == 1:
        X = depth_from_model(rec, obs[0].image, np.array([obs[0].x, obs[0].y]))
        if X is None:
            return None, [], [], "one click and too few block points near it", "depth"
        return X, [obs[0].image], [], "", "depth"
    tri, _, used, dropped = _triangulate(obs, poses, cams, max_px)
    if tri.xyz is None:
        return None, [], dropped, tri.reason, "triangulated"
    return tri.xyz, [o.image for o in used], dropped, "", "triangulated"


def register_sequence(seq: str, qrec: pycolmap.Reconstruction, ref_rec: pycolmap.Reconstruction,
                      tiepoints: list[TiePoint], settings: RegisterSettings,
                      ref_cache: dict | None = None) -> tuple[pycolmap.Sim3d, list[TieStatus]]:
    """Sim(3) of one query block into the reference frame; raises RegistrationError with the reason."""
    qposes, qcams = model_poses(qrec), model_cameras(qrec)
    ref_poses, ref_cams = (ref_cache or {}).get("poses") or model_poses(ref_rec), (ref_cache or {}).get("cams") or model_cameras(ref_rec)
    prefix = f"queries/{seq}/"
    status = []
    for tp in tiepoints:
        qobs = [o for o in tp.in_block(prefix) if o.image in qposes]  # e.g. zoom photos are in no block
        if not qobs:
            continue
        st = TieStatus(tp.id)
        status.append(st)
        X, used, dropped, why, how = _place(tp.in_block("reference/"), ref_poses, ref_cams, ref_rec, settings.tie_max_px)
        st.dropped_clicks += dropped
        st.mistake = bool(dropped) or "disagree" in why
        if X is None:
            st.reason = f"reference: {why}"
            continue
        st.ref_xyz, st.ref_used = X, used
        X, used, dropped, why, how = _place(qobs, qposes, qcams, qrec, settings.tie_max_px)
        st.dropped_clicks += dropped
        st.mistake = st.mistake or bool(dropped) or "disagree" in why
        if X is None:
            st.reason = f"query: {why}"
            continue
        st.query_xyz, st.query_used, st.query_from_depth = X, used, how == "depth"
    usable = [s for s in status if s.ref_xyz is not None and s.query_xyz is not None]
    if len(usable) < settings.min_tiepoints:
        raise RegistrationError(f"only {len(usable)} usable tie points ({len(status)} clicked in this sequence's "
                                f"registered photos; {settings.min_tiepoints} or more non-collinear ones needed)")
    fit = robust_sim3(np.array([s.query_xyz for s in usable]), np.array([s.ref_xyz for s in usable]),
                      settings.sim3_max_error_m, what="tie points")
    for s, r, ok in zip(usable, fit.residuals_m, fit.inliers):
        s.sim3_residual_m, s.inlier = float(r), bool(ok)
        if not ok:
            s.reason, s.mistake = f"Sim(3) outlier ({r:.2f} m from the fit)", True
    return fit.tgt_from_src, status



def weak_click_support(st: list[TieStatus], b: BootstrapSettings) -> str | None:
    """Why a clicked Sim(3) rests on too little to go unchecked (fewer than ``b.check_clicks_below``
    inlier tie points, or all of them in one query photo), else None. 0 turns the check off."""
    if b.check_clicks_below <= 0:
        return None
    inl = [s for s in st if s.inlier]
    photos = {n for s in inl for n in s.query_used}
    if len(inl) < b.check_clicks_below:
        return f"{len(inl)} tie points"
    if len(photos) < 2:
        return f"{len(inl)} tie points, all in one photo"
    return None


def sim3_disagreement(a: pycolmap.Sim3d, b: pycolmap.Sim3d, block: pycolmap.Reconstruction) -> float:
    """Median distance (m) between the block's camera centres moved by ``a`` and by ``b``."""
    C = np.array([im.projection_center() for im in block.images.values() if im.has_pose]).reshape(-1, 3)
    if not len(C):
        return 0.0
    return float(np.median(np.linalg.norm(sim3_apply(a, C) - sim3_apply(b, C), axis=1)))
