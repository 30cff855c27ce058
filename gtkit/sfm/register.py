"""Register each query block to the georegistered reference block through tie points, then
refine everything in one joint bundle adjustment with the reference block held fixed.

Per sequence:
1. place every tie point in the reference block (fixed, georegistered poses) and in the query
   block (its SfM poses): triangulated from its clicks where it has two or more (a click that
   disagrees with the others by more than ``tie_max_px`` is dropped as a gross mistake), else
   its one click is lifted to 3D with the depth of the block's own 3D points around it.
2. robust Sim(3) (LO-RANSAC) from query-block to reference positions; tie points off the fit by
   more than ``sim3_max_error_m`` are outliers. Fewer than 3 usable tie points, collinear ones,
   or a failed fit: the sequence is an error with its reason (never a prior pose).
3. transform the query block.
A sequence without 3 usable clicks (no ``tiepoints.json`` is no clicks) is placed without them
(:func:`bootstrap_sequence`, ``[register.bootstrap]``): each of its photos is matched to the
reference block's 3D points around the pose its metadata claims (GPS + gimbal; else its pose in
the block's own GPS georegistration; else, with GPS alone, a grid of attitudes at its GPS
position) within a radius that covers consumer GPS (:func:`gtkit.sfm.crossmatch.match_photo_wide`),
and the Sim(3) most matched photos agree with places the block. A sequence this cannot hold is an
error that names why and asks for clicks there (``needs_clicks`` in the record, the GT report's
"Sequences that need clicks").
Automatic tie points (SIFT matches between each query photo and the reference photos looking the
same way, see :mod:`gtkit.sfm.crossmatch`) join the clicks from pass b on; they are not listed.
Then one joint bundle adjustment (the reference photos holding tie clicks keep their poses and
intrinsics fixed; each registered query block enters with its own 3D points; each tie point is
a 3D point observed in both blocks and so ties them together), in passes:
a. robust (Cauchy) BA with the Sim(3) inliers;
b. every tie point of the registered sequences is re-triangulated from all its clicks with the
   refined poses; clicks off by more than ``ba_max_tie_px`` are dropped (listed as mistakes),
   the rest (Sim(3) outliers of step 2 included, when now consistent) re-enter;
c. final least-squares BA; its covariance gives each query photo's pose uncertainty.
"""
from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..camera import Camera
from ..errors import GtkitError
from ..io.atomic import write_json
from ..io.poses import write_covariances, write_intrinsics, write_poses
from ..io.tiepoints import TiePoint, read_tiepoints
from ..pose import Pose, skew
from ..project import PROJECT_FILE, Project, file_fingerprint, mark_stage_done, stage_done, start_stage_clock
from . import quiet_colmap
from .blocks import QUERIES_STAGE, REFERENCE_STAGE
from ..io.exif import prior_pose, read_photo_meta
from .crossmatch import (AUTO_PREFIX, CrossMatchSettings, ReferencePoints, cross_matches, match_photo,
                         match_photo_wide, photo_features, reference_point_of)
from .guided_clicks import (COVARIANCE_FILE, GUIDANCE_FILE, GuidanceSettings, guidance, reference_views, save_states,
                            sequence_states)
from .resect import candidate_priors, resect_sequence
from .extend_reference import ExtendSettings, extension_ties
from .tie_surface import SmoothSurfaceSettings, smooth_surface_filter
from .geometry import (RegistrationError, model_cameras, model_poses, robust_sim3, sim3_apply, triangulate_clicks,
                       triangulate_many)

log = logging.getLogger(__name__)
STAGE = "register"


@dataclass
class BootstrapSettings:
    """``[register.bootstrap]``: a query sequence without 3 usable clicked tie points is placed by its
    photos' automatic matches to the reference block's 3D points (:func:`bootstrap_sequence`)."""
    enabled: bool = True
    # how far (px) a reference point may project from its match around a photo's metadata pose:
    # consumer GPS (5-15 m) and gimbal (1-3 deg) errors move the projections by 30-150 px; a photo
    # that finds nothing is tried again at twice this
    radius_px: float = 200.0
    # photos whose matches must agree on one Sim(3) (one photo alone is not checked by another)
    min_photos: int = 2
    max_pairs: int = 2000          # query-reference 3D point pairs the Sim(3) RANSAC draws from
    # a matched photo's pose farther than this from the prior that guided it is a false match
    max_offset_m: float = 60.0
    # a matched photo agrees with the Sim(3) where its block pose, so moved, is within these of the
    # pose its own matches gave it (a false match is tens of metres off)
    agree_m: float = 3.0
    agree_deg: float = 2.0
    # photos with GPS but no gimbal attitude (and no usable block pose): attitudes searched at their
    # GPS position, on up to ``search_photos`` photos of the sequence until one matches
    search_photos: int = 3
    search_yaw_step_deg: float = 20.0
    # (nadir last: a mapping flight's photos held out of it, when the oblique attitudes found nothing)
    search_pitches_deg: list = field(default_factory=lambda: [-25.0, -45.0, -65.0, -90.0])
    # a clicked Sim(3) with fewer inlier tie points than this, or with all of them in one photo, is
    # checked against the photos' automatic matches (where they place the block): farther than
    # ``agree_m`` apart, the automatic placement wins and the report says so (small seed 13: its first
    # 4 clicks, all in one photo, one of them grossly wrong, put seq1 116 m off; checked: 0.056 m). 0: off
    check_clicks_below: int = 8


@dataclass
class RegisterSettings:
    tie_max_px: float = 4.0          # a click farther than this from its triangulated point is a mistake
    sim3_max_error_m: float = 1.5    # Sim(3) RANSAC inlier threshold, metres in the reference frame
    ba_max_tie_px: float = 3.0       # tie observations above this after the robust BA pass are dropped
    # Automatic tie points are plentiful (hundreds a photo, each a SIFT match), so they must fit tighter.
    # Measured against truth on the medium sample: matches on tree canopies (lit from another sun
    # angle in the query and the reference photos) are 1-2 m off in 3D yet within 3 px (median 1.7 px),
    # the others are unbiased with a median of 0.6 px.
    ba_max_auto_px: float = 1.5
    ba_loss_scale_px: float = 2.0    # Cauchy loss scale of the first BA pass
    refine_query_intrinsics: bool = False  # let the joint BA refine the query cameras' focal/distortion
    min_tiepoints: int = 3
    ba_max_iterations: int = 100
    num_threads: int = 2
    # automatic SIFT tie points between query and reference photos, added to the clicks
    cross: CrossMatchSettings = field(default_factory=CrossMatchSettings)
    # ... kept only where the reference model is a smooth surface (their spot moves with the sun
    # elsewhere; gtkit.sfm.tie_surface)
    smooth_surface: SmoothSurfaceSettings = field(default_factory=SmoothSurfaceSettings)
    # Each photo's reported covariance = the final BA's + a systematic tilt of this many pixels about
    # each image axis, about the ground it sees (the centre shifted so that its median scene point
    # stays put). The BA's covariance holds only what the residuals show; matches between photos
    # under different light shift together, which no residual shows (a spatial jackknife over the
    # ties moved the sequences by 0.2-1.2 cm where they were 3-14 cm off). Calibrated against truth on
    # medium seed 6 (position errors within 2 sigma 82 -> 99 %, rotation 75 -> 95 %), checked on
    # medium seed 5 (85 -> 96 %, 94 -> 100 %). 0: the BA's alone.
    systematic_swing_px: float = 0.15
    # ... added to the sequences whose automatic ties on rough surface the smooth-surface test found
    # biased ("biased"; every medium sequence of seeds 5 and 6), or to every sequence ("all", as
    # before issue 35). Where the test finds no bias the BA's covariance alone already matches the
    # errors: small seeds 13-15, RMS error per camera axis 0.025 / 0.026 / 0.015 m against BA sigmas
    # of 0.023 / 0.025 / 0.013 m; the swing on top (0.03 m an axis at their 0.2 m a pixel) doubled it.
    systematic_swing_where: str = "biased"
    # the next clicks suggested per sequence (work/register/guided_clicks.json, the GT report, the annotator)
    guidance: GuidanceSettings = field(default_factory=GuidanceSettings)
    # sequences without enough usable clicks: placed by automatic matches to the reference points
    bootstrap: BootstrapSettings = field(default_factory=BootstrapSettings)
    # photos placed on their own (left out by their sequence's SfM): registered into the reference
    # block by keypoint matches with the reference photos, its points joining as automatic ties
    extend: ExtendSettings = field(default_factory=ExtendSettings)


