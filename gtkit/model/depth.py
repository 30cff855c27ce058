"""Per-photo depth maps: semi-global matching on rectified pairs, then multi-view agreement.

For a photo and each of its neighbours the pair is rectified here (both cameras turned to look
along their mean direction with the x axis along the baseline; the canvas holds both turned
pictures whole, so a baseline along the image's y axis is no problem), OpenCV's SGBM (C++,
census-like costs aggregated along 3 paths, 1/16 px disparities, left-right check) finds the
disparities in the range the sparse SfM points allow, and each disparity becomes a distance
along the photo's own pixel ray. A pixel keeps a depth where at least ``min_pair_agree`` pairs
agree within ``pair_agree`` (relative); its depth is their mean. Then the texture test
(:func:`texture_test`) gives up the depth of pixels whose surroundings have too little contrast to
match (plain grass, water, blank roofs): SGBM lays a smooth but false surface there that the pairs and
photos agree on; the DSM's gap fill interpolates such areas and marks them instead.

Depth maps are written one file a photo (``work/model/depth/<name>.npz``, atomically), so a killed
run keeps the finished ones.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..io.atomic import write_bytes
from .settings import ModelSettings
from .views import View


def rectify_pair(a: View, b: View, max_pixels: float = 6.0):
    """Homographies and canvas that rectify a -> b (x along the baseline a->b).
    Returns (H_a, H_b, (w, h), K_rect, baseline) or None when the canvas would be too large."""
    ca, cb = a.center, b.center
    base = cb - ca
    bl = float(np.linalg.norm(base))
    x = base / bl
    z = a.axis + b.axis
    z = z - (z @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    Rr = np.stack([x, y, z])                       # world -> rectified camera
    f = 0.5 * (a.K[0, 0] + b.K[1, 1])
    K0 = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]])
    Ha = K0 @ Rr @ a.pose.R.T @ np.linalg.inv(a.K)
    Hb = K0 @ Rr @ b.pose.R.T @ np.linalg.inv(b.K)
    pts = []
    for H, v in ((Ha, a), (Hb, b)):
        c = np.array([[0, 0, 1], [v.width - 1, 0, 1], [0, v.height - 1, 1], [v.width - 1, v.height - 1, 1.0]]).T
        q = H @ c
        if np.any(q[2] <= 0):
            return None
        pts.append((q[:2] / q[2]).T)
    pa, pb = pts
    # x range from picture a (the disparity search reaches into b), y from both
    x0, x1 = pa[:, 0].min(), pa[:, 0].max()
    y0, y1 = min(pa[:, 1].min(), pb[:, 1].min()), max(pa[:, 1].max(), pb[:, 1].max())
    w, h = int(np.ceil(x1 - x0)) + 1, int(np.ceil(y1 - y0)) + 1
    if w * h > max_pixels * a.width * a.height:
        return None
    T = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]])
    return T @ Ha, T @ Hb, (w, h), T @ K0, bl


def sgbm_disparities(ra: np.ndarray, rb: np.ndarray, rb_half: np.ndarray, n: int, settings: ModelSettings):
    """Disparities (px, x_a - x_b) of rectified uint8 pictures over [0, n): (their mean, as is, upside
    down); ``rb_half`` is picture b drawn 0.5 px further right. The mean is corrected for SGBM's
    rounding bias (``settings.sgbm_disparity_bias_px``)."""
    import cv2

    bs = settings.block_size
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=n, blockSize=bs, P1=8 * bs * bs, P2=32 * bs * bs,
                                 disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.StereoSGBM_MODE_SGBM_3WAY)
    # SGBM's 3-way aggregation runs from the top only: on a surface slanted along the rows (the ground
    # in an oblique photo) that biases the disparity by ~0.2 px, with the sign of the slant. The same
    # pair upside down has the opposite bias, so the mean of both is unbiased (and both must agree).
    # The upside-down pass matches b drawn half a pixel further: SGBM's sub-pixel estimate sticks to
    # whole pixels (a texture shifted by fractions of a pixel: errors from -0.26 to +0.30 px), and
    # half a pixel apart the two passes stick in opposite directions (swing over the fractions
    # 0.56 -> 0.19 px on a sample photo), at no extra cost.
    d1 = sgbm.compute(ra, rb).astype(np.float32) / 16.0
    d2 = sgbm.compute(np.ascontiguousarray(ra[::-1]), np.ascontiguousarray(rb_half[::-1]))[::-1].astype(np.float32) / 16.0
    d2 = np.where(d2 > 0, d2 + 0.5, d2)
    return 0.5 * (d1 + d2) - settings.sgbm_disparity_bias_px, d1, d2


def pair_depth(a: View, b: View, img_a: np.ndarray, img_b: np.ndarray, settings: ModelSettings) -> np.ndarray | None:
    """Depth (camera z, metres; NaN where unknown) of photo a's pixels from the pair a-b."""
    import cv2

    r = rectify_pair(a, b)
    if r is None:
        return None
    Ha, Hb, (w, h), K, bl = r
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    ra = cv2.warpPerspective(img_a, Ha, (w, h), flags=cv2.INTER_LINEAR)
    mask_a = cv2.warpPerspective(np.full(img_a.shape, 255, np.uint8), Ha, (w, h), flags=cv2.INTER_NEAREST)
    # picture b in the same canvas but shifted: x_b = x_a - d, and d's range is [dmin, dmin + n)
    fb = f * bl
    dmin = int(np.floor(fb / (a.far * 1.25)))
    dmax = int(np.ceil(fb / (a.near * 0.8)))
    n = int(np.ceil((dmax - dmin) / 16.0)) * 16
    if n > settings.max_disparities:
        n = settings.max_disparities
    # shift b right by dmin so SGBM searches [0, n); the canvas grows by dmin on the left, none needed
    S = np.array([[1, 0, dmin], [0, 1, 0], [0, 0, 1.0]])
    rb = cv2.warpPerspective(img_b, S @ Hb, (w, h), flags=cv2.INTER_LINEAR)
    mask_b = cv2.warpPerspective(np.full(img_b.shape, 255, np.uint8), S @ Hb, (w, h), flags=cv2.INTER_NEAREST)
    S[0, 2] += 0.5
    rb_half = cv2.warpPerspective(img_b, S @ Hb, (w, h), flags=cv2.INTER_LINEAR)
    disp, d1, d2 = sgbm_disparities(ra, rb, rb_half, n, settings)
    valid = (d1 > 0.5) & (d2 > 0.5) & (np.abs(d1 - d2) <= 1.0) & (mask_a > 0)
    # the matched pixel of b must lie inside b's picture
    jj = np.arange(w, dtype=np.float32)[None, :] - disp
    xi = np.clip(np.round(jj).astype(np.int32), 0, w - 1)
    valid &= (jj >= 0) & (np.take_along_axis(mask_b, xi, axis=1) > 0)
    d = disp + dmin
    with np.errstate(divide="ignore", invalid="ignore"):
        Z = np.where(valid & (d > 0), fb / d, np.nan).astype(np.float32)
    # distance along the ray (the same in every frame), then back to photo a's pixels
    u = (np.arange(w, dtype=np.float32) - cx) / f
    v = (np.arange(h, dtype=np.float32) - cy) / f
    lam = Z * np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
    lam_a = cv2.warpPerspective(lam, Ha, (a.width, a.height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    ua = (np.arange(a.width, dtype=np.float32) - a.K[0, 2]) / a.K[0, 0]
    va = (np.arange(a.height, dtype=np.float32) - a.K[1, 2]) / a.K[1, 1]
    return lam_a / np.sqrt(ua[None, :] ** 2 + va[:, None] ** 2 + 1.0)


TEXTURE_SMOOTH_PX = 1.5      # Gaussian sigma of the texture test's smoothing (leaves ~0.19 of white noise)


def local_contrast(gray: np.ndarray, window: int) -> np.ndarray:
    """Per pixel: the standard deviation (DN) of the picture smoothed by :data:`TEXTURE_SMOOTH_PX` over a
    ``window`` x ``window`` box around it (the texture SGBM has to match there, sensor noise mostly
    smoothed away)."""
    import cv2

    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), TEXTURE_SMOOTH_PX)
    m = cv2.blur(g, (window, window), borderType=cv2.BORDER_REFLECT)
    m2 = cv2.blur(g * g, (window, window), borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(m2 - m * m, 0.0))


