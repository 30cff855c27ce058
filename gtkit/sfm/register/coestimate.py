"""The query photos co-estimated with a small reference block (issue 55).

The joint adjustment (:mod:`.joint`) holds the reference photos where the reference SfM put them and
places the query photos on tie points triangulated from them, so a query photo inherits the
reference structure's local error. One SfM of all the photos (what plain COLMAP gives; the real-truth
benchmark's anchor) estimates both at once. Here, after the joint adjustment, every registered query
photo joins the reference block at its pseudo-GT pose:

- matched keypoint to keypoint with the reference photos that see what it sees and with the photos of
  its own sequence (features as the blocks found them: nothing extracted again;
  :func:`gtkit.sfm.extend_reference.extended_database`);
- the block's points completed with its observations and new points triangulated (COLMAP's point
  triangulator, the reference points kept, every pose held);
- the whole block adjusted again with the reference photos held by their positions as the reference
  stage held them (:func:`gtkit.sfm.prior_ba.hold_by_positions`, its sigmas), the intrinsics held,
  except a camera the reference SfM calibrated itself (no cameras.txt, no EXIF focal: focal, principal
  point and distortion): the query photos of the same camera (:func:`gtkit.queries.reference_calibrations`)
  join the block as that camera, each first resected again with it, and the block's BA calibrates it
  again from every photo, as one SfM of all the photos does. A few reference photos alone can misjudge
  it: entry-P10's every second photo split every second (3 reference photos sharing 138 points) put the
  principal point 74 and 139 px off; the 2 query photos placed with it were 1.02 m off with a 0.31 m
  sigma. Calibrated again with them: 5 px off, the query photos 5.7 mm off (one SfM of all 5 photos: 6.8).

The query photos' poses from that adjustment are the pseudo-GT. Each one's move from the joint
adjustment's pose is added to its sigma, a systematic term along the move (two estimates of one photo
from the same matches disagreeing by that much).

Only on a reference block of at most ``up_to_photos`` photos held by its positions: there the whole
block's BA costs seconds, and its positions fix the frame the query photos land in (without them the
block would be free to move). Larger blocks keep the joint adjustment's poses, and the record says why.

Measured against the surveyed truth (docs/benchmarks.md, stop 64): entry-P10, every 3rd photo held out,
self-calibrated: query median 14.7 -> 14.5 mm without positions, 15.6 -> 14.6 with RTK positions (one
SfM of all the photos: 13.1); every 4th 23.7 -> 12.1 mm; fountain-P11 every 3rd 2.9 -> 3.4 mm. With the
self-calibrated camera calibrated again (stop 67): entry-P10 14.6 -> 12.8 mm, fountain-P11 3.4 -> 3.8 mm.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap
from scipy.stats import chi2

from ...camera import Camera
from ...determinism import ba_threads, single_thread_mapper
from ...pose import Pose, skew
from ..extend_reference import extended_database, photo_pairs
from ..prior_ba import hold_by_positions, moved_off_positions
from .real_photo_terms import block_covariance
from .settings import CoestimateSettings
from .uncertainty import position_sigma, with_centre_covariance

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register
CALIBRATION_AGREES = 0.999   # the chi-square quantile a calibration change must stay within (_calibration_check)


def why_not(ref_rec: pycolmap.Reconstruction, held: dict | None, settings: CoestimateSettings) -> str | None:
    """Why the query photos are not co-estimated with this reference block, or None where they are."""
    if not settings.enabled:
        return "off ([register.coestimate] enabled = false)"
    n = ref_rec.num_reg_images()
    if n > settings.up_to_photos:
        return f"{n} photos in the reference block (co-estimated up to {settings.up_to_photos})"
    if not (held or {}).get("applied"):
        return "the reference block is not held by its positions (nothing would fix the frame)"
    return None


def _block_with_photos(ref_rec: pycolmap.Reconstruction, db_path: Path, poses: dict[str, Pose]
                       ) -> pycolmap.Reconstruction:
    """The reference block with the photos of ``poses`` added at them, their cameras and image ids as
    the database ``db_path`` has them (the reference's ids agree with it)."""
    rec = pycolmap.Reconstruction(ref_rec)
    with pycolmap.Database.open(db_path) as db:
        ims = {im.name: im for im in db.read_all_images()}
        cams = {c.camera_id: c for c in db.read_all_cameras()}
    for n in sorted(poses):
        im = ims[n]
        if im.camera_id not in rec.cameras:
            rec.add_camera_with_trivial_rig(cams[im.camera_id])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=n, camera_id=im.camera_id, image_id=im.image_id),
                                         poses[n].to_pycolmap())
    return rec