def swing_covariance(t: np.ndarray, depth_m: float, focal_px: float, swing_px: float) -> np.ndarray:
    """6x6 covariance, in the pose covariance's terms (left perturbation ``R' = exp(dr) R``,
    ``t' = t + dt``, camera frame), of a tilt of ``swing_px / focal_px`` rad about the camera's x and
    y axes that keeps the scene point ``depth_m`` ahead in place: ``dt = [P - t]_x dr`` with
    ``P = (0, 0, depth)``; the camera centre then moves ``depth * tilt`` sideways."""
    tilt = swing_px / focal_px
    d = np.array([0.0, 0.0, depth_m]) - np.asarray(t, np.float64)
    J = np.vstack([np.eye(3), skew(d)])
    return J @ np.diag([tilt ** 2, tilt ** 2, 0.0]) @ J.T


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


@dataclass
class Bootstrap:
    """What :func:`bootstrap_sequence` found: the Sim(3) (None when the sequence cannot be held),
    the reason, and one record per photo."""
    sim: pycolmap.Sim3d | None
    reason: str
    photos: dict[str, dict]
    n_pairs: int = 0
    n_inliers: int = 0
    rmse_m: float | None = None
    fit_from: str = ""

    def record(self) -> dict:
        matched = [n for n, r in self.photos.items() if r.get("n_matches")]
        return {"n_photos": len(self.photos), "n_photos_matched": len(matched),
                "n_photos_agreeing": sum(1 for r in self.photos.values() if r.get("agrees")),
                "n_point_pairs": self.n_pairs, "n_sim3_inliers": self.n_inliers, "sim3_rmse_m": self.rmse_m,
                "sim3_from": self.fit_from,
                "photos": self.photos, **({"reason": self.reason} if self.reason else {})}


def bootstrap_sequence(qrec: pycolmap.Reconstruction, priors, match, settings: RegisterSettings,
                       search=None) -> Bootstrap:
    """Place one query block in the reference frame without clicks.

    Each registered photo is matched to the reference block's 3D points around the poses
    ``priors(name) -> [(label, Pose)]`` gives (its GPS + gimbal metadata, its pose in the block's own
    GPS georegistration); ``match(name, prior, wider) -> (Pose | None, reference xyz (n, 3), query
    keypoint indices)`` (:func:`gtkit.sfm.crossmatch.match_photo_wide`; ``wider``: a photo that finds
    nothing is searched again at twice the radius). Photos with no prior, or none that
    matched, are tried again around their block pose moved by a first Sim(3) from the matched ones.
    Where no photo matched at all, ``search(name) -> [(label, Pose)]`` (a photo's GPS position with
    a grid of attitudes: no gimbal tags) is tried on up to ``bootstrap.search_photos`` photos, the
    first that matches ending the search. A match farther than ``bootstrap.max_offset_m`` from the
    pose that guided it is taken for a false one.
    Each match whose query keypoint is a 3D point of the block is a pair (block point, reference
    point); a robust Sim(3) (LO-RANSAC, ``sim3_max_error_m``) over all pairs is one candidate, the
    Sim(3)s from the matched photos' poses (:func:`_sim3_from_poses`, each pair of photos) the
    others: the one most photos agree with wins (their block poses so moved within ``agree_m`` /
    ``agree_deg`` of the poses their own matches gave them), refitted on them. A short sequence's
    own 3D points can be metres off in depth (tiny seed 0's seq3 at 150 m: its point Sim(3) 13 m and
    4.7 deg from all three photos' own poses), its relative poses are not. It holds only where
    ``bootstrap.min_photos`` photos or more agree."""
    b = settings.bootstrap
    names = sorted(im.name for im in qrec.images.values() if im.has_pose)
    photos: dict[str, dict] = {n: {} for n in names}
    pairs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    matched_pose: dict[str, Pose] = {}     # each matched photo's own pose from its matches (PnP)

    def pairs_of(name, X_ref, kk):
        im = qrec.find_image_with_name(name)
        src, tgt, pid = [], [], []
        for X, k in zip(X_ref, kk):
            p2 = im.points2D[int(k)]
            if p2.has_point3D():
                src.append(qrec.points3D[p2.point3D_id].xyz)
                tgt.append(X)
                pid.append(p2.point3D_id)
        return np.array(src).reshape(-1, 3), np.array(tgt).reshape(-1, 3), np.array(pid, np.int64)

    def try_photo(name, cands, wider=True):
        best = None
        for label, prior in cands:
            pose, X_ref, kk = match(name, prior, wider)
            if pose is not None and np.linalg.norm(pose.center - prior.center) > b.max_offset_m:
                pose = None   # matched far from where its metadata put it: a false match
            if pose is not None and (best is None or len(kk) > len(best[2])):
                best = (label, X_ref, kk, pose)
            if best is not None and label != "block GPS":   # the metadata pose found it: enough
                break
        if best is None:
            return False
        photos[name] = {"n_matches": int(len(best[2])), "guided_by": best[0]}
        pairs[name] = pairs_of(name, best[1], best[2])
        matched_pose[name] = best[3]
        return True

    for n in names:
        cands = priors(n)
        if not cands:
            photos[n] = {"reason": "no GPS + gimbal metadata and no GPS georegistration of its block"}
            continue
        if not try_photo(n, cands):
            photos[n] = {"reason": f"fewer than {settings.cross.min_inliers} consistent matches to the reference "
                                   "points around its metadata pose"}
    if not pairs and search is not None:   # no attitude to guide any photo: searched at its GPS position
        tried = 0
        for n in names:
            cands = search(n)
            if not cands or tried >= b.search_photos:
                continue
            tried += 1
            if try_photo(n, cands, wider=False):
                break
            photos[n] = {"reason": (photos[n]["reason"] + "; " if photos[n].get("reason") else "")
                         + f"no match around its GPS position at any of {len(cands)} searched attitudes"}

    def fit():
        src = np.vstack([pairs[n][0] for n in pairs]) if pairs else np.zeros((0, 3))
        tgt = np.vstack([pairs[n][1] for n in pairs]) if pairs else np.zeros((0, 3))
        who = np.concatenate([np.full(len(pairs[n][0]), k) for k, n in enumerate(pairs)]) if pairs else np.zeros(0, int)
        if len(src) > b.max_pairs:
            pick = np.sort(np.random.default_rng(0).choice(len(src), b.max_pairs, replace=False))
            src, tgt, who = src[pick], tgt[pick], who[pick]
        return robust_sim3(src, tgt, settings.sim3_max_error_m, what="block-reference point matches"), src, tgt, who

    def offsets(sim, n):
        """(m, deg) between the photo's block pose moved by ``sim`` and the pose its matches gave it."""
        Rs = np.asarray(sim.rotation.matrix())
        block = Pose.from_pycolmap(qrec.find_image_with_name(n).cam_from_world())
        moved = Pose.from_center(block.R @ Rs.T, np.asarray(sim * block.center))
        return moved.error_to(matched_pose[n])

    def agreeing(sim):
        offs = {n: offsets(sim, n) for n in pairs}
        ok = [n for n, (dm, dd) in offs.items() if dm <= b.agree_m and dd <= b.agree_deg]
        return ok, float(np.mean([offs[n][0] for n in ok])) if ok else np.inf

    def choose():
        """(the Sim(3) most matched photos agree with or None, how, the agreeing photos, point fit, its
        pair sources, error of the point fit)."""
        try:
            f = fit()
            point_err = ""
        except RegistrationError as e:
            f, point_err = None, str(e)
        scale = None if f is None else float(f[0].tgt_from_src.scale)
        block = {n: Pose.from_pycolmap(qrec.find_image_with_name(n).cam_from_world()) for n in pairs}
        hyps = [("block-reference point pairs", f[0].tgt_from_src)] if f is not None else []
        for ij in itertools.islice(itertools.combinations(sorted(pairs), 2), 300):
            h = _sim3_from_poses([block[n] for n in ij], [matched_pose[n] for n in ij], scale)
            if h is not None:
                hyps.append(("photo poses", h))
        if not hyps:
            return None, "", [], f, point_err
        scored = [(agreeing(h), how, h) for how, h in hyps]
        (ok, _), how, sim = max(scored, key=lambda x: (len(x[0][0]), -x[0][1]))
        if len(ok) >= 2:   # refit on every agreeing photo
            h = _sim3_from_poses([block[n] for n in ok], [matched_pose[n] for n in ok], scale)
            if h is not None and len(agreeing(h)[0]) >= len(ok):
                how, sim, ok = "photo poses", h, agreeing(h)[0]
        return sim, how, ok, f, point_err

    # photos not matched around their own priors: around their block pose through a first Sim(3)
    missing = [n for n in names if n not in pairs]
    if pairs and missing:
        first = choose()[0]
        if first is not None:
            for n in missing:
                im = qrec.find_image_with_name(n)
                C = np.asarray(first * im.projection_center())
                R = Pose.from_pycolmap(im.cam_from_world()).R @ np.asarray(first.rotation.matrix()).T
                if try_photo(n, [("matched photos of its block", Pose.from_center(R, C))]):
                    photos[n].pop("reason", None)
    n_matched = len(pairs)
    if n_matched < b.min_photos:
        whys = [r["reason"] for r in photos.values() if r.get("reason")]
        common = max(set(whys), key=whys.count) if whys else ""
        return Bootstrap(None, f"only {n_matched} of {len(names)} photos matched the reference points "
                               f"({b.min_photos} needed" + (f"; {whys.count(common)} with {common}" if common else "")
                         + ")", photos)
    sim, how, ok, f, point_err = choose()
    if sim is None:
        return Bootstrap(None, f"{n_matched} of {len(names)} photos matched the reference points but {point_err}",
                         photos)
    fit3, src, who = (f[0], f[1], f[3]) if f is not None else (None, np.zeros((0, 3)), np.zeros(0, int))
    for k, n in enumerate(pairs):
        mine = who == k
        d_m, d_deg = offsets(sim, n)
        photos[n].update({"n_pairs": int(mine.sum()),
                          "n_sim3_inliers": int(fit3.inliers[mine].sum()) if fit3 is not None else 0,
                          "offset_m": float(d_m), "offset_deg": float(d_deg), "agrees": n in ok})
    out = Bootstrap(sim, "", photos, int(len(src)), int(fit3.inliers.sum()) if fit3 is not None else 0,
                    float(fit3.rmse_inliers_m) if fit3 is not None else None, fit_from=how)
    if len(ok) < b.min_photos:
        out.sim = None
        out.reason = (f"{n_matched} of {len(names)} photos matched the reference points, but only {len(ok)} agree on "
                      f"one Sim(3) ({b.min_photos} needed)")
    return out


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


