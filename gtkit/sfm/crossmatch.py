"""Automatic tie points between the blocks: each registered query photo matched to the reference
block's own 3D points, guided by the photo's pose.

After the tie-point Sim(3) a query photo's pose is known to a metre or so. Every reference 3D point
in front of it is projected into it and compared (SIFT descriptor, ratio test among the query
keypoints within ``radius_px``) with the keypoints near its projection; the descriptor used is the one
of the point's reference observation that looked at it from the closest direction, so a shallow
query is compared with the oblique that saw the ground like it did. A PnP RANSAC on the undistorted
pixels keeps the consistent matches; a second pass around the pose PnP found (``refine_radius_px``)
adds the matches the first radius was too coarse for.

Each kept match becomes a tie point ``auto:ref<reference point id>`` with the query observation(s)
and up to ``track_obs`` of the point's reference observations: the point is fixed by the reference
photos (held in the joint BA), so every match constrains its query photo in both image directions,
where a two-view query-reference match constrains it only across its epipolar line. Matches spread
over the whole photo hold a query block's position and tilt apart. They join the annotators' clicks
as extra, unlisted tie points in the joint BA, where the same re-triangulation test (with the
refined poses) drops any that disagree with the geometry.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from ..camera import Camera
from ..pose import Pose

log = logging.getLogger(__name__)
AUTO_PREFIX = "auto:"   # ids of automatic tie points: auto:ref<reference point id>


def auto_tie_id(point3d_id: int) -> str:
    return f"{AUTO_PREFIX}ref{point3d_id}"


def reference_point_of(tie_id: str) -> int:
    """The reference block's 3D point an automatic tie point was matched to."""
    return int(tie_id[len(AUTO_PREFIX) + 3:])


@dataclass
class CrossMatchSettings:
    enabled: bool = True          # automatic tie points (False: the annotators' clicks only)
    radius_px: float = 40.0       # first pass: query keypoints this close to a reference point's projection
    refine_radius_px: float = 6.0  # second pass, around the PnP pose of the first
    ratio: float = 0.8            # best / second-best descriptor distance among those keypoints
    pnp_px: float = 3.0           # PnP RANSAC threshold (undistorted pixels)
    min_inliers: int = 15         # fewer PnP inliers: the photo gets no automatic tie points
    max_per_photo: int = 600      # keep at most this many a photo (spread: random)
    track_obs: int = 4            # reference observations each tie point takes from its reference point
    descriptors_per_point: int = 4  # reference observations (directions) whose descriptors are kept per point


class ReferencePoints:
    """The reference block's 3D points with a few observations each (photo, pixel, descriptor,
    direction from the point to the photo), chosen to span the directions the point was seen from."""

    def __init__(self, rec: pycolmap.Reconstruction, db_path: Path, k: int):
        names = {iid: im.name for iid, im in rec.images.items() if im.has_pose}
        pids = [pid for pid, p in rec.points3D.items() if p.track.length() >= 2]
        n = len(pids)
        self.ids = np.array(pids, np.int64)
        self.xyz = np.array([rec.points3D[p].xyz for p in pids]).reshape(-1, 3)
        self.names = sorted(set(names.values()))
        col = {nm: i for i, nm in enumerate(self.names)}
        centre = {iid: rec.images[iid].projection_center() for iid in names}
        self.img = np.full((n, k), -1, np.int32)
        self.kp = np.zeros((n, k), np.int32)
        self.xy = np.zeros((n, k, 2))
        self.dirs = np.zeros((n, k, 3))
        want: dict[int, list[tuple[int, int, int]]] = {}
        for i, pid in enumerate(pids):
            els = [e for e in rec.points3D[pid].track.elements if e.image_id in names]
            d = np.array([centre[e.image_id] - self.xyz[i] for e in els])
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            pick = [0]
            while len(pick) < min(k, len(els)):   # farthest direction from those picked so far
                cos = (d @ d[pick].T).max(axis=1)
                cos[pick] = 2.0
                pick.append(int(np.argmin(cos)))
            for j, e in enumerate(els[q] for q in pick):
                self.img[i, j], self.kp[i, j] = col[names[e.image_id]], e.point2D_idx
                self.xy[i, j] = rec.images[e.image_id].points2D[e.point2D_idx].xy
                self.dirs[i, j] = d[pick[j]]
                want.setdefault(e.image_id, []).append((i, j, e.point2D_idx))
        self.desc = np.zeros((n, k, 128), np.uint8)
        with pycolmap.Database.open(Path(db_path)) as db:
            for iid, rows in want.items():
                de = db.read_descriptors(iid)
                de = np.asarray(de.data if hasattr(de, "data") else de)
                r = np.array(rows)
                self.desc[r[:, 0], r[:, 1]] = de[r[:, 2]]