def _completed_block(ref_rec, ref_db: Path, photos: dict, poses: dict[str, Pose], image_root: Path, work: Path,
                     settings: CoestimateSettings, num_threads: int, reproducible: bool,
                     shared: dict[int, Camera]) -> pycolmap.Reconstruction:
    """The reference block with the query photos at ``poses``, matched with their nearest reference views
    and their sequence, its tracks completed and new points triangulated, every pose held; a query photo
    whose camera is a ``shared`` reference calibration takes that camera."""
    pairs = photo_pairs(ref_rec, poses, settings.neighbours)
    db_path = extended_database(ref_db, {n: (v[1], v[2]) for n, v in photos.items()}, pairs, image_root, work,
                                num_threads=num_threads, shared=shared)
    rec = _block_with_photos(ref_rec, db_path, poses)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    single_thread_mapper(opts, reproducible)     # gtkit.determinism
    return pycolmap.triangulate_points(rec, db_path, image_root, work / "triangulated", clear_points=False,
                                       options=opts, refine_intrinsics=False)


def _one_of(cam: Camera, cams: dict[int, Camera]) -> Camera | None:
    """The camera of ``cams`` that ``cam`` is (model, size and parameters), or None."""
    return next((c for c in cams.values() if cam.model == c.model and (cam.width, cam.height) == (c.width, c.height)
                 and np.allclose(cam.params, c.params, rtol=1e-9, atol=1e-9)), None)


def _off_positions(held: dict, it: str) -> str | None:
    """Why a pose-prior BA's block (``it``, as the sentence names it) is not kept
    (:func:`gtkit.sfm.prior_ba.hold_by_positions`'s report: not applied, or moved off its positions), or None."""
    if held.get("applied") and not moved_off_positions(held):
        return None
    res = held.get("residual_median_m") or {}
    return held.get("reason") or (f"moved {it} off its positions (residual median {res['before']:.3f} -> "
                                  f"{res['after']:.3f} m)")


def _resected_with(rec: pycolmap.Reconstruction, cams: dict[str, Camera], poses: dict[str, Pose]
                   ) -> dict[str, Pose]:
    """``poses``, those of the photos of ``cams`` resected again with that camera on their points in the
    completed block ``rec`` (where that fails, the pose stays)."""
    out = dict(poses)
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.random_seed = 0
    opts.ransac.max_error = 4.0
    for n, cam in sorted(cams.items()):
        im = rec.find_image_with_name(n)
        if im is None:
            continue
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        if len(obs) < 12:
            continue
        r = pycolmap.estimate_and_refine_absolute_pose(np.array([o[0] for o in obs]), np.array([o[1] for o in obs]),
                                                       cam.to_pycolmap(), opts)
        if r is not None:
            out[n] = Pose.from_pycolmap(r["cam_from_world"])
    return out


def _calibration_check(ref_rec: pycolmap.Reconstruction, free: dict[int, list[str]], joined: pycolmap.Reconstruction
                       ) -> dict:
    """{camera id: its calibration before and after the block's BA with the query photos of it, the change's
    squared Mahalanobis distance ``d2`` in the reference block's own covariance of it (at 1 px; None where
    that is not known) and its limit (chi-square at 99.9 %, one degree of freedom a parameter)}. The same
    camera moves within what the reference photos left open (the shared sets' 8 self-calibrated cases:
    d2 0.2-5.0, the 3-photo block 7.1); another camera of the same size (10 % longer focal) drags it far
    outside (1,262)."""
    own = pycolmap.Reconstruction(ref_rec)
    cov = block_covariance(own, sorted(own.reg_image_ids()), free)
    out: dict = {}
    for c, parts in free.items():
        before, after = np.array(ref_rec.cameras[c].params), np.array(joined.cameras[c].params)
        d = after - before
        C = cov.get_other_params_cov(own.cameras[c].params) if cov is not None else None
        d2 = None
        if C is not None and C.shape == (len(d), len(d)) and np.all(np.isfinite(C)):
            try:
                d2 = float(d @ np.linalg.solve(C, d))
            except np.linalg.LinAlgError:
                d2 = None
        out[c] = {"parts": parts, "before": [float(v) for v in before], "after": [float(v) for v in after],
                  "d2": d2, "limit": float(chi2.ppf(CALIBRATION_AGREES, len(d)))}
    return out