def _sim3_from_poses(block: list[Pose], ref: list[Pose], fallback_scale: float | None) -> pycolmap.Sim3d | None:
    """Sim(3) reference_from_block from photos' block poses and their poses in the reference frame:
    the rotation the chordal mean of R_ref^T R_block, scale and translation least squares on the
    centres (``fallback_scale`` where they span less than a metre, None without one)."""
    M = sum(r.R.T @ q.R for q, r in zip(block, ref))
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    cs = np.array([q.center for q in block])
    cr = np.array([r.center for r in ref])
    a = (cs - cs.mean(0)) @ R.T
    d = cr - cr.mean(0)
    if len(block) >= 2 and np.linalg.norm(d, axis=1).max() >= 1.0 and (a * a).sum() > 0:
        scale = float((a * d).sum() / (a * a).sum())
    else:
        scale = fallback_scale
    if scale is None or not np.isfinite(scale) or scale <= 0:
        return None
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(R), cr.mean(0) - scale * R @ cs.mean(0))


# --- the joint model -----------------------------------------------------------------------

class _Builder:
    """Assembles one pycolmap Reconstruction from several blocks with fresh ids."""

    def __init__(self):
        self.rec = pycolmap.Reconstruction()
        self.next_cam = 1
        self.next_img = 1
        self.image_ids: dict[str, int] = {}

    def add_camera(self, cam: pycolmap.Camera) -> int:
        c = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=list(cam.params),
                            camera_id=self.next_cam)
        self.rec.add_camera_with_trivial_rig(c)
        self.next_cam += 1
        return c.camera_id

    def add_image(self, name: str, cam_id: int, pose: pycolmap.Rigid3d, keypoints: np.ndarray) -> int:
        iid = self.next_img
        self.next_img += 1
        im = pycolmap.Image(name=name, keypoints=np.asarray(keypoints, float).reshape(-1, 2), camera_id=cam_id,
                            image_id=iid)
        self.rec.add_image_with_trivial_frame(im, pose)
        self.image_ids[name] = iid
        return iid


@dataclass
class Joint:
    rec: pycolmap.Reconstruction
    image_ids: dict[str, int]
    ref_ids: set[int]
    slot: dict[tuple[str, str], int]        # (tie id, image) -> point2D index of that click
    clicks: dict[str, dict[str, tuple]]     # tie id -> {image: (x, y)} for every click on a joint image
    tie_pids: dict[str, int] = field(default_factory=dict)

    def poses_cams(self):
        return model_poses(self.rec), model_cameras(self.rec)

    def set_ties(self, ties: dict[str, tuple[np.ndarray, list[str]]]) -> None:
        """Replace all tie points by ``ties``: id -> (xyz, images whose click is used)."""
        for pid in self.tie_pids.values():
            if pid in self.rec.points3D:
                self.rec.delete_point3D(pid)
        self.tie_pids = {}
        for tid, (xyz, images) in ties.items():
            els = [pycolmap.TrackElement(self.image_ids[n], self.slot[(tid, n)]) for n in images]
            self.tie_pids[tid] = self.rec.add_point3D(np.asarray(xyz, float), pycolmap.Track(els))


