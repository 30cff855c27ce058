"""The joint model: the reference photos holding tie clicks (held fixed) and every registered query
block in one pycolmap Reconstruction, each tie point a 3D point observed in both, and its bundle
adjustment in passes (robust, tie points re-triangulated, final least squares with covariance)."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ...determinism import ba_threads
from ..crossmatch import AUTO_PREFIX
from ..geometry import model_cameras, model_poses, triangulate_many
from .covariance import joint_covariance
from .settings import RegisterSettings

log = logging.getLogger(__package__)   # the stage's log: gtkit.sfm.register


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
    seq_cams: dict[str, set[int]] = field(default_factory=dict)   # sequence -> its cameras' ids here
    calibrated: set[int] = field(default_factory=set)   # query cameras whose intrinsics the BA refines
    undetermined: dict[str, str] = field(default_factory=dict)   # sequence -> why its covariance is undetermined

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
    seq_cams: dict[str, set[int]] = {}
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
        seq_cams[seq] = set(cam_map.values())
    clicks = {tid: {n: xy for n, xy in obs.items() if n in b.image_ids} for tid, obs in clicks.items()}
    return Joint(b.rec, b.image_ids, ref_ids, slot, clicks, seq_cams=seq_cams)


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


def _problem(rec, ref_ids, settings: RegisterSettings, loss: str, calibrated: set[int] = frozenset(),
             held: set[int] = frozenset()):
    """The joint model's bundle adjuster (not solved): the reference photos held, and ``held`` query
    photos too; ``calibrated``: query cameras whose focal, principal point and distortion it refines
    (else only with ``refine_query_intrinsics``, focal and distortion)."""
    cfg = pycolmap.BundleAdjustmentConfig()
    ref_cams = {rec.images[i].camera_id for i in ref_ids}
    for iid in rec.reg_image_ids():
        cfg.add_image(iid)
    for iid in set(ref_ids) | set(held):
        cfg.set_constant_rig_from_world_pose(rec.images[iid].frame_id)
    for cid in rec.cameras:
        if cid in ref_cams or not (settings.refine_query_intrinsics or cid in calibrated):
            cfg.set_constant_cam_intrinsics(cid)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_principal_point = bool(calibrated)
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss)
    opts.ceres.loss_function_scale = settings.ba_loss_scale_px
    opts.ceres.solver_options.max_num_iterations = settings.ba_max_iterations
    opts.ceres.solver_options.num_threads = ba_threads(settings.num_threads, settings.reproducible)
    return pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)


def _bundle_adjust(rec, ref_ids, settings: RegisterSettings, loss: str, calibrated: set[int] = frozenset()):
    """One BA of the joint model (:func:`_problem`); its Ceres summary."""
    return _problem(rec, ref_ids, settings, loss, calibrated).solve()


def _median_depth(rec, im) -> float:
    """Median depth (camera z, metres) of the 3D points a registered image observes."""
    X = np.array([rec.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()])
    if not len(X):
        return 0.0
    M = im.cam_from_world().matrix()
    return float(np.median(X @ M[:, :3].T[:, 2] + M[2, 3]))


def point_reprojection_errors(rec, point_ids, image_ids: set[int] | None = None) -> np.ndarray:
    """Reprojection errors (px) of the points' observations (only those in ``image_ids`` where given)."""
    errs = []
    for pid in point_ids:
        p = rec.points3D[pid]
        for e in p.track.elements:
            if image_ids is not None and e.image_id not in image_ids:
                continue
            im = rec.images[e.image_id]
            proj = im.project_point(p.xyz)
            errs.append(np.inf if proj is None else float(np.linalg.norm(np.asarray(proj) - im.points2D[e.point2D_idx].xy)))
    return np.asarray(errs)



def ties_per_photo(j: Joint, seq: str) -> int:
    """The median number of automatic tie points the photos of ``seq`` observe in the joint model now."""
    counts = {n: 0 for n in j.image_ids if n.startswith(f"queries/{seq}/")}
    for tid, pid in j.tie_pids.items():
        if not tid.startswith(AUTO_PREFIX):
            continue
        for e in j.rec.points3D[pid].track.elements:
            n = j.rec.images[e.image_id].name
            if n in counts:
                counts[n] += 1
    return int(np.median(list(counts.values()))) if counts else 0


def _seq_tie_residual(rec, j: Joint, seq: str) -> float:
    """Median reprojection error (px) of the tie points' observations in the photos of ``seq``."""
    ids = {iid for n, iid in j.image_ids.items() if n.startswith(f"queries/{seq}/")}
    errs = point_reprojection_errors(rec, j.tie_pids.values(), ids)
    return float(np.median(errs)) if len(errs) else np.inf


def _calibration_helps(j: Joint, seq: str, settings: RegisterSettings) -> bool:
    """Whether calibrating ``seq``'s cameras from the ties (on a copy of the joint model) lowers its
    tie residuals by more than ``calibration_gain``: a starting calibration taken for the reference's
    by image size alone is kept where the ties confirm it, corrected where they do not."""
    trial = pycolmap.Reconstruction(j.rec)
    r0 = _seq_tie_residual(trial, j, seq)
    _bundle_adjust(trial, j.ref_ids, settings, "CAUCHY", calibrated=j.seq_cams.get(seq, set()))
    r1 = _seq_tie_residual(trial, j, seq)
    log.info("sequence %s: tie residual %.2f px with the reference's calibration, %.2f px calibrated from the ties",
             seq, r0, r1)
    return r1 < (1.0 - settings.calibration_gain) * r0


def _adjust(ref_rec, blocks, statuses, clicks: dict, auto: set[str], settings: RegisterSettings,
            calibrate: dict[str, str] | None = None):
    """The joint adjustment of the registered sequences (reference held) with the clicks and the
    automatic ties in ``clicks``: passes a-c, the last with its covariance. ``calibrate``: sequence ->
    "self" (its cameras calibrated from the ties from pass b on) or "confirm" (only where that lowers
    its tie residuals: :func:`_calibration_helps`), where its photos hold ``calibrate_from_ties``
    automatic ties each after pass a (``Joint.calibrated``)."""
    calibrate = calibrate or {}
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
    if settings.calibrate_from_ties > 0:
        for q, how in sorted(calibrate.items()):
            if ties_per_photo(j, q) >= settings.calibrate_from_ties and (how == "self" or _calibration_helps(j, q, settings)):
                j.calibrated |= j.seq_cams.get(q, set())
        if j.calibrated:   # the ties placed: the cameras first calibrated on them, then every tie re-judged
            _bundle_adjust(j.rec, j.ref_ids, settings, "CAUCHY", calibrated=j.calibrated)
    # pass b: every tie point re-triangulated from all its clicks with the refined poses
    use, dropped = retriangulate_ties(j, settings)
    j.set_ties(use)
    _bundle_adjust(j.rec, j.ref_ids, settings, "CAUCHY", calibrated=j.calibrated)
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
    ba = _problem(j.rec, j.ref_ids, settings, "TRIVIAL", j.calibrated)
    summary = ba.solve()
    cov, j.undetermined = joint_covariance(
        j, ba, lambda held: _problem(j.rec, j.ref_ids, settings, "TRIVIAL", j.calibrated, held))
    return j, summary, cov, dropped
