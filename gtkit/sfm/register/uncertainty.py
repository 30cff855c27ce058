"""The uncertainty model: each query photo's pose covariance, the final joint BA's (at 1 px of the
size its features were found at, or the sequence's measured residual field where that is larger) plus a systematic tilt
about the ground it sees (``systematic_swing_px``) on the sequences it applies to, plus the reference
block's own uncertainty where the photo sees it (:mod:`.real_photo_terms`, issue 48)."""
from __future__ import annotations

import numpy as np

from ...camera import Camera
from ...pose import Pose, skew
from ..crossmatch import AUTO_PREFIX
from .joint import Joint, _median_depth
from .real_photo_terms import (SigmaSettings, feature_noise_px, reference_shape, sigma_side, reference_term,
                               residual_variance_factor, variance_scale)


def swing_covariance(t: np.ndarray, depth_m: float, focal_px: float, swing_px: float) -> np.ndarray:
    """6x6 covariance, in the pose covariance's terms (left perturbation ``R' = exp(dr) R``,
    ``t' = t + dt``, camera frame), of a tilt of ``swing_px / focal_px`` rad about the camera's x and
    y axes that keeps the scene point ``depth_m`` ahead in place: ``dt = [P - t]_x dr`` with
    ``P = (0, 0, depth)``; the camera centre then moves ``depth * tilt`` sideways."""
    tilt = swing_px / focal_px
    d = np.array([0.0, 0.0, depth_m]) - np.asarray(t, np.float64)
    J = np.vstack([np.eye(3), skew(d)])
    return J @ np.diag([tilt ** 2, tilt ** 2, 0.0]) @ J.T


def position_sigma(pose: Pose) -> float | None:
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


def _sequence_factors(j: Joint, qids: list[int], sigma: SigmaSettings) -> dict[str, float | None]:
    """Each sequence's measured residual variance factor (:func:`residual_variance_factor`)."""
    by_seq: dict[str, list[int]] = {}
    for iid in qids:
        by_seq.setdefault(j.rec.images[iid].name.split("/")[1], []).append(iid)
    return {q: residual_variance_factor(j.rec, ids, sigma) for q, ids in by_seq.items()}


def with_centre_covariance(pose: Pose, c_ref: np.ndarray) -> Pose:
    """``pose`` with a centre covariance ``c_ref`` (world frame) added as a shift of its centre:
    ``dt = -R dC``, so its centre covariance grows by exactly ``c_ref``."""
    add = np.zeros((6, 6))
    add[3:, 3:] = pose.R @ c_ref @ pose.R.T
    return Pose(pose.R, pose.t, pose.covariance + add)