def build_joint(ref_rec, blocks: dict[str, pycolmap.Reconstruction], clicks: dict[str, dict[str, tuple]]) -> Joint:
    """Reference photos clicked in ``clicks`` (fixed later) + every registered query block with its
    points; each click becomes an extra keypoint of its photo."""
    b = _Builder()
    per_image: dict[str, list] = {}
    for tid, obs in clicks.items():
        for name, xy in obs.items():
            per_image.setdefault(name, []).append((tid, xy))
    slot, ref_ids, cam_map = {}, set(), {}
    for name in sorted(n for n in per_image if n.startswith("reference/")):
        im = ref_rec.find_image_with_name(name)
        if im is None or not im.has_pose:
            continue
        if im.camera_id not in cam_map:
            cam_map[im.camera_id] = b.add_camera(ref_rec.cameras[im.camera_id])
        for k, (tid, _) in enumerate(per_image[name]):
            slot[(tid, name)] = k
        ref_ids.add(b.add_image(name, cam_map[im.camera_id], im.cam_from_world(),
                                np.array([xy for _, xy in per_image[name]])))
    for seq, rec in blocks.items():
        cam_map, id_map = {}, {}
        for iid, im in rec.images.items():
            if not im.has_pose:
                continue
            if im.camera_id not in cam_map:
                cam_map[im.camera_id] = b.add_camera(rec.cameras[im.camera_id])
            kp = np.array([p.xy for p in im.points2D]).reshape(-1, 2)
            extra = per_image.get(im.name, [])
            for k, (tid, _) in enumerate(extra):
                slot[(tid, im.name)] = len(kp) + k
            if extra:
                kp = np.vstack([kp, np.array([xy for _, xy in extra])])
            id_map[iid] = b.add_image(im.name, cam_map[im.camera_id], im.cam_from_world(), kp)
        for p in rec.points3D.values():
            els = [pycolmap.TrackElement(id_map[e.image_id], e.point2D_idx) for e in p.track.elements
                   if e.image_id in id_map]
            if len(els) >= 2:
                b.rec.add_point3D(p.xyz, pycolmap.Track(els), p.color)
    clicks = {tid: {n: xy for n, xy in obs.items() if n in b.image_ids} for tid, obs in clicks.items()}
    return Joint(b.rec, b.image_ids, ref_ids, slot, clicks)


def _max_px(tid: str, settings: RegisterSettings) -> float:
    return settings.ba_max_auto_px if tid.startswith(AUTO_PREFIX) else settings.ba_max_tie_px


def retriangulate_ties(j: Joint, settings: RegisterSettings) -> tuple[dict, dict]:
    """Every tie point from all its clicks with the joint model's current poses. Returns
    (ties to use: id -> (xyz, images), dropped clicks: id -> [{image, residual_px}])."""
    poses, cams = j.poses_cams()
    use, dropped = {}, {}
    todo = {}
    for tid, obs in j.clicks.items():
        names = [n for n in obs if n in poses]
        if len(names) >= 2 and any(n.startswith("queries/") for n in names):
            todo[tid] = names
    for tid, tri in zip(todo, _triangulate_ties(j, todo, poses, cams, settings)):
        names = todo[tid]
        bad = [{"image": n, "residual_px": float(r)} for n, u, r in zip(names, tri.used, tri.residuals_px) if not u]
        if tri.xyz is None:
            dropped[tid] = [{"image": n, "residual_px": float(r)} for n, r in zip(names, tri.residuals_px)]
            continue
        if bad:
            dropped[tid] = bad
        kept = [n for n, u in zip(names, tri.used) if u]
        if any(n.startswith("queries/") for n in kept) and any(n.startswith("reference/") for n in kept):
            use[tid] = (tri.xyz, kept)
    return use, dropped


def _triangulate_ties(j: Joint, todo: dict[str, list[str]], poses, cams, settings: RegisterSettings) -> list:
    """Each tie of ``todo`` (id -> its images) from its clicks in those images, automatic ties and
    clicked ties with their own pixel limits, many points at once (geometry.triangulate_many)."""
    out = {}
    for auto in (True, False):
        ids = [t for t in todo if t.startswith(AUTO_PREFIX) == auto]
        tracks = [([cams[n] for n in todo[t]], [poses[n] for n in todo[t]], np.array([j.clicks[t][n] for n in todo[t]]))
                  for t in ids]
        max_px = settings.ba_max_auto_px if auto else settings.ba_max_tie_px
        out.update(zip(ids, triangulate_many(tracks, max_px=max_px, min_angle_deg=0.5)))
    return [out[t] for t in todo]


def _placed_by_reference(j: Joint, ties: dict[str, dict], settings: RegisterSettings) -> dict:
    """Tie points triangulated from their reference observations alone: id -> (xyz, all its joint images)."""
    poses, cams = j.poses_cams()
    todo, queries = {}, {}
    for tid, obs in ties.items():
        refs = [n for n in obs if n.startswith("reference/") and n in poses]
        queries[tid] = [n for n in obs if n.startswith("queries/") and n in poses]
        if len(refs) >= 2 and queries[tid]:
            todo[tid] = refs
    out = {}
    for tid, tri in zip(todo, _triangulate_ties(j, todo, poses, cams, settings)):
        if tri.xyz is not None:
            out[tid] = (tri.xyz, [n for n, u in zip(todo[tid], tri.used) if u] + queries[tid])
    return out


def _bundle_adjust(rec, ref_ids, settings: RegisterSettings, loss: str, covariance: bool = False):
    cfg = pycolmap.BundleAdjustmentConfig()
    ref_cams = {rec.images[i].camera_id for i in ref_ids}
    for iid in rec.reg_image_ids():
        cfg.add_image(iid)
    for iid in ref_ids:
        cfg.set_constant_rig_from_world_pose(rec.images[iid].frame_id)
    for cid in rec.cameras:
        if cid in ref_cams or not settings.refine_query_intrinsics:
            cfg.set_constant_cam_intrinsics(cid)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_principal_point = False
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss)
    opts.ceres.loss_function_scale = settings.ba_loss_scale_px
    opts.ceres.solver_options.max_num_iterations = settings.ba_max_iterations
    opts.ceres.solver_options.num_threads = settings.num_threads
    ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
    summary = ba.solve()
    cov = None
    if covariance:
        try:
            cov = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), rec, ba)
        except Exception as e:  # noqa: BLE001 - covariance is optional output; the reason is logged
            log.warning("BA covariance failed: %s", e)
    return summary, cov


def _median_depth(rec, im) -> float:
    """Median depth (camera z, metres) of the 3D points a registered image observes."""
    X = np.array([rec.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()])
    if not len(X):
        return 0.0
    M = im.cam_from_world().matrix()
    return float(np.median(X @ M[:, :3].T[:, 2] + M[2, 3]))


def _write_guidance(out: Path, rec, cov, ref_ids, floors, ref_rec, settings: GuidanceSettings,
                    unregistered: dict[str, list[str]]) -> None:
    """``guided_clicks.json`` (the next clicks per sequence, :mod:`gtkit.sfm.guided_clicks`; for the
    ``unregistered`` sequences, photos to click first) and the sequences' joint covariances it was
    computed from (``sequence_covariance.npz``)."""
    for f in (GUIDANCE_FILE, COVARIANCE_FILE):
        (out / f).unlink(missing_ok=True)
    if not settings.enabled or cov is None:
        return
    states = sequence_states(rec, cov, ref_ids, floors)
    save_states(out / COVARIANCE_FILE, states)
    write_json(out / GUIDANCE_FILE, guidance(states, rec, reference_views(ref_rec), settings, unregistered))


def _reference_model(paths) -> Path | None:
    """The project's reference model, or None before one is built or imported."""
    from ..export.sources import reference_model

    try:
        return reference_model(paths)
    except GtkitError:
        return None


def point_reprojection_errors(rec, point_ids) -> np.ndarray:
    errs = []
    for pid in point_ids:
        p = rec.points3D[pid]
        for e in p.track.elements:
            im = rec.images[e.image_id]
            proj = im.project_point(p.xyz)
            errs.append(np.inf if proj is None else float(np.linalg.norm(np.asarray(proj) - im.points2D[e.point2D_idx].xy)))
    return np.asarray(errs)


def _block_georegistered(block_json: Path) -> bool:
    """Whether a query block's SfM was placed in the world by its photos' GPS (its record says so)."""
    import json

    if not block_json.is_file():
        return False
    b = json.loads(block_json.read_text())
    return b.get("frame") == "project world frame" and "error" not in (b.get("georegistration") or {})


def _count_query_images(P, seq_dirs) -> int:
    """All photos of the query blocks (registered or not), from each block's record."""
    import json

    from ..project import Project
    from ..queries import query_photos

    n = 0
    for seq, d in seq_dirs.items():
        f = d.parent / "block.json"
        n += json.loads(f.read_text())["n_images"] if f.is_file() else len(query_photos(Project.load(P.root), seq))
    return n