def _read_features(db: pycolmap.Database, image_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints x, y as float64; descriptors as float32) of one image of an open COLMAP database."""
    kp = np.asarray(db.read_keypoints(image_id))[:, :2]
    de = db.read_descriptors(image_id)
    de = np.asarray(de.data if hasattr(de, "data") else de)
    return kp.astype(np.float64), de.astype(np.float32)


def _features(db_path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    with pycolmap.Database.open(db_path) as db:
        return {im.name: _read_features(db, im.image_id) for im in db.read_all_images()}


def _match(pose: Pose, cam: Camera, ref: ReferencePoints, tree: cKDTree, dq: np.ndarray, radius: float,
           ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(reference point rows, query keypoint indices) of the ratio-test matches near the projections."""
    uv, front = cam.project(pose.transform(ref.xyz))
    ok = np.flatnonzero(front & cam.in_image(uv, -radius))
    if not len(ok):
        return np.zeros(0, int), np.zeros(0, int)
    to_cam = pose.center - ref.xyz[ok]
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    cos = np.einsum("nkd,nd->nk", ref.dirs[ok], to_cam)
    cos[ref.img[ok] < 0] = -2.0
    j = np.argmax(cos, axis=1)
    dr = ref.desc[ok, j].astype(np.float32)
    dist, nb = tree.query(uv[ok], k=8, distance_upper_bound=radius)
    valid = np.isfinite(dist)
    nb = np.where(valid, nb, 0)
    d = np.linalg.norm(dq[nb] - dr[:, None, :], axis=2)
    d[~valid] = np.inf
    order = np.argsort(d, axis=1)
    best = np.take_along_axis(d, order[:, :1], 1)[:, 0]
    second = np.take_along_axis(d, order[:, 1:2], 1)[:, 0]
    keep = np.isfinite(best) & np.isfinite(second) & (best < ratio * second)
    rows, kq, dbest = ok[keep], nb[keep, order[keep, 0]], best[keep]
    first = np.lexsort((dbest, kq))        # one reference point a query keypoint: the closest descriptor
    uniq = np.ones(len(first), bool)
    uniq[1:] = kq[first][1:] != kq[first][:-1]
    sel = first[uniq]
    return rows[sel], kq[sel]


def _pnp(pose: Pose, cam: Camera, X: np.ndarray, uv: np.ndarray, px: float) -> tuple[Pose | None, np.ndarray]:
    if len(X) < 6:
        return None, np.zeros(len(X), bool)
    pin = cam.pinhole_part()
    und = cam.undistort_pixels(uv)
    rvec, _ = cv2.Rodrigues(pose.R)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X, und, pin.K(), None, rvec.copy(), pose.t.reshape(3, 1).copy(),
                                             useExtrinsicGuess=True, iterationsCount=500, reprojectionError=px,
                                             confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
    mask = np.zeros(len(X), bool)
    if not ok or inl is None:
        return None, mask
    mask[inl.ravel()] = True
    return Pose(cv2.Rodrigues(rvec)[0], tvec.ravel()), mask