def _why_not_joined(held: dict, calibration: dict) -> str | None:
    """Why the block with the query photos as the reference camera is not the one kept, or None."""
    off = _off_positions(held, "the block")
    if off:
        return f"its BA {off}"
    for c, v in calibration.items():
        if v["d2"] is None:
            return f"camera {c}: the reference block's own uncertainty of its calibration could not be computed"
        if v["d2"] > v["limit"]:
            return (f"camera {c}: the calibration it gives (focal {v['after'][0]:.0f} px) is not the reference "
                    f"photos' own (focal {v['before'][0]:.0f} px; change {v['d2']:.0f} in its own variance, limit "
                    f"{v['limit']:.0f}): another camera of the same size")
    return None


def coestimate(ref_rec: pycolmap.Reconstruction, ref_db: Path, photos: dict[str, tuple[Pose, Camera, Path]],
               priors: dict, image_root: Path, work: Path, settings: CoestimateSettings,
               num_threads: int = 2, reproducible: bool = True, self_calibrated: dict[int, list[str]] | None = None,
               same_camera: dict[str, Camera] | None = None) -> tuple[dict[str, Pose], dict[str, Camera], dict]:
    """({photo: its co-estimated pose (no covariance)}, {photo: its camera, where the block's BA refined
    it}, record) for ``photos`` ({name: (joint pose, camera, its sequence's feature database)});
    ``priors``: the reference photos' positions as the reference stage held them: {"positions",
    "accuracy", "outliers", "sigma_hv"}; ``self_calibrated``: the reference cameras its SfM calibrated
    ({id: the parts it refined}): the block's BA refines them again, with every query photo of the same
    camera (``same_camera``: {photo: the reference calibration of its camera}) as that camera, where the
    calibration it gives agrees with the reference photos' own (:func:`_calibration_check`). Empty dicts where
    it could not be done (the record says why). The co-estimated block is left in ``work/model``."""
    photos = {n: v for n, v in photos.items() if Path(v[2]).is_file()}
    if not photos:
        return {}, {}, {"applied": False, "reason": "no query photo with a feature database"}
    joint = {n: v[0] for n, v in photos.items()}
    free = {c: p for c, p in (self_calibrated or {}).items() if p and c in ref_rec.cameras}
    shared = {c: Camera.from_pycolmap(ref_rec.cameras[c]) for c in free}
    # {photo: the very reference camera it joins as}
    joins = {n: sc for n, c in (same_camera or {}).items() if n in photos and (sc := _one_of(c, shared)) is not None}
    try:
        rec = _completed_block(ref_rec, ref_db, photos, joint, image_root, Path(work), settings, num_threads,
                               reproducible, {})
        joined = None
        if joins:
            # the joint poses were estimated with the query photos' own calibration: each photo that joins
            # as a reference camera is resected again with it on the completed block's points first
            again = _resected_with(rec, joins, joint)
            joined = _completed_block(ref_rec, ref_db, {n: (v[0], joins.get(n, v[1]), v[2]) for n, v in photos.items()},
                                      again, image_root, Path(work) / "joined", settings, num_threads, reproducible,
                                      shared)
    except (RuntimeError, ValueError) as e:   # COLMAP's checks: the joint poses stay, the record says why
        return {}, {}, {"applied": False, "reason": f"the block with the query photos could not be made ({e})"}
    n_before = ref_rec.num_points3D()

    def adjusted(block, free_intrinsics):   # the reference photos the reference stage held, as it held them
        return hold_by_positions(block, priors["positions"], set(priors["outliers"]), priors["accuracy"],
                                 num_threads=ba_threads(num_threads, reproducible),
                                 sigma_hv=tuple(priors["sigma_hv"]), free_intrinsics=free_intrinsics)

    calibration, not_joined = {}, None
    free = {c: p for c, p in free.items() if joined is not None
            and any(im.camera_id == c for n in joins if (im := joined.find_image_with_name(n)))}
    if free:
        held = adjusted(joined, free)
        calibration = _calibration_check(ref_rec, free, joined)
        why = _why_not_joined(held, calibration)
        if why is None:
            rec = joined
        else:
            not_joined = {"photos": sorted(joins), "why": why, "check": {str(c): v for c, v in calibration.items()}}
            log.warning("query photos not co-estimated as the reference camera: %s; as their own cameras, held", why)
            free = {}
    if not free:
        held = adjusted(rec, None)
    off = _off_positions(held, "it")
    if off:
        return {}, {}, {"applied": False, "reason": f"the block's BA with the query photos {off}"}
    out, moved, cams = {}, {}, {}
    for n in sorted(joint):
        im = rec.find_image_with_name(n)
        if im is None or not im.has_pose:
            continue
        out[n] = Pose.from_pycolmap(im.cam_from_world())
        moved[n] = float(np.linalg.norm(out[n].center - joint[n].center))
        if im.camera_id in free:
            cams[n] = Camera.from_pycolmap(rec.cameras[im.camera_id])
    if not out:
        return {}, {}, {"applied": False, "reason": "no query photo kept a pose in the block's BA"}
    ref_moved = []
    for im in rec.images.values():
        before = ref_rec.find_image_with_name(im.name)
        if im.has_pose and before is not None and before.has_pose:
            ref_moved.append(float(np.linalg.norm(im.projection_center() - before.projection_center())))
    (Path(work) / "model").mkdir(exist_ok=True)
    rec.write(Path(work) / "model")
    rec_out = {"applied": True, "n_photos": len(out), "n_reference_photos": len(ref_moved),
               "n_points": {"reference": n_before, "with_query_photos": rec.num_points3D()},
               "query_moved_median_m": float(np.median(list(moved.values()))) if moved else None,
               "reference_moved_median_m": float(np.median(ref_moved)) if ref_moved else None,
               "prior_ba": {k: held[k] for k in ("n_priors", "sigma_h_m", "sigma_v_m", "residual_median_m", "converged",
                                                 "iterations", "seconds") if k in held},
               "moved_m": moved,
               "calibrated": {str(c): calibration[c] for c in free},
               "joined_reference_camera": sorted(cams)}
    if not_joined:
        rec_out["not_joined_reference_camera"] = not_joined
    log.info("query photos co-estimated with the reference block: %d photos, moved %.1f mm (median) from the joint "
             "adjustment, reference photos %.1f mm", len(out), 1000 * (rec_out["query_moved_median_m"] or 0.0),
             1000 * (rec_out["reference_moved_median_m"] or 0.0))
    return out, cams, rec_out