def _adjust(ref_rec, blocks, statuses, clicks: dict, auto: set[str], settings: RegisterSettings):
    """The joint adjustment of the registered sequences (reference held) with the clicks and the
    automatic ties in ``clicks``: passes a-c, the last with its covariance."""
    j = build_joint(ref_rec, blocks, clicks)
    # pass a: Sim(3) inliers and the automatic tie points (placed by their reference photos alone, so
    # the query poses move to what both say before any automatic tie is judged by its residual)
    first = {}
    for st in statuses.values():
        for s in st:
            if s.inlier:
                imgs = [n for n in s.ref_used + s.query_used if n in j.image_ids]
                first[s.id] = (s.ref_xyz, imgs)
    first.update(_placed_by_reference(j, {t: j.clicks[t] for t in auto if t in j.clicks}, settings))
    j.set_ties(first)
    _bundle_adjust(j.rec, j.ref_ids, settings, "CAUCHY")
    # pass b: every tie point re-triangulated from all its clicks with the refined poses
    use, dropped = retriangulate_ties(j, settings)
    j.set_ties(use)
    _bundle_adjust(j.rec, j.ref_ids, settings, "CAUCHY")
    # pass c: drop what still disagrees, then the final least-squares BA (+ covariance)
    for tid, pid in list(j.tie_pids.items()):
        p = j.rec.points3D[pid]
        for e in list(p.track.elements):
            im = j.rec.images[e.image_id]
            proj = im.project_point(p.xyz)
            r = np.inf if proj is None else float(np.linalg.norm(np.asarray(proj) - im.points2D[e.point2D_idx].xy))
            if r > _max_px(tid, settings):
                dropped.setdefault(tid, []).append({"image": im.name, "residual_px": r})
                if im.points2D[e.point2D_idx].point3D_id != pid:   # (rare) no longer linked to it
                    continue
                if j.rec.points3D[pid].track.length() > 2:
                    j.rec.delete_observation(e.image_id, e.point2D_idx)
                else:
                    j.rec.delete_point3D(pid)
                    del j.tie_pids[tid]
                    break
    summary, cov = _bundle_adjust(j.rec, j.ref_ids, settings, "TRIVIAL", covariance=True)
    return j, summary, cov, dropped


def _without(clicks: dict, ties: set[str], seqs: set[str]) -> dict:
    """``clicks`` with the given ties' clicks in photos of ``seqs`` removed (a tie left with no query
    click is dropped)."""
    prefixes = tuple(f"queries/{q}/" for q in seqs)
    out = {}
    for tid, obs in clicks.items():
        if tid in ties:
            obs = {n: xy for n, xy in obs.items() if not n.startswith(prefixes)}
            if not any(n.startswith("queries/") for n in obs):
                continue
        out[tid] = obs
    return out


def _solution(j: Joint, cov) -> dict[str, tuple[Pose, float]]:
    """Query photo -> (its pose with the BA's covariance, the median depth of the points it sees)."""
    out = {}
    for iid in j.rec.reg_image_ids():
        if iid in j.ref_ids:
            continue
        out[j.rec.images[iid].name] = (_ba_pose(j.rec, cov, iid), _median_depth(j.rec, j.rec.images[iid]))
    return out


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


def solution_shift(a: tuple[Pose, float], s: tuple[Pose, float], on: str) -> tuple[float, float | None, float | None]:
    """How far one photo moved between two solutions ``a`` and ``s`` (each: pose with covariance,
    median depth), and each solution's 1-sigma of that quantity (None without a covariance):
    - ``"centre"``: the camera centre;
    - ``"footprint"``: what the camera sees, the ground point on its optical axis at its median
      depth (fixed in the world by solution ``a``) in the camera's frame. A camera that swings about
      the ground it sees (rotation and position trading off, a mode the photo's own rays barely
      hold) moves its centre but not this; biased ties, which shift the image, move both."""
    (pa, depth), (ps, _) = a, s
    if on == "centre":
        return float(np.linalg.norm(pa.center - ps.center)), _position_sigma(pa), _position_sigma(ps)
    X = pa.center + pa.R.T @ np.array([0.0, 0.0, depth])

    def sigma(p: Pose) -> float | None:
        if p.covariance is None:
            return None
        J = p.point_jacobian(X)
        return float(np.sqrt(np.trace(J @ p.covariance @ J.T)))

    return float(np.linalg.norm(pa.transform(X[None])[0] - ps.transform(X[None])[0])), sigma(pa), sigma(ps)


def choose_smooth(all_ties: dict, smooth_only: dict, factor: float, on: str = "both") -> dict[str, dict]:
    """Per sequence, whether its rough-surface automatic ties are biased: the two solutions (all ties,
    smooth-surface ties only) differ by more than ``factor`` x the spread their difference would have
    if both were unbiased, sqrt(sigma_smooth^2 - sigma_all^2) (a Hausman test; medians over the
    sequence's photos) in what ``on`` measures (:func:`solution_shift`: "centre" or "footprint"), or
    in both (``"both"``: biased ties move the camera and its view; a camera swinging about its view
    moves only the first). Inputs: photo -> (pose with covariance, median depth) of each solution."""
    if on == "both":
        c, f = choose_smooth(all_ties, smooth_only, factor, "centre"), choose_smooth(all_ties, smooth_only, factor, "footprint")
        return {q: {**f[q], "smooth_only": c[q]["smooth_only"] and f[q]["smooth_only"], "on": "both",
                    "centre_shift_m": c[q]["shift_m"], "centre_limit_m": c[q]["limit_m"]} for q in f}
    seqs: dict[str, list[str]] = {}
    for n in all_ties:
        if n in smooth_only:
            seqs.setdefault(n.split("/")[1], []).append(n)
    out = {}
    for q, names in sorted(seqs.items()):
        shifts = [solution_shift(all_ties[n], smooth_only[n], on) for n in names]
        d = float(np.median([x[0] for x in shifts]))
        sa = [x[1] for x in shifts if x[1] is not None]
        ss = [x[2] for x in shifts if x[2] is not None]
        if not sa or not ss:
            out[q] = {"smooth_only": True, "shift_m": d, "limit_m": None, "on": on}
            continue
        spread = float(np.sqrt(max(np.median(ss) ** 2 - np.median(sa) ** 2, 0.0)))
        out[q] = {"smooth_only": bool(d > factor * spread), "shift_m": d, "limit_m": factor * spread, "on": on}
    return out


def tie_test_words(c: dict) -> str:
    """One sequence's smooth-surface test (a record of ``choose_smooth``, as in registration.json;
    records without ``on`` predate the footprint test and compared centres) in words."""
    def lim(v):
        return "-" if v is None else f"{v:.3f}"
    what = "centres" if c.get("on", "centre") == "centre" else "footprints"
    words = f"the two solutions' {what} {c['shift_m']:.3f} m apart, limit {lim(c['limit_m'])} m"
    if "centre_shift_m" in c:
        words += f"; centres {c['centre_shift_m']:.3f} m apart, limit {lim(c['centre_limit_m'])} m"
    return words


