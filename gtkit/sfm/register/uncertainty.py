"""The uncertainty model: each query photo's pose covariance, the final joint BA's plus a systematic
tilt about the ground it sees (``systematic_swing_px``) on the sequences it applies to."""
from __future__ import annotations

import numpy as np

from ...camera import Camera
from ...pose import Pose, skew
from ..crossmatch import AUTO_PREFIX
from .joint import Joint, _median_depth


def swing_covariance(t: np.ndarray, depth_m: float, focal_px: float, swing_px: float) -> np.ndarray:
    """6x6 covariance, in the pose covariance's terms (left perturbation ``R' = exp(dr) R``,
    ``t' = t + dt``, camera frame), of a tilt of ``swing_px / focal_px`` rad about the camera's x and
    y axes that keeps the scene point ``depth_m`` ahead in place: ``dt = [P - t]_x dr`` with
    ``P = (0, 0, depth)``; the camera centre then moves ``depth * tilt`` sideways."""
    tilt = swing_px / focal_px
    d = np.array([0.0, 0.0, depth_m]) - np.asarray(t, np.float64)
    J = np.vstack([np.eye(3), skew(d)])
    return J @ np.diag([tilt ** 2, tilt ** 2, 0.0]) @ J.T


def _position_sigma(pose: Pose) -> float | None:
    """The 1-sigma radius of the camera centre, sqrt(trace), or None without a covariance."""
    cc = pose.center_covariance()
    return None if cc is None else float(np.sqrt(np.trace(cc)))


def _ba_pose(rec, cov, iid: int) -> Pose:
    """An image's pose with the BA's covariance (None where it has none or it is not finite)."""
    c = None
    if cov is not None:
        try:
            c = np.asarray(cov.get_cam_cov_from_world(iid))
        except Exception:  # noqa: BLE001 - not every image gets one
            c = None
    ok = c is not None and c.shape == (6, 6) and np.all(np.isfinite(c))
    return Pose.from_pycolmap(rec.images[iid].cam_from_world(), c if ok else None)


def query_poses(j: Joint, cov, swing_px: float, swung: set[str], resected: dict):
    """Each registered query photo's pose (with its covariance: the BA's, plus the systematic swing on
    the sequences in ``swung``), camera and record (``resected``: the photos left out by their
    sequence's SfM). Returns (poses, cameras, covariances, records, floors: photo -> the systematic
    part's centre variance, which clicks do not lower)."""
    rec = j.rec
    qids = [i for i in rec.reg_image_ids() if i not in j.ref_ids]
    poses, cams, covs, per_image = {}, {}, {}, {}
    tie_count: dict[str, int] = {}
    auto_count: dict[str, int] = {}
    for tid, pid in j.tie_pids.items():
        cnt = auto_count if tid.startswith(AUTO_PREFIX) else tie_count
        for e in rec.points3D[pid].track.elements:
            n = rec.images[e.image_id].name
            cnt[n] = cnt.get(n, 0) + 1
    floors: dict[str, float] = {}   # photo -> the systematic part's centre variance (clicks do not lower it)
    for iid in qids:
        im = rec.images[iid]
        pose = _ba_pose(rec, cov, iid)
        ok = pose.covariance is not None
        sigma_ba = _position_sigma(pose)
        if ok and swing_px > 0 and im.name.split("/")[1] in swung:
            sw = swing_covariance(pose.t, _median_depth(rec, im), rec.cameras[im.camera_id].mean_focal_length(),
                                  swing_px)
            floors[im.name] = float(np.trace(Pose(pose.R, pose.t, sw).center_covariance()))
            pose = Pose(pose.R, pose.t, pose.covariance + sw)
        poses[im.name] = pose
        cams[im.name] = Camera.from_pycolmap(rec.cameras[im.camera_id])
        info = {"sequence": im.name.split("/")[1], "n_points": int(im.num_points3D),
                "n_tiepoints": tie_count.get(im.name, 0), "n_auto_tiepoints": auto_count.get(im.name, 0)}
        if im.name in resected:  # left out by its sequence's SfM, registered on its own
            info["resected"] = resected[im.name]
        if ok:
            covs[im.name] = pose.covariance
            info["sigma_pos_m"] = _position_sigma(pose)
            info["sigma_rot_deg"] = float(np.degrees(np.sqrt(np.trace(pose.covariance[:3, :3]))))
            info["sigma_pos_ba_m"] = sigma_ba   # the final BA's alone, without the systematic swing
        per_image[im.name] = info
    return poses, cams, covs, per_image, floors
