"""Automatic tie points between the blocks: SIFT matches between each registered query photo and
the reference photos that look at the same ground from a similar direction, verified by a
fundamental-matrix RANSAC on undistorted pixels. They join the annotators' clicks as extra,
unlisted tie points in the joint BA, where the same re-triangulation test (with the refined
poses) drops any that disagree with the geometry."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ..camera import Camera
from ..pose import Pose

log = logging.getLogger(__name__)
AUTO_PREFIX = "auto:"   # ids of automatic tie points: auto:<query image>:<reference image>:<match>


@dataclass
class CrossMatchSettings:
    ref_per_query: int = 4        # reference photos matched with each query photo (0: off)
    max_view_angle_deg: float = 40.0  # only reference photos looking within this angle of the query's direction
    ratio: float = 0.8            # Lowe ratio test
    ransac_px: float = 2.0        # fundamental-matrix RANSAC threshold on undistorted pixels
    min_inliers: int = 20
    max_per_pair: int = 150       # keep at most this many matches a pair (spread, random)


def _features(db_path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    with pycolmap.Database.open(db_path) as db:
        for im in db.read_all_images():
            kp = np.asarray(db.read_keypoints(im.image_id))[:, :2]
            de = db.read_descriptors(im.image_id)
            de = np.asarray(de.data if hasattr(de, "data") else de)
            out[im.name] = (kp.astype(np.float64), de.astype(np.float32))
    return out


def cross_matches(query_poses: dict[str, Pose], query_cams: dict[str, Camera], query_centroid: dict[str, np.ndarray],
                  ref_poses: dict[str, Pose], ref_cams: dict[str, Camera], query_dbs: list[Path], ref_db: Path,
                  s: CrossMatchSettings, seed: int = 0) -> dict[str, dict[str, tuple[float, float]]]:
    """{auto tie id: {image: (x, y)}} with one query and one reference observation each."""
    query_dbs = [d for d in query_dbs if Path(d).is_file()]
    if s.ref_per_query <= 0 or not Path(ref_db).is_file() or not query_dbs:
        return {}
    rng = np.random.default_rng(seed)
    qf = {}
    for d in query_dbs:
        qf.update(_features(d))
    rf = _features(ref_db)
    ref_names = [n for n in ref_poses if n in rf]
    rdirs = np.array([ref_poses[n].R[2] for n in ref_names])       # optical axes in world
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out, n_pairs = {}, 0
    for qn, qp in query_poses.items():
        if qn not in qf or qn not in query_centroid:
            continue
        X = query_centroid[qn]
        cos = rdirs @ qp.R[2]
        cand = []
        for k, rn in enumerate(ref_names):
            if cos[k] < np.cos(np.radians(s.max_view_angle_deg)):
                continue
            uv, front = ref_cams[rn].project(ref_poses[rn].transform(X[None]))
            if front[0] and ref_cams[rn].in_image(uv, 0.15 * ref_cams[rn].width)[0]:
                cand.append((cos[k], rn))
        for _, rn in sorted(cand, reverse=True)[:s.ref_per_query]:
            kq, dq = qf[qn]
            kr, dr = rf[rn]
            if len(kq) < 8 or len(kr) < 8:
                continue
            m = matcher.knnMatch(dq, dr, k=2)
            good = [a for a, b in (p for p in m if len(p) == 2) if a.distance < s.ratio * b.distance]
            if len(good) < s.min_inliers:
                continue
            iq = np.array([g.queryIdx for g in good])
            ir = np.array([g.trainIdx for g in good])
            pq = query_cams[qn].undistort_pixels(kq[iq])
            pr = ref_cams[rn].undistort_pixels(kr[ir])
            F, mask = cv2.findFundamentalMat(pq, pr, cv2.FM_RANSAC, s.ransac_px, 0.999, 2000)
            if F is None or mask is None or mask.sum() < s.min_inliers:
                continue
            inl = np.flatnonzero(mask.ravel())
            if len(inl) > s.max_per_pair:
                inl = rng.choice(inl, s.max_per_pair, replace=False)
            n_pairs += 1
            for i in inl:
                out[f"{AUTO_PREFIX}{qn}:{rn}:{i}"] = {qn: tuple(kq[iq[i]]), rn: tuple(kr[ir[i]])}
    log.info("cross-block matches: %d from %d query-reference pairs", len(out), n_pairs)
    return out