def texture_test(depth: np.ndarray, gray: np.ndarray, settings: ModelSettings) -> tuple[np.ndarray, int, int]:
    """The depth map with the pixels of too little texture and a margin around them given up (NaN; see
    ``ModelSettings.texture_min_contrast``, ``texture_margin_px``), how many pixels had a depth and how many
    were given up."""
    had = np.isfinite(depth)
    n_had = int(had.sum())
    if settings.texture_min_contrast <= 0:
        return depth, n_had, 0
    plain = local_contrast(gray, settings.texture_window) < settings.texture_min_contrast
    r = int(settings.texture_margin_px)
    if r > 0 and plain.any():        # and the margin around it (see ModelSettings.texture_margin_px)
        import cv2

        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        plain = cv2.dilate(plain.astype(np.uint8), disc) > 0
    gone = had & plain
    return np.where(gone, np.nan, depth).astype(np.float32), n_had, int(gone.sum())


def combine_pairs(depths: list[np.ndarray], settings: ModelSettings) -> np.ndarray:
    """Per pixel: the mean of the pair depths that agree with their median (NaN where fewer than
    ``min_pair_agree`` agree)."""
    import warnings

    D = np.stack(depths)
    with warnings.catch_warnings(), np.errstate(invalid="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)       # all-NaN pixels
        med = np.nanmedian(D, axis=0)
        agree = np.abs(D - med) <= settings.pair_agree * med
    cnt = agree.sum(0)
    mean = np.where(agree, D, 0).sum(0) / np.maximum(cnt, 1)
    return np.where(cnt >= settings.min_pair_agree, mean, np.nan).astype(np.float32)


def depth_file(folder: Path, name: str) -> Path:
    return folder / (name.replace("/", "__").rsplit(".", 1)[0] + ".npz")


def write_depth(path: Path, depth: np.ndarray, info: dict) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, depth=depth.astype(np.float32), **{k: np.asarray(v) for k, v in info.items()})
    write_bytes(path, buf.getvalue())


def read_depth(path: Path) -> np.ndarray:
    with np.load(path) as z:
        return z["depth"]


def read_depth_counts(path: Path) -> tuple[int, int]:
    """(pixels with a depth before the texture test, pixels it gave up) of a written depth map ((0, 0) for a
    map written without the counts)."""
    with np.load(path) as z:
        if "had_depth" not in z.files:
            return 0, 0
        return int(z["had_depth"]), int(z["textureless"])
