"""Query photos their own sequence could not hold, registered on their own.

A photo of a query sequence that the sequence's SfM left out (e.g. "no verified matches with any
other image": a low photo over a field) still has its tie-point clicks, and those tie points are
triangulated in the reference block. Each such photo is resected from them: gravity-guided P3P
RANSAC (:func:`gtkit.localize.pnp.gravity_pnp_ransac`, the IMU's gravity from the photo's gimbal
tags) on the clicks whose tie points the reference photos place, in the reference frame. The photo is
then added to its (already Sim(3)-registered) sequence model with no SfM points, so the joint
adjustment refines it with its clicks and the automatic query-reference tie points like any other
photo. Its record says it was resected and from how many clicks.

Where its clicks cannot hold it (too few, or too few consistent: small seed 17's seq2/0002 had 8
clicks and 5 inliers), the photo is matched to the reference block's own 3D points as the automatic
tie points are (:func:`gtkit.sfm.crossmatch.match_photo`: SIFT near the points' projections, PnP
RANSAC, a second pass), guided by its own metadata pose (GPS, gimbal) or that pose corrected by a
registered neighbour (:func:`candidate_priors`), whichever most matches agree with. Its record then says
``"from": "automatic matches"`` and how many matches held it; a photo neither way holds keeps both
reasons.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Camera
from ..conventions import dji_to_rotation, gravity_in_camera
from ..io.exif import read_photo_meta
from ..io.tiepoints import TiePoint
from ..pose import Pose

log = logging.getLogger(__name__)


@dataclass
class Resection:
    name: str
    pose: Pose | None
    n_clicks: int
    n_inliers: int = 0
    reason: str | None = None

    def record(self) -> dict:
        out = {"resected": self.pose is not None, "n_clicks": self.n_clicks, "n_inliers": self.n_inliers}
        if self.reason:
            out["reason"] = self.reason
        return out


def unregistered_photos(block_json: Path) -> dict[str, str]:
    """{photo: why the sequence's SfM left it out} from the block's record."""
    if not block_json.is_file():
        return {}
    return dict(json.loads(block_json.read_text()).get("unregistered") or {})


def resect_photo(name: str, camera: Camera, ties: list[tuple[np.ndarray, np.ndarray]], image_path: Path,
                 max_px: float, min_inliers: int = 6) -> Resection:
    """Pose of one photo from ``ties``: (click (x, y) in the photo, world point) pairs."""
    from ..localize.pnp import PnPSettings, gravity_pnp_ransac

    res = Resection(name, None, len(ties))
    if len(ties) < min_inliers:
        res.reason = f"{len(ties)} clicks on tie points the reference places ({min_inliers} needed)"
        return res
    uv = np.array([t[0] for t in ties], float)
    X = np.array([t[1] for t in ties], float)
    pin = camera.pinhole_part()
    if camera.has_distortion:
        uv = camera.undistort_pixels(uv)
    try:
        meta = read_photo_meta(image_path)
    except Exception:  # noqa: BLE001 - unreadable tags: resected without the gravity check
        meta = None
    g = gravity_in_camera(dji_to_rotation(meta.gimbal_yaw, meta.gimbal_pitch, meta.gimbal_roll)) \
        if meta is not None and meta.has_gimbal else None
    r = gravity_pnp_ransac(uv, X, pin, g, PnPSettings(max_error_px=max_px, min_inliers=min_inliers,
                                                      covariance_inflation=1.0))
    res.n_inliers = r.n_inliers
    if not r.ok:
        res.reason = f"resection failed: {r.reason}"
        return res
    res.pose = r.pose
    return res


def candidate_priors(name: str, qrec: pycolmap.Reconstruction, metadata_pose, neighbours: int = 2) -> list[Pose]:
    """Poses to guide a left-out photo's matching: its own metadata pose (``metadata_pose(name) ->
    Pose | None``: GPS position, gimbal attitude), then that pose corrected by each of the
    ``neighbours`` nearest registered photos of its sequence (names sort in flight order) that have
    metadata: R = R_reg R_meta^T R_own, C = C_own + C_reg - C_meta. The correction helps where the
    GPS and gimbal errors hold over a few seconds; on the samples they do not (small seed 17's
    seq2/0002: own metadata 2.6 m / 2.1 deg off, corrected by a neighbour 6.7 m / 4.9 deg), so the
    photo's own pose comes first and the caller keeps the one most matches agree with."""
    own = metadata_pose(name)
    if own is None:
        return []
    out = [own]
    registered = sorted(im.name for im in qrec.images.values() if im.has_pose)
    order = sorted(set(registered) | {name})
    k = order.index(name)
    for n in sorted(registered, key=lambda m: abs(order.index(m) - k)):
        if len(out) > neighbours:
            break
        meta = metadata_pose(n)
        if meta is None:
            continue
        reg = Pose.from_pycolmap(qrec.find_image_with_name(n).cam_from_world())
        R = reg.R @ meta.R.T @ own.R
        out.append(Pose.from_center(R, own.center + reg.center - meta.center))
    return out


