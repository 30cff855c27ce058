"""Snap a mark to a checkered GCP target's centre (the X-corner where its dark and light quadrants
meet), as survey software's marker detection does: the annotator's "accept a snapped mark" key.

Corners within ``radius`` px of the given position (the prediction) are refined to sub-pixel
(OpenCV ``cornerSubPix``) and kept only where rings around them show the X-corner's signature (two
dark and two light arcs, opposite arcs alike, the same diagonals dark at two radii); the one with
the most contrast is the target's centre. Pixels in
gtkit's convention (:mod:`gtkit.conventions`).
"""
from __future__ import annotations

import numpy as np

from ..conventions import index_to_pixel, pixel_to_index

MIN_CONTRAST = 30.0   # grey levels between the light and the dark arcs


def _ring(gray: np.ndarray, c: np.ndarray, r: float, n: int = 32) -> np.ndarray:
    import cv2

    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pts = (c[None] + r * np.c_[np.cos(a), np.sin(a)]).astype(np.float32)
    return cv2.remap(gray.astype(np.float32), pts[:, 0].reshape(1, -1), pts[:, 1].reshape(1, -1),
                     cv2.INTER_LINEAR).ravel()


def _harmonics(gray: np.ndarray, c_idx: np.ndarray, r: float) -> tuple[complex, complex]:
    v = _ring(gray, c_idx, r)
    n = len(v)
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    d = v - v.mean()
    return 2.0 * np.sum(d * np.exp(-1j * a)) / n, 2.0 * np.sum(d * np.exp(-2j * a)) / n


def x_corner_score(gray: np.ndarray, c_idx: np.ndarray, radii=(1.5, 2.5)) -> float:
    """Contrast of an X-corner at array position ``c_idx``: on rings of each radius the intensity
    is a cos(2a) pattern (dark / light / dark / light, opposite quarters alike: the 2nd harmonic
    strong, the 1st weak) of one phase (the same two diagonals dark); 0 where it is not."""
    h = [_harmonics(gray, c_idx, r) for r in radii]
    amp = [abs(h2) for _, h2 in h]
    if min(amp) < 0.5 * MIN_CONTRAST or any(abs(h1) > 0.5 * abs(h2) for h1, h2 in h):
        return 0.0
    dphase = abs(np.angle(h[0][1] / h[-1][1]))     # twice the rotation between the rings' patterns
    if dphase > np.radians(40):
        return 0.0
    return float(min(amp))


def snap_target(gray: np.ndarray, xy, radius: float = 12.0) -> tuple[np.ndarray | None, str]:
    """(pixel of the target's centre, "") or (None, why not). ``gray``: the photo (full resolution)."""
    import cv2

    h, w = gray.shape[:2]
    c = pixel_to_index(np.asarray(xy, float))
    r = float(max(4.0, radius))
    x0, y0 = int(max(0, np.floor(c[0] - r - 6))), int(max(0, np.floor(c[1] - r - 6)))
    x1, y1 = int(min(w, np.ceil(c[0] + r + 7))), int(min(h, np.ceil(c[1] + r + 7)))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None, "too close to the photo's edge"
    crop = gray[y0:y1, x0:x1].astype(np.float32)
    cands = cv2.goodFeaturesToTrack(crop, maxCorners=20, qualityLevel=0.05, minDistance=2, blockSize=3)
    if cands is None:
        return None, "no corner near the mark"
    best = None
    for p in cands.reshape(-1, 2):
        q = p + [x0, y0]
        if np.linalg.norm(q - c) > r:
            continue
        ref = cv2.cornerSubPix(gray.astype(np.float32), q.reshape(1, 1, 2).astype(np.float32), (2, 2), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.01)).reshape(2)
        if np.linalg.norm(ref - q) > 2.0:
            continue
        s = x_corner_score(gray, ref)
        if s > 0 and (best is None or s > best[0]):
            best = (s, ref)
    if best is None:
        return None, f"no checkered target centre within {r:.0f} px"
    return index_to_pixel(best[1]), ""
