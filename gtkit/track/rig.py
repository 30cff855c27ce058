"""The wide + zoom camera rig: the zoom camera's intrinsics and its fixed pose relative to the
wide camera, estimated from photo pairs taken at the same instant.

Model (poses world-to-camera, OpenCV axes, see :mod:`gtkit.conventions`)::

    x_zoom = R_zw @ (x_wide - offset)      (offset = zoom centre in the wide camera frame)
    R_zoom = R_zw @ R_wide,   t_zoom = R_zw @ (t_wide - offset)

Calibration. The two lenses are a few centimetres apart and the scene is 50-200 m away, so a
zoom pixel and the wide pixel of the same scene point are related by the infinite homography
``H = K_w R_zw^T K_z^-1`` (parallax offset/depth is below 0.1 deg and below the wide
camera's pixel). Each pair is matched with SIFT (the zoom image is first shrunk to the wide
image's scale, found from the nominal focal lengths or by a small scale search), a RANSAC
homography keeps the inliers, and ``R_zw`` and the zoom focal length(s) are refined by robust
nonlinear least squares over all pairs, with reprojection error in wide-image pixels (the wide
camera's calibration, distortion included, is taken as known). The zoom principal point is kept
at its nominal value (image centre): with a narrow field of view it is not separable from
the rotation. The offset is NOT observable this way (its effect is offset/depth); it is taken
from the spec (settings) and written down with the result.

Focal settings: pairs are grouped by the zoom photo's EXIF focal length (mm) and image size;
each group gets its own focal length in pixels, the rotation is shared. A photo at a setting
that was not calibrated is given the nearest calibrated camera scaled by the ratio of the EXIF
focal lengths.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..camera import MODELS, Camera
from ..conventions import index_to_pixel, rotation_angle_deg, rotmat_to_quat
from ..errors import GtkitError
from ..io.atomic import write_json
from ..pose import Pose

log = logging.getLogger(__name__)


# --- the rig ------------------------------------------------------------------------------

@dataclass
class ZoomSetting:
    camera: Camera
    focal_mm: float | None = None      # EXIF focal length of the photos this setting is for

    @property
    def key(self) -> str:
        return f"{self.camera.width}x{self.camera.height}@" + ("?" if self.focal_mm is None else f"{self.focal_mm:g}mm")


@dataclass
class Rig:
    R_zw: np.ndarray                                  # zoom-from-wide rotation
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # zoom centre in wide frame (m)
    settings: list[ZoomSetting] = field(default_factory=list)
    wide: Camera | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self.R_zw = np.asarray(self.R_zw, dtype=np.float64)
        self.offset = np.asarray(self.offset, dtype=np.float64).reshape(3)
        if self.R_zw.shape != (3, 3) or abs(np.linalg.det(self.R_zw) - 1) > 1e-6:
            raise GtkitError("rig rotation must be a 3x3 rotation matrix")

    def zoom_pose(self, wide: Pose) -> Pose:
        R = self.R_zw @ wide.R
        return Pose(R, self.R_zw @ (wide.t - self.offset))

    def zoom_camera(self, width: int | None = None, height: int | None = None,
                    focal_mm: float | None = None) -> Camera:
        """The calibrated zoom camera for a photo of this size and EXIF focal length."""
        if not self.settings:
            raise GtkitError("the rig has no zoom calibration")
        cands = [s for s in self.settings
                 if width is None or (s.camera.width, s.camera.height) == (width, height)]
        if not cands:  # same sensor at another resolution: scale the first setting
            s = self.settings[0]
            return s.camera.scaled(width / s.camera.width)
        if focal_mm is None:
            return cands[0].camera
        known = [s for s in cands if s.focal_mm is not None]
        if not known:
            return cands[0].camera
        best = min(known, key=lambda s: abs(s.focal_mm - focal_mm))
        if abs(best.focal_mm - focal_mm) < 1e-3:
            return best.camera
        return with_focal(best.camera, best.camera.fx * focal_mm / best.focal_mm)

    # --- file --------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "model": "x_zoom = R_zoom_from_wide @ (x_wide - offset_m); poses world-to-camera, OpenCV axes",
            "R_zoom_from_wide": self.R_zw.tolist(),
            "q_zoom_from_wide": rotmat_to_quat(self.R_zw).tolist(),
            "offset_m": self.offset.tolist(),
            "offset_note": "zoom centre in the wide camera frame; from the spec, not estimated "
                           "(unobservable from image pairs at 50-200 m range)",
            "zoom": [{"focal_mm": s.focal_mm, "camera": s.camera.to_line()} for s in self.settings],
            "wide": self.wide.to_line() if self.wide else None,
            "calibration": self.info,
        }

    def save(self, path: str | Path) -> Path:
        return write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "Rig":
        path = Path(path)
        if not path.is_file():
            raise GtkitError("rig calibration not found (run `gtkit track calibrate DIR` first)", path)
        try:
            d = json.loads(path.read_text())
            settings = []
            for z in d["zoom"]:
                f = z["camera"].split()
                settings.append(ZoomSetting(Camera(f[0], int(f[1]), int(f[2]), tuple(float(v) for v in f[3:])),
                                            z.get("focal_mm")))
            wide = None
            if d.get("wide"):
                f = d["wide"].split()
                wide = Camera(f[0], int(f[1]), int(f[2]), tuple(float(v) for v in f[3:]))
            return cls(np.array(d["R_zoom_from_wide"]), np.array(d.get("offset_m", [0, 0, 0])), settings, wide,
                       d.get("calibration", {}))
        except (json.JSONDecodeError, KeyError, ValueError, TypeError, IndexError, GtkitError) as e:
            raise GtkitError(f"invalid rig file ({e})", path) from None


def with_focal(c: Camera, fx: float) -> Camera:
    """The same camera (model, principal point, distortion, aspect) with focal length ``fx``."""
    k = fx / c.fx
    params = [v * k if name in ("f", "fx", "fy") else v for name, v in zip(MODELS[c.model], c.params)]
    return Camera(c.model, c.width, c.height, tuple(params))


# --- matching -----------------------------------------------------------------------------

@dataclass
class RigCalibrationSettings:
    sift_features: int = 4000          # SIFT keypoints per image
    ratio: float = 0.8                 # Lowe's ratio test
    ransac_px: float = 3.0             # homography RANSAC threshold (wide pixels)
    min_inliers: int = 20              # a pair with fewer homography inliers is dropped
    scale_search: tuple[float, ...] = (1.0, 0.7, 1.4, 0.5, 2.0)  # x nominal zoom->wide scale, tried in order
    max_pairs: int = 40                # pairs used (evenly spread over all pairs found)
    # Working resolution: the wide photo is matched at most this long side (the zoom photo shrunk to
    # the same scale, so 5184 -> 373 px; results in full-resolution pixels); 0 = full resolution.
    # Full-size sample seed 0 (4056 px wide, 5184 px zoom, 28 pairs, loaded 2-core machine, issue 48):
    # full 4056 px: 1,784 points, rotation 0.0184 deg / focal -0.013 % from the truth, 109 CPU s;
    # 2048: 3,096 points, 0.0183 deg / -0.013 %, 38 CPU s; 1024: 2,779 points, 0.0185 deg / -0.024 %,
    # 18 CPU s. 2048 keeps full resolution's accuracy at a third of its CPU (4,000 SIFT keypoints over
    # 12 MP leave fewer where the zoom looks). Photos at most this size (every sample but fullsize) are
    # matched as before.
    wide_max_side: int = 2048
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # zoom centre in the wide frame (spec)


def _gray(img):
    import cv2

    img = np.asarray(img)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def _sift(gray, n):
    import cv2

    sift = cv2.SIFT_create(nfeatures=n)
    kp, des = sift.detectAndCompute(gray, None)
    pts = index_to_pixel(np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2))
    return pts, des


def wide_features(wide_img, s: RigCalibrationSettings):
    """SIFT of a wide photo at its working resolution (long side <= ``s.wide_max_side``), keypoints in
    full-resolution pixels (COLMAP convention: a resize by k maps u to u * k). Returns (pts, desc, k)."""
    import cv2

    g = _gray(wide_img)
    h, w = g.shape
    k = min(1.0, s.wide_max_side / max(w, h)) if s.wide_max_side else 1.0
    if k < 1.0:
        g = cv2.resize(g, (max(16, int(round(w * k))), max(16, int(round(h * k)))), interpolation=cv2.INTER_AREA)
    pts, des = _sift(g, s.sift_features)
    return pts * np.array([w / g.shape[1], h / g.shape[0]]), des, g.shape[1] / w


def match_pair(wide_img, zoom_img, scale: float, s: RigCalibrationSettings, wide_feats=None):
    """Match a zoom photo into the wide photo of the same instant.

    ``scale`` ~ f_wide / f_zoom (how much the zoom image is shrunk before matching).
    Returns (zoom_px (N,2) full-resolution pixels, wide_px (N,2), H zoom->wide) of the
    homography inliers, or None."""
    import cv2

    wg = _gray(wide_img)
    zg = _gray(zoom_img)
    pw, dw = wide_feats if wide_feats is not None else _sift(wg, s.sift_features)
    if dw is None or len(pw) < s.min_inliers:
        return None
    zh, zw = zg.shape
    w2, h2 = max(16, int(round(zw * scale))), max(16, int(round(zh * scale)))
    small = cv2.resize(zg, (w2, h2), interpolation=cv2.INTER_AREA)
    pz, dz = _sift(small, s.sift_features)
    if dz is None or len(pz) < s.min_inliers:
        return None
    pz = pz * np.array([zw / w2, zh / h2])  # back to full-resolution zoom pixels (COLMAP convention)
    m = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dz, dw, k=2)
    good = [a for a, *b in m if b and a.distance < s.ratio * b[0].distance]
    if len(good) < s.min_inliers:
        return None
    iz = np.array([g.queryIdx for g in good])
    iw = np.array([g.trainIdx for g in good])
    src, dst = pz[iz], pw[iw]
    H, mask = cv2.findHomography(src, dst, cv2.RANSAC, s.ransac_px, maxIters=5000, confidence=0.999)
    if H is None or mask is None or int(mask.sum()) < s.min_inliers:
        return None
    inl = mask.ravel().astype(bool)
    return src[inl], dst[inl], H


def _rotation_from_h(H, Kw, Kz):
    """H (zoom->wide pixels) ~ K_w R_zw^T K_z^-1 -> R_zw (nearest rotation)."""
    M = np.linalg.inv(Kw) @ H @ Kz
    M = M / np.cbrt(np.linalg.det(M))
    U, _, Vt = np.linalg.svd(M)
    Rt = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    return Rt.T


# --- calibration --------------------------------------------------------------------------

@dataclass
class PairObs:
    name: str
    zoom_px: np.ndarray
    wide_px: np.ndarray
    group: int


def _names(names: list[str], most: int = 3) -> str:
    """``a, b, c and 4 more``: a list of photos on one line."""
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def fit_rig(obs: list[PairObs], wide: Camera, zoom_init: list[ZoomSetting], R_init: np.ndarray,
            offset=(0.0, 0.0, 0.0)) -> Rig:
    """Robust least squares for R_zw and one zoom focal length per setting (principal point
    and distortion kept at their nominal values)."""
    if not obs:
        raise GtkitError("no matched wide/zoom pair to calibrate the rig from")
    ng = len(zoom_init)
    f0 = np.array([z.camera.fx for z in zoom_init])
    zpx = np.concatenate([o.zoom_px for o in obs])
    wpx = np.concatenate([o.wide_px for o in obs])
    grp = np.concatenate([np.full(len(o.zoom_px), o.group) for o in obs])
    base = [z.camera for z in zoom_init]
    # normalised zoom coordinates at unit focal (distortion removed with the nominal model)
    xz = np.empty_like(zpx)
    for g in range(ng):
        m = grp == g
        xz[m] = base[g].image_to_world(zpx[m]) * base[g].fx  # = (u - cx) * fx/fx, undistorted, in px
    aspect = np.array([base[g].fy / base[g].fx for g in range(ng)])

    def residual(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix()
        f = f0 * np.exp(p[3:3 + ng])
        fg = f[grp]
        rz = np.column_stack([xz[:, 0] / fg, xz[:, 1] / (fg * aspect[grp]), np.ones(len(xz))])
        rw = rz @ R  # R_zw^T @ r_z, row-wise
        uv, front = wide.project(rw)
        r = uv - wpx
        r[~front] = 1e3
        return r.ravel()

    p0 = np.concatenate([Rotation.from_matrix(R_init).as_rotvec(), np.zeros(ng)])
    sol = least_squares(residual, p0, loss="soft_l1", f_scale=1.0, x_scale="jac")
    res = sol.fun.reshape(-1, 2)
    err = np.linalg.norm(res, axis=1)
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    f = f0 * np.exp(sol.x[3:3 + ng])
    settings = [ZoomSetting(with_focal(z.camera, f[g]), z.focal_mm) for g, z in enumerate(zoom_init)]
    # uncertainty of the estimate from the Gauss-Newton normal matrix at the inliers
    inl = err < 3.0
    sigma = {}
    try:
        J = sol.jac
        sig2 = float(np.sum(res[inl] ** 2) / max(2 * inl.sum() - len(sol.x), 1))
        cov = np.linalg.inv(J.T @ J) * sig2
        sd = np.sqrt(np.diag(cov))
        sigma = {"rotation_deg": float(np.degrees(np.linalg.norm(sd[:3]))),
                 "focal_pct": [float(100 * s) for s in sd[3:]]}
    except np.linalg.LinAlgError:
        pass
    per_pair = {}
    k = 0
    for o in obs:
        n = len(o.zoom_px)
        per_pair[o.name] = {"n": n, "median_px": float(np.median(err[k:k + n]))}
        k += n
    info = {"n_pairs": len(obs), "n_points": int(len(err)), "inlier_share_3px": float(inl.mean()),
            "median_px": float(np.median(err)), "rms_inlier_px": float(np.sqrt(np.mean(err[inl] ** 2))),
            "sigma": sigma, "rotation_from_init_deg": rotation_angle_deg(R, R_init), "per_pair": per_pair}
    return Rig(R, np.asarray(offset, float), settings, wide, info)


def calibrate_pairs(pairs, wide_cams, zoom_init: list[ZoomSetting], zoom_group, settings: RigCalibrationSettings,
                    load_image) -> Rig:
    """Calibrate from ``pairs`` = [(wide_name, zoom_name)].

    ``wide_cams[name]`` is each wide photo's (known) camera, ``zoom_init`` the nominal zoom
    settings, ``zoom_group[zoom_name]`` the index of a zoom photo's setting in ``zoom_init``,
    ``load_image(name)`` returns an RGB array."""
    obs, Rs, missed = [], [], []
    if len(pairs) > settings.max_pairs:
        pick = np.linspace(0, len(pairs) - 1, settings.max_pairs).round().astype(int)
        pairs = [pairs[i] for i in pick]
    scale_hint: dict[int, float] = {}
    for wname, zname in pairs:
        wc = wide_cams[wname]
        g = zoom_group[zname]
        zc = zoom_init[g].camera
        wide_img = load_image(wname)
        zoom_img = load_image(zname)
        if (wide_img.shape[1], wide_img.shape[0]) != (wc.width, wc.height):
            raise GtkitError(f"image is {wide_img.shape[1]}x{wide_img.shape[0]} but its camera says "
                             f"{wc.width}x{wc.height}", wname)
        *feats, k = wide_features(wide_img, settings)
        nominal = wc.fx / zc.fx
        # once a pair of this setting matched, its observed scale is the only one tried
        factors = [scale_hint[g] / nominal] if g in scale_hint else list(settings.scale_search)
        got = None
        for fct in factors:
            got = match_pair(wide_img, zoom_img, min(1.0, nominal * fct * k), settings, feats)
            if got is not None:
                break
        if got is None:
            log.debug("rig: %s / %s: no homography with %d inliers", wname, zname, settings.min_inliers)
            missed.append(zname)
            continue
        zp, wp, H = got
        # scale actually observed: sqrt(det) of H's linear part near the zoom image centre
        scale_hint[g] = float(np.sqrt(abs(np.linalg.det(_local_affine(H, zc.cx, zc.cy)))))
        Rs.append((len(zp), _rotation_from_h(H, wc.K(), zc.K())))
        obs.append(PairObs(zname, zp, wp, g))
        log.debug("rig: %s: %d inliers", zname, len(zp))
    if missed:  # one line for all of them (each is in the DEBUG log)
        log.info("rig: %d of %d wide/zoom pairs matched; no homography with %d inliers in %s", len(obs), len(obs) + len(missed),
                 settings.min_inliers, _names(missed))
    if not obs:
        raise GtkitError("no wide/zoom pair could be matched; check that the zoom photos see part of "
                         "the wide photos and that the nominal zoom focal length is roughly right")
    # start from the rotation of the best pair; the focal from the observed scale
    R0 = max(Rs, key=lambda r: r[0])[1]
    wide_cam = wide_cams[pairs[0][0]]
    init = []
    for g, z in enumerate(zoom_init):
        c = with_focal(z.camera, wide_cam.fx / scale_hint[g]) if g in scale_hint else z.camera
        init.append(ZoomSetting(c, z.focal_mm))
    # all wide photos share one camera in a rig; use the per-photo ones only for the check above
    return fit_rig(obs, wide_cam, init, R0, settings.offset_m)


def _local_affine(H, x, y):
    """2x2 Jacobian of the homography at pixel (x, y)."""
    p = H @ np.array([x, y, 1.0])
    w = p[2]
    return np.array([[H[0, 0] * w - p[0] * H[2, 0], H[0, 1] * w - p[0] * H[2, 1]],
                     [H[1, 0] * w - p[1] * H[2, 0], H[1, 1] * w - p[1] * H[2, 1]]]) / w ** 2


def rig_errors(est: Rig, R_true: np.ndarray, zoom_true: Camera) -> dict:
    """Rotation error (deg) and focal error (%) against a known rig (evaluation only)."""
    cam = est.zoom_camera(zoom_true.width, zoom_true.height)
    return {"rotation_err_deg": rotation_angle_deg(est.R_zw, R_true),
            "focal_err_pct": float(100 * (cam.fx - zoom_true.fx) / zoom_true.fx),
            "focal_est_px": cam.fx, "focal_true_px": zoom_true.fx}
