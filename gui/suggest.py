"""Suggested correspondences between two photos: OpenCV SIFT, Lowe's ratio test, a RANSAC
fundamental matrix, then a spread-out subset. The annotator accepts or rejects each. No Qt here."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gtkit.conventions import index_to_pixel
from gtkit.render.overlay import read_photo, working_scale


@dataclass
class SuggestSettings:
    max_side: int = 1600       # photos are matched at most this size (long side)
    n_features: int = 4000     # SIFT keypoints per photo
    ratio: float = 0.8         # Lowe's ratio test
    ransac_px: float = 2.0     # fundamental-matrix RANSAC threshold, working pixels
    max_suggestions: int = 40  # at most this many, spread over a grid on the query photo
    grid: tuple[int, int] = (8, 6)
    gate: float = 0.15         # with a pose predictor: matches farther than this share of the
                               # reference's long side from the predicted position are dropped
    min_inliers: int = 12      # fewer RANSAC inliers than this: no suggestions (unreliable)


@dataclass
class Suggestion:
    xq: float
    yq: float
    xr: float
    yr: float
    score: float  # ratio-test distance ratio (lower = more distinctive)


def _load(path: Path, max_side: int):
    from PIL import Image

    with Image.open(path) as im:
        w, h = im.size
    s = working_scale(w, h, max_side)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    import cv2

    g = cv2.cvtColor(read_photo(path, size), cv2.COLOR_RGB2GRAY)
    return g, size[0] / w, size[1] / h


def suggest(query_path: str | Path, ref_path: str | Path, settings: SuggestSettings | None = None,
            predict=None) -> list[Suggestion]:
    """Suggested tie points between two photos, in full-resolution pixels (gtkit convention).

    ``predict`` (optional, see :meth:`gui.ranking.OverlapRanker.predictor`) maps query pixels to
    their expected reference pixels from the photos' poses; matches far from it are dropped
    before RANSAC, which removes the repetitive-texture mismatches wide-baseline oblique pairs
    are full of."""
    import cv2

    st = settings or SuggestSettings()
    gq, sqx, sqy = _load(Path(query_path), st.max_side)
    gr, srx, sry = _load(Path(ref_path), st.max_side)
    sift = cv2.SIFT_create(nfeatures=st.n_features)
    kq, dq = sift.detectAndCompute(gq, None)
    kr, dr = sift.detectAndCompute(gr, None)
    if dq is None or dr is None or len(kq) < 8 or len(kr) < 8:
        return []
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dq, dr, k=2)
    good = [(m.queryIdx, m.trainIdx, m.distance / max(n.distance, 1e-6))
            for m, n in (p for p in knn if len(p) == 2) if m.distance < st.ratio * n.distance]
    if len(good) < 8:
        return []
    pq = np.array([kq[i].pt for i, _, _ in good], np.float64)
    pr = np.array([kr[j].pt for _, j, _ in good], np.float64)
    ratio = np.array([r for _, _, r in good])
    if predict is not None:
        exp = np.asarray(predict(index_to_pixel(pq) / [sqx, sqy]), float)  # full-resolution reference pixels
        got = index_to_pixel(pr) / [srx, sry]
        limit = st.gate * max(gr.shape) / max(srx, sry)
        near = np.linalg.norm(exp - got, axis=1) < limit  # NaN (no prediction) compares False
        pq, pr, ratio = pq[near], pr[near], ratio[near]
    if len(pq) < 8:
        return []
    _, inl = cv2.findFundamentalMat(pq, pr, cv2.FM_RANSAC, st.ransac_px, 0.999)
    if inl is None or int(inl.sum()) < st.min_inliers:
        return []
    keep = inl.ravel().astype(bool)
    pq, pr, ratio = pq[keep], pr[keep], ratio[keep]
    # spread: the most distinctive match per grid cell first, then the rest by distinctiveness
    gx, gy = st.grid
    cell = (np.minimum(pq[:, 0] / gq.shape[1] * gx, gx - 1).astype(int)
            + gx * np.minimum(pq[:, 1] / gq.shape[0] * gy, gy - 1).astype(int))
    order = np.argsort(ratio)
    first, rest, seen = [], [], set()
    for i in order:
        (rest if cell[i] in seen else first).append(i)
        seen.add(cell[i])
    pick = (first + rest)[: st.max_suggestions]
    uq = index_to_pixel(pq[pick]) / [sqx, sqy]
    ur = index_to_pixel(pr[pick]) / [srx, sry]
    return [Suggestion(float(a[0]), float(a[1]), float(b[0]), float(b[1]), float(ratio[i]))
            for a, b, i in zip(uq, ur, pick)]