def _adjust_choosing_ties(ref_rec, blocks, statuses, clicks: dict, auto: set[str], rough: set[str],
                          settings: RegisterSettings):
    """The joint adjustment, with the automatic ties on rough model surface (``rough``) kept only for
    the sequences where they are not biased (``choose_smooth``); ``rough`` empty: one adjustment."""
    if not rough:
        return (*_adjust(ref_rec, blocks, statuses, clicks, auto, settings), {})
    mode = settings.smooth_surface.choose
    smooth_clicks = _without(clicks, rough, set(blocks))
    if mode == "smooth":
        return (*_adjust(ref_rec, blocks, statuses, smooth_clicks, auto, settings), {})
    a = _adjust(ref_rec, blocks, statuses, clicks, auto, settings)
    s = _adjust(ref_rec, blocks, statuses, smooth_clicks, auto, settings)
    choice = choose_smooth(_solution(a[0], a[2]), _solution(s[0], s[2]), settings.smooth_surface.test_factor,
                           settings.smooth_surface.test_on)
    picked = {q for q, c in choice.items() if c["smooth_only"]}
    for q, c in choice.items():
        log.info("sequence %s: %s (%s)", q, "automatic ties on smooth surface only" if c["smooth_only"]
                 else "all automatic ties", tie_test_words(c))
    if not picked:
        return (*a, choice)
    if picked >= set(choice):
        return (*s, choice)
    return (*_adjust(ref_rec, blocks, statuses, _without(clicks, rough, picked), auto, settings), choice)


# --- the stage ---------------------------------------------------------------------------------

