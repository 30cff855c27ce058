"""The georegistered reference block as the dense steps see it.

A :class:`View` is one registered photo as an undistorted pinhole camera at the working size
(OpenCV pixel convention inside this package: pixel (0, 0)'s centre is (0, 0); gtkit's own
convention puts it at (0.5, 0.5), so ``K`` here is gtkit's minus 0.5 on the principal point),
its world-to-camera pose, and the range of scene depths its sparse SfM points span.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..io.poses import INTRINSICS, POSES, read_intrinsics, read_poses
from ..pose import Pose
from ..project import Project
from .settings import ModelSettings

REFERENCE_STAGE = "sfm_reference"


@dataclass
class View:
    name: str
    camera: Camera          # gtkit camera of the photo as registered (distortion included)
    pose: Pose
    scale: float            # working size / photo size
    width: int
    height: int
    K: np.ndarray           # 3x3, pinhole at the working size, OpenCV pixel convention
    near: float             # scene depth range from the sparse points (metres, camera z)
    far: float
    median_depth: float

    @property
    def center(self) -> np.ndarray:
        return self.pose.center

    @property
    def axis(self) -> np.ndarray:
        """Viewing direction (camera z) in the world."""
        return self.pose.R[2]


def block_dir(project: Project) -> Path:
    return project.paths.stage(REFERENCE_STAGE)


def check_georegistered(project: Project) -> Path:
    """The reference block folder, or a one-line error when it is missing or not georegistered."""
    out = block_dir(project)
    info = out / "block.json"
    if not info.is_file():
        raise GtkitError("no reference block: run `gtkit sfm DIR --block reference` first", out)
    try:
        block = json.loads(info.read_text())
    except json.JSONDecodeError as e:
        raise GtkitError(f"unreadable block record ({e})", info) from None
    geo = block.get("georegistration")
    if not isinstance(geo, dict) or "error" in geo or block.get("frame") != "project world frame":
        why = geo.get("error") if isinstance(geo, dict) and "error" in geo else block.get("frame", "no georegistration")
        raise GtkitError(f"the reference block is not georegistered ({why}); a model in an arbitrary frame "
                         "would not fit the project: fix the GPS/GCPs and re-run `gtkit sfm --block reference`",
                         info)
    for f in (POSES, INTRINSICS):
        if not (out / f).is_file():
            raise GtkitError(f"reference block has no {f}", out)
    return out


def _depth_ranges(block: Path, poses: dict[str, Pose], cams: dict[str, Camera]) -> dict[str, tuple[float, float, float]]:
    """(near, far, median) camera depth of each photo's scene from the sparse points (pycolmap
    reconstruction). A photo's own points can miss a tall roof (few features there): ``near`` is
    also no farther than where its rays meet the height of the block's highest points."""
    import pycolmap

    model = block / "model"
    if not model.is_dir():
        return {}
    rec = pycolmap.Reconstruction(str(model))
    xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
    if not xyz:
        return {}
    z_top = float(np.percentile(np.array(list(xyz.values()))[:, 2], 99.9)) + 1.0
    out = {}
    for im in rec.images.values():
        pose = poses.get(im.name)
        if pose is None or im.name not in cams:
            continue
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()]
        if len(ids) < 20:
            continue
        z = pose.transform(np.array([xyz[i] for i in ids]))[:, 2]
        z = z[z > 0]
        if len(z) < 20:
            continue
        near = float(np.percentile(z, 1))
        cam = cams[im.name]
        u, v = np.meshgrid(np.linspace(0, cam.width, 7), np.linspace(0, cam.height, 7))
        xn = cam.image_to_world(np.stack([u.ravel(), v.ravel()], 1))
        d = np.concatenate([xn, np.ones((len(xn), 1))], 1) @ pose.R      # world directions, camera z = 1
        down = d[:, 2] < -1e-6
        height = pose.center[2] - z_top
        if down.any() and height > 0:
            near = min(near, float(np.min(height / -d[down, 2])))
        out[im.name] = (near, float(np.percentile(z, 99)), float(np.median(z)))
    return out


def load_views(project: Project, settings: ModelSettings) -> tuple[dict[str, View], dict[str, str]]:
    """Registered reference photos as views; photos left out and why."""
    block = check_georegistered(project)
    poses = read_poses(block / POSES)
    cams = read_intrinsics(block / INTRINSICS)
    ranges = _depth_ranges(block, poses, cams)
    views, skipped = {}, {}
    for name in sorted(poses):
        if name not in cams:
            skipped[name] = "no intrinsics in the reference block"
            continue
        if name not in ranges:
            skipped[name] = "fewer than 20 sparse points: no scene depth range"
            continue
        cam = cams[name]
        s = min(1.0, settings.max_image_size / max(cam.width, cam.height))
        w, h = int(round(cam.width * s)), int(round(cam.height * s))
        sx, sy = w / cam.width, h / cam.height
        K = np.array([[cam.fx * sx, 0, cam.cx * sx - 0.5], [0, cam.fy * sy, cam.cy * sy - 0.5], [0, 0, 1.0]])
        near, far, med = ranges[name]
        views[name] = View(name, cam, poses[name], s, w, h, K, near, far, med)
    return views, skipped