def match_photo(pose: Pose, cam: Camera, kq: np.ndarray, dq: np.ndarray, ref: ReferencePoints,
                s: CrossMatchSettings) -> tuple[Pose | None, np.ndarray, np.ndarray]:
    """One query photo (keypoints ``kq``, descriptors ``dq``) matched to the reference points around
    ``pose``: (the PnP pose of the second pass, reference point rows, query keypoint indices of its
    inliers); (None, [], []) when either pass keeps fewer than ``s.min_inliers``."""
    none = (None, np.zeros(0, int), np.zeros(0, int))
    if len(kq) < 8:
        return none
    tree = cKDTree(kq)
    rows, kk = _match(pose, cam, ref, tree, dq, s.radius_px, s.ratio)
    p1, inl = _pnp(pose, cam, ref.xyz[rows], kq[kk], s.pnp_px)
    if p1 is None or inl.sum() < s.min_inliers:
        return none
    rows, kk = _match(p1, cam, ref, tree, dq, s.refine_radius_px, s.ratio)
    p2, inl = _pnp(p1, cam, ref.xyz[rows], kq[kk], s.pnp_px)
    if p2 is None or inl.sum() < s.min_inliers:
        return none
    return p2, rows[inl], kk[inl]


def _match_wide(pose: Pose, cam: Camera, ref: ReferencePoints, kq: np.ndarray, dq: np.ndarray, radius: float,
                ratio: float, k: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """(reference point rows, query keypoint indices) of the matches between the query keypoints and
    the reference points projecting within ``radius`` of them from ``pose``, with the ratio test among
    every such point (not only a keypoint's 8 nearest, as :func:`_match` does), so a pose off by a
    hundred pixels or more still finds its matches. Each keypoint's ``k`` nearest descriptors
    (FLANN): the best one within ``radius`` is compared with the next one within ``radius``, or,
    when none of the ``k`` is, with the ``k``-th (every point not among them is farther). One
    keypoint a reference point (the closest descriptor)."""
    uv, front = cam.project(pose.transform(ref.xyz))
    ok = np.flatnonzero(front & cam.in_image(uv, -radius))
    if len(ok) < k + 1 or len(kq) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    to_cam = pose.center - ref.xyz[ok]
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    cos = np.einsum("nkd,nd->nk", ref.dirs[ok], to_cam)
    cos[ref.img[ok] < 0] = -2.0
    dr = np.ascontiguousarray(ref.desc[ok, np.argmax(cos, axis=1)], np.float32)
    uvo = uv[ok]
    # FLANN's randomised kd-trees draw from OpenCV's RNG: seeded here, the same photo gives the same
    # matches in every run (unseeded, a register run on the same blocks drew other matches and the
    # tiny sample's sequences moved by up to 0.15 m median from run to run)
    cv2.setRNGSeed(0)
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    knn = flann.knnMatch(np.ascontiguousarray(dq, np.float32), dr, k=k)
    idx = np.full((len(kq), k), -1, np.int64)
    dist = np.full((len(kq), k), np.inf)
    for q, ms in enumerate(knn):
        for j, m in enumerate(ms):
            idx[q, j], dist[q, j] = m.trainIdx, m.distance
    valid = idx >= 0
    near = valid & (np.linalg.norm(uvo[np.where(valid, idx, 0)] - kq[:, None, :], axis=2) <= radius)
    has = near.any(axis=1)
    first = np.argmax(near, axis=1)
    rest = near.copy()
    rest[np.arange(len(kq)), first] = False
    second_j = np.argmax(rest, axis=1)
    best = dist[np.arange(len(kq)), first]
    second = np.where(rest.any(axis=1), dist[np.arange(len(kq)), second_j], dist[:, -1])
    keep = has & np.isfinite(best) & (best < ratio * second)
    rows, kk, d = idx[keep, first[keep]], np.flatnonzero(keep), best[keep]
    order = np.lexsort((d, rows))     # one query keypoint a reference point: the closest descriptor
    uniq = np.ones(len(order), bool)
    uniq[1:] = rows[order][1:] != rows[order][:-1]
    sel = order[uniq]
    return ok[rows[sel]], kk[sel]


def match_photo_wide(pose: Pose, cam: Camera, kq: np.ndarray, dq: np.ndarray, ref: ReferencePoints,
                     s: CrossMatchSettings, radius_px: float) -> tuple[Pose | None, np.ndarray, np.ndarray]:
    """:func:`match_photo` for a pose known only roughly (a query photo's GPS + gimbal metadata: metres
    and degrees off, a hundred pixels or more): matches within ``radius_px`` of the projections
    (:func:`_match_wide`), a PnP RANSAC without the pose as a guess, then :func:`match_photo`'s two
    passes around the pose it found. Same return as :func:`match_photo`."""
    none = (None, np.zeros(0, int), np.zeros(0, int))
    if len(kq) < 8:
        return none
    rows, kk = _match_wide(pose, cam, ref, kq, dq, radius_px, s.ratio)
    if len(rows) < max(6, s.min_inliers):
        return none
    und = cam.undistort_pixels(kq[kk])
    ok, rvec, tvec, inl = cv2.solvePnPRansac(ref.xyz[rows], und, cam.pinhole_part().K(), None, iterationsCount=2000,
                                             reprojectionError=2 * s.pnp_px, confidence=0.9999,
                                             flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < s.min_inliers:
        return none
    coarse = Pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return match_photo(coarse, cam, kq, dq, ref, s)


def photo_features(db_path: Path, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(keypoints x, y; descriptors as float32) of one photo of a COLMAP database, None if absent."""
    with pycolmap.Database.open(db_path) as db:
        if not db.exists_image(name):
            return None
        return _read_features(db, db.read_image_with_name(name).image_id)


def cross_matches(query_poses: dict[str, Pose], query_cams: dict[str, Camera], query_dbs: list[Path],
                  ref_rec: pycolmap.Reconstruction, ref_db: Path, s: CrossMatchSettings,
                  seed: int = 0, ref: ReferencePoints | None = None) -> dict[str, dict[str, tuple[float, float]]]:
    """{auto tie id: {image: (x, y)}}: the query photos that matched a reference point + up to
    ``s.track_obs`` of its reference observations (see the module docstring). ``ref``: the
    reference points if already read."""
    query_dbs = [d for d in query_dbs if Path(d).is_file()]
    if not s.enabled or not Path(ref_db).is_file() or not query_dbs or ref_rec.num_points3D() == 0:
        return {}
    rng = np.random.default_rng(seed)
    ref = ref or ReferencePoints(ref_rec, ref_db, s.descriptors_per_point)
    qf = {}
    for d in query_dbs:
        qf.update(_features(d))
    out: dict[str, dict[str, tuple[float, float]]] = {}
    n_photos = 0
    for qn, pose in query_poses.items():
        if qn not in qf:
            continue
        kq, dq = qf[qn]
        p2, rows, kk = match_photo(pose, query_cams[qn], kq, dq, ref, s)
        if p2 is None:
            continue
        if len(rows) > s.max_per_photo:
            pick = rng.choice(len(rows), s.max_per_photo, replace=False)
            rows, kk = rows[pick], kk[pick]
        n_photos += 1
        for r, k in zip(rows, kk):
            tid = auto_tie_id(ref.ids[r])
            if tid not in out:
                obs = [(ref.names[ref.img[r, j]], tuple(ref.xy[r, j])) for j in range(ref.img.shape[1])
                       if ref.img[r, j] >= 0][:s.track_obs]
                out[tid] = dict(obs)
            out[tid].setdefault(qn, tuple(kq[k]))
    log.info("automatic tie points: %d reference points matched in %d query photos", len(out), n_photos)
    return out