def run(project: Project | str | Path, settings: RegisterSettings, force: bool = False) -> dict:
    """``gtkit register DIR``: pseudo-GT poses of every registered query photo."""
    quiet_colmap()
    project = project if isinstance(project, Project) else Project.load(project)
    P = project.paths
    if settings.systematic_swing_where not in ("biased", "all"):
        raise GtkitError(f'[register] systematic_swing_where = "{settings.systematic_swing_where}": '
                         'expected "biased" or "all"', project.paths.root / PROJECT_FILE)
    if settings.smooth_surface.choose not in ("test", "smooth"):
        raise GtkitError(f'[register.smooth_surface] choose = "{settings.smooth_surface.choose}": '
                         'expected "test" or "smooth"', project.paths.root / PROJECT_FILE)
    if settings.smooth_surface.test_on not in ("both", "footprint", "centre"):
        raise GtkitError(f'[register.smooth_surface] test_on = "{settings.smooth_surface.test_on}": '
                         'expected "both", "footprint" or "centre"', project.paths.root / PROJECT_FILE)
    out = P.stage(STAGE)
    ref_dir = P.stage(REFERENCE_STAGE) / "model"
    if not ref_dir.is_dir():
        raise GtkitError("reference block missing: run `gtkit sfm DIR --block reference` first", ref_dir)
    seq_dirs = {s: P.stage(QUERIES_STAGE) / s / "model" for s in P.query_sequences()}
    model = _reference_model(P) if settings.cross.enabled and settings.smooth_surface.enabled else None
    inputs = {"tiepoints": file_fingerprint(P.tiepoints),
              "reference": file_fingerprint(ref_dir / "images.bin"),
              "queries": {s: file_fingerprint(d / "images.bin") for s, d in seq_dirs.items()}}
    if model is not None:   # the automatic ties it keeps depend on it
        from ..export.sources import input_fingerprint_paths
        inputs["model"] = [file_fingerprint(f) for f in input_fingerprint_paths(model)]
    if not force and stage_done(out, settings, inputs):
        import json
        return json.loads((out / "registration.json").read_text())
    start_stage_clock(out)   # (also under --force): its log goes to work/register/log.txt
    t0 = time.time()
    tiepoints = read_tiepoints(P.tiepoints) if P.tiepoints.is_file() else []   # no file: no clicks
    ref_rec = pycolmap.Reconstruction(ref_dir)
    ref_cache = {"poses": model_poses(ref_rec), "cams": model_cameras(ref_rec)}
    seq_report, blocks, statuses, resected = {}, {}, {}, {}
    ref_db = P.stage(REFERENCE_STAGE) / "database.db"
    ref_points: dict[str, ReferencePoints] = {}   # read once, when first needed

    def reference_points() -> ReferencePoints:
        if "ref" not in ref_points:
            ref_points["ref"] = ReferencePoints(ref_rec, ref_db, settings.cross.descriptors_per_point)
        return ref_points["ref"]

    def gps_centre(name: str) -> np.ndarray | None:
        """The photo's GPS position in the project frame (EXIF GPS + altitude), None without one."""
        try:
            m = read_photo_meta(P.images / name)
        except GtkitError:
            return None
        if not m.has_gps or m.altitude is None:
            return None
        return project.frame.wgs84_to_local(m.lon, m.lat, m.altitude)

    def reference_neighbour_priors(name: str, k: int = 2) -> list[Pose]:
        """Poses at the photo's GPS position with the attitude of the nearest reference photos (a photo
        held out of the reference flight looks the way its neighbours do), at its GPS height and at
        theirs (consumer altitudes drift)."""
        C = gps_centre(name)
        if C is None:
            return []
        refs = sorted(ref_cache["poses"].values(), key=lambda q: float(np.linalg.norm(q.center[:2] - C[:2])))[:k]
        out = []
        for q in refs:
            out.append(Pose.from_center(q.R, C))
            out.append(Pose.from_center(q.R, np.array([C[0], C[1], q.center[2]])))
        return out

    def solo_block(seq: str) -> pycolmap.Reconstruction | None:
        """A sequence whose SfM made no model: an empty block holding its camera (gtkit.queries'
        resolution: the reference block's calibration of the same camera, else EXIF), to which its
        photos are added one by one as they are resected from automatic matches."""
        from ..queries import query_cameras, query_photos

        names = query_photos(project, seq)
        if not names or not (P.stage(QUERIES_STAGE) / seq / "database.db").is_file():
            return None
        try:
            cams = query_cameras(project, names)
        except GtkitError:
            return None
        rec = pycolmap.Reconstruction()
        c = cams[names[0]].camera.to_pycolmap()
        c.camera_id = 1
        rec.add_camera_with_trivial_rig(c)
        return rec

    def match_reference(seq: str):
        """A left-out photo of ``seq`` resected from automatic matches to the reference points."""
        def match(name: str, qrec: pycolmap.Reconstruction):
            if not settings.cross.enabled or not ref_db.is_file():
                return None, 0, "automatic matching is off or the reference database is missing"
            priors = candidate_priors(name, qrec, lambda n: prior_pose(P.images / n, project.frame))
            # its nearest registered neighbours' poses (in flight order), for a wider search
            order = sorted({im.name for im in qrec.images.values() if im.has_pose} | {name})
            k = order.index(name)
            near = [Pose.from_pycolmap(qrec.find_image_with_name(n).cam_from_world())
                    for n in sorted((n for n in order if n != name), key=lambda m: abs(order.index(m) - k))[:2]]
            by_reference = reference_neighbour_priors(name)
            priors = priors + by_reference
            if not priors and not near:
                return None, 0, "no GPS to guide matching"
            feats = photo_features(P.stage(QUERIES_STAGE) / seq / "database.db", name)
            if feats is None:
                return None, 0, "no features in its sequence's database"
            cam = Camera.from_pycolmap(qrec.cameras[sorted(qrec.cameras)[0]])
            found = [match_photo(p, cam, *feats, reference_points(), settings.cross) for p in priors]
            pose, rows, _ = max(found, key=lambda f: len(f[1])) if found else (None, [], [])
            if pose is None and settings.bootstrap.enabled:   # a wider search around its own and its neighbours' poses
                guides = priors[:1] + near + [q for q in by_reference if q is not priors[0]]
                # then wider still, at last over the whole image: a low photo under consumer GPS and
                # without attitude is hundreds of pixels off, or turned, from its guides (Brighton at
                # 35 m with ~10 m GPS: found only with the whole image)
                r0 = settings.bootstrap.radius_px
                for radius in (r0, 4 * r0, max(cam.width, cam.height)):
                    found = [(g, match_photo_wide(g, cam, *feats, reference_points(), settings.cross, radius))
                             for g in guides]
                    found = [f for g, f in found if f[0] is not None
                             and np.linalg.norm(f[0].center - g.center) <= settings.bootstrap.max_offset_m]
                    if found:
                        pose, rows, _ = max(found, key=lambda f: len(f[1]))
                        break
            if pose is None:
                return None, 0, (f"fewer than {settings.cross.min_inliers} consistent matches to the reference "
                                 "points around its metadata pose" + (" or its neighbours' poses" if near else ""))
            return pose, len(rows), ""
        return match

    def bootstrap(seq: str, qrec: pycolmap.Reconstruction) -> Bootstrap:
        """The sequence placed by its photos' automatic matches (no clicks needed)."""
        if not settings.bootstrap.enabled:
            return Bootstrap(None, "placing sequences by automatic matches is off ([register.bootstrap] enabled)", {})
        if not settings.cross.enabled or not ref_db.is_file():
            return Bootstrap(None, "automatic matching is off or the reference database is missing", {})
        sdir = P.stage(QUERIES_STAGE) / seq
        db = sdir / "database.db"
        if not db.is_file():
            return Bootstrap(None, "its sequence's feature database is missing", {})
        georegistered = _block_georegistered(sdir / "block.json")
        cams = model_cameras(qrec)

        def priors(name):
            out = []
            meta = prior_pose(P.images / name, project.frame)
            if meta is not None:
                out.append(("metadata", meta))
            if georegistered:
                out.append(("block GPS", Pose.from_pycolmap(qrec.find_image_with_name(name).cam_from_world())))
            return out

        features: dict = {}

        def match(name, prior, wider=True):
            if name not in features:
                features[name] = photo_features(db, name)
            feats = features[name]
            if feats is None:
                return None, np.zeros((0, 3)), np.zeros(0, int)
            ref = reference_points()
            radii = (settings.bootstrap.radius_px, 2 * settings.bootstrap.radius_px)
            for radius in radii if wider else radii[:1]:   # then a wider search
                pose, rows, kk = match_photo_wide(prior, cams[name], *feats, ref, settings.cross, radius)
                if pose is not None:
                    break
            return pose, ref.xyz[rows], kk

        def search(name):
            C = gps_centre(name)
            if C is None:
                return []
            b = settings.bootstrap
            return [(f"GPS, attitude searched (yaw {yaw:.0f}, pitch {pitch:.0f})", Pose.from_dji(yaw, pitch, 0.0, C))
                    for pitch in b.search_pitches_deg for yaw in np.arange(0.0, 360.0, b.search_yaw_step_deg)]

        return bootstrap_sequence(qrec, priors, match, settings, search)

    for seq, d in seq_dirs.items():
        if not d.is_dir():
            # its SfM made no model (e.g. photos held out of a flight, too far apart to match each
            # other): each photo on its own, resected from automatic matches to the reference points
            qrec = solo_block(seq) if (d.parent / "block.json").is_file() else None
            res = resect_sequence(seq, qrec, d.parent / "block.json", P.images, tiepoints,
                                  lambda obs: _place(obs, ref_cache["poses"], ref_cache["cams"], ref_rec,
                                                     settings.tie_max_px)[0], settings.tie_max_px,
                                  match_reference(seq)) if qrec is not None else {}
            done = {n: r for n, r in res.items() if r["resected"]}
            if not done:
                why = ("no query-block model (run `gtkit sfm DIR --block queries`)" if qrec is None else
                       "its SfM made no model and none of its photos matched the reference points on its own"
                       + (f" ({next(iter(res.values())).get('auto_reason')})" if res else ""))
                seq_report[seq] = {"status": "error", "error": why, "needs_clicks": qrec is not None,
                                   **({"left_out_by_sfm": res} if res else {})}
                log.error("sequence %s not registered: %s", seq, why)
                continue
            blocks[seq], statuses[seq] = qrec, []
            resected.update(done)
            seq_report[seq] = {"status": "registered", "registered_by": "single photos (its SfM made no model)",
                               "scale": 1.0, "n_tiepoints": 0, "n_sim3_inliers": 0, "sim3_rmse_m": None,
                               "left_out_by_sfm": res}
            log.info("sequence %s: no SfM model; %d of %d photos resected one by one from automatic matches",
                     seq, len(done), len(res))
            continue
        qrec = pycolmap.Reconstruction(d)
        n_clicked = sum(1 for tp in tiepoints if tp.in_block(f"queries/{seq}/"))
        check = None
        try:
            sim, st = register_sequence(seq, qrec, ref_rec, tiepoints, settings, ref_cache)
            boot = None
            weak = weak_click_support(st, settings.bootstrap)
            if weak:   # a few clicks, or all in one photo: one gross mistake among them moves the block
                check = bootstrap(seq, qrec)
                if check.sim is not None:
                    shift = sim3_disagreement(sim, check.sim, qrec)
                    if shift > settings.bootstrap.agree_m:
                        raise RegistrationError(
                            f"its clicks ({weak}) place it {shift:.1f} m from where "
                            f"{check.record()['n_photos_agreeing']} of its photos' automatic matches agree to put it: "
                            "placed by the automatic matches (check its clicks)")
        except RegistrationError as e:
            clicks_why = str(e) if n_clicked else "no clicked tie points"
            boot = check if check is not None and check.sim is not None else bootstrap(seq, qrec)
            if boot.sim is None:
                err = (f"{clicks_why}; automatic matches: {boot.reason}; "
                       f"click 3 or more tie points in its photos (queries/{seq}/) and the reference photos "
                       "(`gtkit annotate DIR`)")
                seq_report[seq] = {"status": "error", "error": err, "needs_clicks": True,
                                   "clicks": clicks_why, "automatic": boot.record()}
                log.error("sequence %s not registered: %s", seq, err)
                continue
            sim, st = boot.sim, []
            log.info("sequence %s: placed by automatic matches (%s): %d of %d photos agree, Sim(3) from %s",
                     seq, clicks_why, boot.record()["n_photos_agreeing"], len(boot.photos), boot.fit_from)
        qrec.transform(sim)
        blocks[seq], statuses[seq] = qrec, st
        if boot is None:
            seq_report[seq] = {"status": "registered", "registered_by": "clicked tie points", "scale": float(sim.scale),
                               "n_tiepoints": len(st), "n_sim3_inliers": sum(s.inlier for s in st),
                               "sim3_rmse_m": float(np.sqrt(np.mean([s.sim3_residual_m ** 2 for s in st if s.inlier])))}
        else:
            seq_report[seq] = {"status": "registered", "registered_by": "automatic matches", "scale": float(sim.scale),
                               "n_tiepoints": n_clicked, "n_sim3_inliers": 0, "sim3_rmse_m": None,
                               "clicks": clicks_why, "automatic": boot.record()}
        # photos the sequence's SfM left out: resected from their clicks, then adjusted with the rest
        res = resect_sequence(seq, qrec, P.stage(QUERIES_STAGE) / seq / "block.json", P.images, tiepoints,
                              lambda obs: _place(obs, ref_cache["poses"], ref_cache["cams"], ref_rec,
                                                 settings.tie_max_px)[0], settings.tie_max_px, match_reference(seq))
        if res:
            seq_report[seq]["left_out_by_sfm"] = res
            resected.update({n: r for n, r in res.items() if r["resected"]})
    t_sim = time.time()
    result = {"sequences": seq_report, "n_registered": 0, "n_images": _count_query_images(P, seq_dirs), "images": {}}
    out.mkdir(parents=True, exist_ok=True)
    if not blocks:
        for f in ("poses.txt", "intrinsics.txt", "covariances.txt", GUIDANCE_FILE, COVARIANCE_FILE):
            (out / f).unlink(missing_ok=True)
        write_json(out / "registration.json", result)
        mark_stage_done(out, settings, inputs, n_registered=0)
        return result
    # every click of every tie point that touches a registered sequence
    prefixes = tuple(f"queries/{s}/" for s in blocks)
    clicks = {tp.id: {o.image: (o.x, o.y) for o in tp.observations}
              for tp in tiepoints if any(o.image.startswith(prefixes) for o in tp.observations)}
    t_cm = time.time()
    qp, qc = {}, {}
    for rec_q in blocks.values():
        qp.update(model_poses(rec_q))
        qc.update(model_cameras(rec_q))
    auto = cross_matches(qp, qc, [P.stage(QUERIES_STAGE) / sq / "database.db" for sq in blocks], ref_rec,
                         ref_db, settings.cross, ref=ref_points.get("ref"))
    n_auto_found = len(auto)
    smooth = smooth_surface_filter(model, project.frame, settings.smooth_surface) if auto else None
    rough: set[str] = set()
    if smooth is not None:
        ids = sorted(auto)
        keep = smooth(np.array([ref_rec.points3D[reference_point_of(t)].xyz for t in ids]))
        rough = {t for t, k in zip(ids, keep) if not k}
        log.info("automatic tie points: %d of %d on smooth model surface", len(auto) - len(rough), n_auto_found)
    clicks.update(auto)
    solo = sorted(n for n, r in resected.items() if r.get("resected") and n in qp)
    if solo and settings.extend.enabled:
        ext, ext_rec = extension_ties(
            ref_rec, ref_db, {n: (qp[n], qc[n], P.stage(QUERIES_STAGE) / n.split("/")[1] / "database.db") for n in solo},
            P.images, out / "extend", settings.extend, num_threads=settings.num_threads)
        for n, r in ext_rec.items():
            resected[n]["extended"] = r
        clicks.update(ext)
        auto.update(ext)
    t_cm = time.time() - t_cm
    j, summary, cov, dropped, auto_choice = _adjust_choosing_ties(ref_rec, blocks, statuses, clicks, set(auto), rough,
                                                                 settings)
    auto = {t: v for t, v in auto.items() if t in j.clicks}
    # the sequences whose automatic ties off smooth surface were dropped
    smooth_only = (sorted(blocks) if rough and settings.smooth_surface.choose == "smooth"
                   else sorted(q for q, c in auto_choice.items() if c["smooth_only"]))
    t_ba = time.time()
    rec = j.rec
    qids = [i for i in rec.reg_image_ids() if i not in j.ref_ids]
    tie_set = set(j.tie_pids.values())
    sfm_err = point_reprojection_errors(rec, [p for p in rec.points3D if p not in tie_set])
    poses, cams, covs, per_image = {}, {}, {}, {}
    tie_count: dict[str, int] = {}
    auto_count: dict[str, int] = {}
    for tid, pid in j.tie_pids.items():
        cnt = auto_count if tid.startswith(AUTO_PREFIX) else tie_count
        for e in rec.points3D[pid].track.elements:
            n = rec.images[e.image_id].name
            cnt[n] = cnt.get(n, 0) + 1
    swung = set(blocks) if settings.systematic_swing_where == "all" else set(smooth_only)
    floors: dict[str, float] = {}   # photo -> the systematic part's centre variance (clicks do not lower it)
    for iid in qids:
        im = rec.images[iid]
        pose = _ba_pose(rec, cov, iid)
        ok = pose.covariance is not None
        sigma_ba = _position_sigma(pose)
        if ok and settings.systematic_swing_px > 0 and im.name.split("/")[1] in swung:
            sw = swing_covariance(pose.t, _median_depth(rec, im), rec.cameras[im.camera_id].mean_focal_length(),
                                  settings.systematic_swing_px)
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
    # per tie point: final residuals, and the list of bad ones (gross click mistakes)
    tie_table, bad = {}, {}
    status_by_id = {s.id: (seq, s) for seq, st in statuses.items() for s in st}
    for tid in clicks:
        if tid.startswith(AUTO_PREFIX):
            continue
        seq, s = status_by_id.get(tid, (None, None))
        note = s.reason if s else "not usable for the Sim(3)"
        if seq is None:   # no Sim(3) status (its sequence placed by automatic matches, or its photo left out
            # of its sequence's SfM): named by its query clicks, which still count in the joint BA
            seq = next((n.split("/")[1] for n in clicks[tid] if n.startswith(prefixes)), None)
            if seq is not None and seq_report[seq].get("registered_by") == "automatic matches":
                note = "its sequence was placed by the automatic matches (its clicks not used for the Sim(3))"
        row = {"sequence": seq, "sim3_inlier": bool(s and s.inlier), "sim3_residual_m": s.sim3_residual_m if s else None,
               "in_final_ba": tid in j.tie_pids, "note": note}
        if tid in j.tie_pids:
            p = rec.points3D[j.tie_pids[tid]]
            row["reproj_px"] = {rec.images[e.image_id].name: float(np.linalg.norm(
                np.asarray(rec.images[e.image_id].project_point(p.xyz)) - rec.images[e.image_id].points2D[e.point2D_idx].xy))
                for e in p.track.elements}
        drops = (s.dropped_clicks if s else []) + dropped.get(tid, [])
        if drops or (s and s.mistake and tid not in j.tie_pids):
            seen = {}
            for dd in drops:
                seen.setdefault(dd["image"], dd)
            bad[tid] = {"sequence": seq, "reason": ("clicks dropped as mistakes" if drops else s.reason),
                        "dropped_clicks": [{"image": v["image"], "residual_px": float(v["residual_px"])} for v in seen.values()],
                        "in_final_ba": tid in j.tie_pids}
        tie_table[tid] = row
    tie_err = [r for row in tie_table.values() for r in row.get("reproj_px", {}).values()]
    for seq in blocks:
        seq_report[seq]["n_tiepoints_final_ba"] = sum(1 for r in tie_table.values() if r["sequence"] == seq and r["in_final_ba"])
    result.update({
        "n_registered": len(poses), "images": per_image,
        "median_reproj_px": float(np.median(sfm_err)) if len(sfm_err) else None,
        "mean_reproj_px": float(np.mean(sfm_err)) if len(sfm_err) else None,
        "median_tiepoint_reproj_px": float(np.median(tie_err)) if tie_err else None,
        "median_auto_tiepoint_reproj_px": (float(np.median(point_reprojection_errors(
            rec, [pid for t, pid in j.tie_pids.items() if t.startswith(AUTO_PREFIX)])))
            if any(t.startswith(AUTO_PREFIX) for t in j.tie_pids) else None),
        "n_tiepoints_in_ba": sum(1 for t in j.tie_pids if not t.startswith(AUTO_PREFIX)),
        "n_auto_tiepoints_found": n_auto_found, "auto_tiepoints_on_smooth_surface_only": smooth_only,
        "auto_ties_test_by_sequence": auto_choice,
        "n_auto_tiepoints": len(auto), "n_auto_tiepoints_in_ba": sum(1 for t in j.tie_pids if t.startswith(AUTO_PREFIX)),
        "bad_tiepoints": bad, "tiepoints": tie_table,
        "ba_final_cost": float(summary.final_cost) if hasattr(summary, "final_cost") else None,
        "seconds": {"sim3": t_sim - t0, "cross_matching": t_cm, "joint_ba": t_ba - t_sim - t_cm}})
    (out / "model").mkdir(exist_ok=True)
    rec.write(out / "model")
    write_poses(out / "poses.txt", poses, header="pseudo-GT poses of the query photos (gtkit register)")
    write_intrinsics(out / "intrinsics.txt", cams)
    if covs:
        write_covariances(out / "covariances.txt", covs)
    from ..queries import query_photos
    _write_guidance(out, rec, cov, j.ref_ids, floors, ref_rec, settings.guidance,
                    {q: query_photos(project, q) for q, v in seq_report.items() if v.get("status") == "error"})
    write_json(out / "registration.json", result)
    mark_stage_done(out, settings, inputs, n_registered=result["n_registered"])
    return result