def transported(cov: np.ndarray, old: Pose, new: Pose) -> np.ndarray:
    """``cov`` (6x6, the left perturbation of ``old``: ``R' = exp(dr) R``, ``t' = t + dt``) as the same
    rotation and centre perturbations of ``new``: ``dr_new = Q dr``, ``dt_new = (Q [t]_x - [t_new]_x Q) dr + Q dt``
    with ``Q = R_new R^T``, so that ``new``'s rotation and centre covariances are ``old``'s, turned by Q."""
    Q = new.R @ old.R.T
    T = np.zeros((6, 6))
    T[:3, :3] = T[3:, 3:] = Q
    T[3:, :3] = Q @ skew(old.t) - skew(new.t) @ Q
    return T @ cov @ T.T


def carry_over(poses: dict[str, Pose], covs: dict, per_image: dict, floors: dict, moved_to: dict[str, Pose]
               ) -> dict[str, Pose]:
    """The query poses with the co-estimated ones in place of the joint adjustment's (``moved_to``),
    each one's covariance (where it has one) that of its joint pose (:func:`transported`) plus the move as
    a systematic term along it (its centre covariance grows by d d^T, d the move in the world), kept in
    ``floors`` with the other systematic terms; ``covs`` and ``per_image``'s sigmas and terms updated.
    Returns the new poses."""
    out = dict(poses)
    for n, new in moved_to.items():
        old = poses[n]
        d = new.center - old.center
        info = per_image[n]
        info["coestimated_moved_m"] = float(np.linalg.norm(d))
        if old.covariance is None:
            out[n] = new
            continue
        pose = with_centre_covariance(Pose(new.R, new.t, transported(old.covariance, old, new)), np.outer(d, d))
        out[n] = pose
        covs[n] = pose.covariance
        floors[n] = floors.get(n, 0.0) + float(d @ d)
        info["sigma_pos_m"] = position_sigma(pose)
        info.setdefault("sigma_terms", {})["coestimation_m"] = float(np.linalg.norm(d))
    return out