def load_image(project: Project, view: View, gray: bool = True) -> np.ndarray:
    """The photo undistorted to the view's pinhole camera at the working size (uint8)."""
    import cv2

    path = project.paths.images / view.name
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if img is None:
        raise GtkitError("photo unreadable", path)
    if not gray:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    cam = view.camera
    if img.shape[1] != cam.width or img.shape[0] != cam.height:
        raise GtkitError(f"photo is {img.shape[1]}x{img.shape[0]} but the block says {cam.width}x{cam.height}", path)
    if view.scale < 1.0:
        img = cv2.resize(img, (view.width, view.height), interpolation=cv2.INTER_AREA)
    sx, sy = view.width / cam.width, view.height / cam.height
    # for every working pixel: its ray, then where the (distorted, resized) photo saw it
    jj, ii = np.meshgrid(np.arange(view.width, dtype=np.float64), np.arange(view.height, dtype=np.float64))
    xn = np.stack([(jj - view.K[0, 2]) / view.K[0, 0], (ii - view.K[1, 2]) / view.K[1, 1]], -1)
    uv = cam.world_to_image(xn) * (sx, sy) - 0.5
    return cv2.remap(img, uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT)


def choose_neighbours(views: dict[str, View], settings: ModelSettings) -> tuple[dict[str, list[str]], dict[str, str]]:
    """For every view its best neighbours for stereo (most similar direction, baseline / depth near the
    target ratio, sees the view's scene centre); views with fewer than ``min_neighbours`` are reported."""
    names = list(views)
    C = np.array([views[n].center for n in names])
    A = np.array([views[n].axis for n in names])
    cos_max = np.cos(np.radians(settings.max_angle_deg))
    lo, hi = settings.baseline_ratio
    out, skipped = {}, {}
    for i, n in enumerate(names):
        v = views[n]
        b = np.linalg.norm(C - C[i], axis=1)
        ratio = b / v.median_depth
        cosang = A @ A[i]
        # the baseline must run across the view (a move along the view puts the epipole near the picture)
        with np.errstate(invalid="ignore", divide="ignore"):
            along = np.abs((C - C[i]) @ A[i]) / np.maximum(b, 1e-9)
        ok = (cosang > cos_max) & (ratio > lo) & (ratio < hi) & (along < np.cos(np.radians(settings.min_baseline_angle_deg)))
        # the photo's scene centre must be inside the neighbour's picture
        target = v.center + v.median_depth * v.axis
        cand = []
        for j in np.flatnonzero(ok):
            w = views[names[j]]
            pc = w.pose.transform(target[None])[0]
            if pc[2] <= 0:
                continue
            u, vv = w.K[0, 0] * pc[0] / pc[2] + w.K[0, 2], w.K[1, 1] * pc[1] / pc[2] + w.K[1, 2]
            if not (0.05 * w.width < u < 0.95 * w.width and 0.05 * w.height < vv < 0.95 * w.height):
                continue
            # a baseline along the picture's rows or columns rectifies without turning the picture
            # (a diagonal one needs a canvas up to twice as large)
            bc = v.pose.R @ (C[j] - C[i])
            turn = abs(np.sin(2 * np.arctan2(bc[1], bc[0])))
            score = abs(np.log(ratio[j] / settings.target_ratio)) + 2.0 * (1.0 - cosang[j]) + 0.5 * turn
            cand.append((score, names[j]))
        cand.sort()
        chosen = [m for _, m in cand[:settings.neighbours]]
        if len(chosen) < settings.min_neighbours:
            skipped[n] = (f"only {len(chosen)} usable neighbour(s) (need {settings.min_neighbours}: within "
                          f"{settings.max_angle_deg:g} deg, baseline/depth {lo:g}-{hi:g}, overlapping)")
        else:
            out[n] = chosen
    return out, skipped


def fusion_neighbours(views: dict[str, View], names: list[str], k: int = 8, max_angle_deg: float = 45.0) -> dict[str, list[str]]:
    """For the consistency check at fusion: up to ``k`` nearest views among ``names`` that look the same way."""
    C = np.array([views[n].center for n in names])
    A = np.array([views[n].axis for n in names])
    out = {}
    for i, n in enumerate(names):
        d = np.linalg.norm(C - C[i], axis=1)
        ok = (A @ A[i] > np.cos(np.radians(max_angle_deg))) & (d < views[n].median_depth) & (d > 0)
        idx = np.flatnonzero(ok)
        out[n] = [names[j] for j in idx[np.argsort(d[idx])][:k]]
    return out


def region(views: dict[str, View], margin: float) -> np.ndarray:
    """(2, 2) min/max world x, y of the area to model: the camera centres' box grown by ``margin`` x the
    photos' median scene depth (obliques see far beyond the flight; that far ground is left out)."""
    C = np.array([v.center[:2] for v in views.values()])
    m = margin * float(np.median([v.median_depth for v in views.values()]))
    return np.stack([C.min(0) - m, C.max(0) + m])