def query_poses(j: Joint, cov, swing_px: float, swung: set[str], resected: dict, ref_model=None,
                sigma: SigmaSettings = SigmaSettings(), feature_side: dict[str, int | None] | None = None,
                ref_positions_of=None):
    """Each registered query photo's pose (with its covariance: the BA's, scaled by its sequence's
    residual field, plus the systematic swing on the sequences in ``swung`` and the reference block's
    own uncertainty from its SfM model folder ``ref_model``), camera and record (``resected``: the
    photos left out by their sequence's SfM; ``feature_side``: the long side each block's features were
    found at, ``"reference"`` and each sequence, :func:`feature_noise_px`; ``ref_positions_of``:
    the reference photos' names -> their positions and stated accuracy, :func:`reference_shape`). Returns (poses, cameras, covariances, records, floors:
    photo -> the centre variance clicks do not lower: the terms added to the BA's, so that the
    guidance's sigma is the stated one)."""
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
    factors = _sequence_factors(j, qids, sigma) if sigma.residual_field else {}
    side = (feature_side or {}) if sigma.feature_size else {}
    shape = (reference_shape(ref_model, {rec.images[i].name for i in j.ref_ids}, sigma, side.get("reference"),
                             positions_of=ref_positions_of)
             if sigma.reference_shape and ref_model is not None and qids else None)
    floors: dict[str, float] = {}   # photo -> the systematic part's centre variance (clicks do not lower it)
    for iid in qids:
        im = rec.images[iid]
        seq = im.name.split("/")[1]
        pose = _ba_pose(rec, cov, iid)
        ok = pose.covariance is not None
        sigma_ba = position_sigma(pose)
        k2 = shape is not None and shape.k2_applied and side.get(seq) and side.get(seq) == side.get("reference")
        # features found at the reference block's size: its measured k^2 holds for this BA's covariance
        # too; elsewhere the features' pixel is taken no finer than the default's (sigma_side)
        noise_px = feature_noise_px(rec.cameras[im.camera_id], side.get(seq) if k2 else sigma_side(side.get(seq)))
        terms: dict = {"ba_m": sigma_ba, "residual_factor": factors.get(seq), "feature_px": noise_px}
        scale = variance_scale(noise_px, factors.get(seq))
        if k2:
            scale *= shape.k2_factor
            terms["k2_factor"] = shape.k2_factor
        if ok and scale > 1.0:
            # the scaled part is kept apart as systematic too (the guidance's clicks lower the BA's alone)
            floors[im.name] = (scale - 1.0) * sigma_ba ** 2
            pose = Pose(pose.R, pose.t, pose.covariance * scale)
        if ok and swing_px > 0 and seq in swung:
            sw = swing_covariance(pose.t, _median_depth(rec, im), rec.cameras[im.camera_id].mean_focal_length(),
                                  swing_px * noise_px)
            sw_var = float(np.trace(Pose(pose.R, pose.t, sw).center_covariance()))
            floors[im.name] = floors.get(im.name, 0.0) + sw_var
            terms["swing_m"] = float(np.sqrt(sw_var))
            pose = Pose(pose.R, pose.t, pose.covariance + sw)
        c_ref = reference_term(rec, iid, None, shape) if ok and shape is not None else None
        if c_ref is not None:
            terms["reference_m"] = float(np.sqrt(np.trace(c_ref)))
            terms["reference_residual_factor"] = shape.field_factor
            terms["reference_k2"] = shape.k2
            terms["reference_k2_factor"] = shape.k2_factor if shape.k2_applied else None
            terms["reference_k2_not_applied"] = shape.k2_reason or None
            floors[im.name] = floors.get(im.name, 0.0) + float(np.trace(c_ref))
            pose = with_centre_covariance(pose, c_ref)
        poses[im.name] = pose
        cams[im.name] = Camera.from_pycolmap(rec.cameras[im.camera_id])
        info = {"sequence": seq, "n_points": int(im.num_points3D), "scene_depth_m": _median_depth(rec, im),
                "n_tiepoints": tie_count.get(im.name, 0), "n_auto_tiepoints": auto_count.get(im.name, 0)}
        if im.name in resected:  # left out by its sequence's SfM, registered on its own
            info["resected"] = resected[im.name]
        if ok:
            covs[im.name] = pose.covariance
            info["sigma_pos_m"] = position_sigma(pose)
            info["sigma_rot_deg"] = float(np.degrees(np.sqrt(np.trace(pose.covariance[:3, :3]))))
            info["sigma_pos_ba_m"] = sigma_ba   # the final BA's alone, without the terms added
            info["sigma_terms"] = terms
        else:   # a pose without sigma is not a result: kept, but unverified (issue 55)
            info["unverified"] = j.undetermined.get(seq) or "the final BA gave this photo no covariance"
        per_image[im.name] = info
    return poses, cams, covs, per_image, floors


def unverify_uninformative(per_image: dict) -> list[str]:
    """Marks unverified every photo whose position sigma is larger than its distance to what it sees
    (``scene_depth_m``, the median depth of its points): such a pose says nothing about where the photo
    was taken (tiny sample, ``rtk-few`` seed 0: 7 photos "registered" 185 m off with a median sigma of
    1,453 m, 100 m above the ground). Returns their names."""
    out = []
    for n, info in per_image.items():
        s, d = info.get("sigma_pos_m"), info.get("scene_depth_m")
        if s and d and s > d and "unverified" not in info:
            info["unverified"] = (f"its position sigma ({s:.3g} m) is larger than its distance to what it sees "
                                  f"({d:.3g} m): the pose says nothing about where it was taken")
            out.append(n)
    return out