def add_to_block(rec: pycolmap.Reconstruction, name: str, camera_id: int, pose: Pose) -> int:
    """Add a resected photo to a block model (pose only, no keypoints), or give the pose to the
    photo the model holds without one; returns its image id."""
    im = rec.find_image_with_name(name)
    if im is not None:
        rec.frames[im.frame_id].rig_from_world = pose.to_pycolmap()   # trivial rig: camera = rig
        rec.register_frame(im.frame_id)
        return im.image_id
    iid = max(rec.images) + 1 if rec.images else 1
    im = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=camera_id, image_id=iid)
    rec.add_image_with_trivial_frame(im, pose.to_pycolmap())
    return iid


def resect_sequence(seq: str, qrec: pycolmap.Reconstruction, block_json: Path, images: Path,
                    tiepoints: list[TiePoint], place_in_reference, max_px: float,
                    match_reference=None) -> dict[str, dict]:
    """Resect every photo of ``seq`` its SfM left out and add the resected ones to ``qrec`` (already
    in the reference frame). ``place_in_reference(observations) -> xyz | None`` places a tie point
    from its reference clicks; ``match_reference(name, qrec) -> (Pose | None, n matches, reason)``,
    if given, resects a photo its clicks cannot hold from automatic matches to the reference
    (see the module doc). Returns {photo: record}."""
    left_out = unregistered_photos(block_json)
    if not left_out or not qrec.cameras:
        return {}
    registered = {im.name for im in qrec.images.values() if im.has_pose}
    cam_id = sorted(qrec.cameras)[0]  # a sequence's photos share their camera (one DJI lens a block)
    camera = Camera.from_pycolmap(qrec.cameras[cam_id])
    out = {}
    for name, why in sorted(left_out.items()):
        if name in registered:
            continue
        ties = []
        for tp in tiepoints:
            mine = [o for o in tp.observations if o.image == name]
            if not mine:
                continue
            X = place_in_reference(tp.in_block("reference/"))
            if X is not None:
                ties.append((np.array([mine[0].x, mine[0].y]), np.asarray(X, float)))
        r = resect_photo(name, camera, ties, images / name, max_px)
        rec = {"sfm_reason": why, **r.record()}
        if r.pose is None and match_reference is not None:
            pose, n, auto_why = match_reference(name, qrec)
            if pose is not None:
                r.pose = pose
                rec.update({"resected": True, "from": "automatic matches", "n_auto_matches": n,
                            "clicks_reason": rec.pop("reason", None)})
                log.info("register: %s (left out by its sequence: %s) resected from %d automatic matches "
                         "to the reference", name, why, n)
            else:
                rec["auto_reason"] = auto_why
        if r.pose is not None:
            add_to_block(qrec, name, cam_id, r.pose)
            if rec.get("from") != "automatic matches":
                log.info("register: %s (left out by its sequence: %s) resected from %d of %d clicks",
                         name, why, r.n_inliers, r.n_clicks)
        else:
            log.warning("register: %s (left out by its sequence: %s) not resected: %s%s", name, why, r.reason,
                        f"; {rec['auto_reason']}" if rec.get("auto_reason") else "")
        out[name] = rec
    return out
