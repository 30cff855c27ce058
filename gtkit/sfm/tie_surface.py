"""Where an automatic tie point lies on the reference model: on smooth surface, in 3D, or not.

The query sequences are flown at another hour than the reference block, under another sun. Where
the surface bends (building edges, roofs' ridges, tree canopies) the shading moves with the sun, and
so does the spot SIFT finds: a match between a query and a reference photo there is off by a
fraction of a pixel, always the same way, and thousands of them pull a whole sequence towards the
query sun (medium sample: every sequence 4-12 cm west). On a smooth surface, of any orientation
(ground, a flat roof, a facade), the texture is the surface's own and does not move with the light.

So a tie is judged by the model as the photos see it: the model's depth is drawn from a reference
photo that observes the tie (the renderer, at most ``render_max_side`` px), the surface around the
tie's pixel, over a disk of ``radius_px`` pixels of the photo at the size its features were found
at (what a SIFT feature's support covers), is lifted to 3D and a plane fitted to it in any
orientation (principal axes): the tie is on smooth surface where the points lie within
``max_rms`` x the disk's radius of that plane and the tie itself within ``max_off`` x the radius.
The disk scales with the photos: 8 feature px is about 2 m on the sample sites' references at
120-170 m (the 2 m the height-grid test used before issue 55) and a few centimetres on a wall 7 m
from a terrestrial camera. A tie whose disk is mostly off the model (less than ``min_valid`` of its
pixels drawn), or that no reference photo sees in front of it, is *undecided*: the caller keeps it
(a tie is never dropped because the model could not judge it).

The height-grid test it replaces (a 2 m disk on a 0.5 m DSM) could not keep a tie on a wall, a
facade or a statue: on the real terrestrial sets of issue 55 it kept 0 of 178-1622 matched ties.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import GtkitError
from ..pose import Pose

log = logging.getLogger(__name__)


@dataclass
class SmoothSurfaceSettings:
    enabled: bool = True
    radius_px: float = 8.0         # the disk around a tie, in pixels of the photo's features
    max_rms: float = 0.05          # the surface's spread about its plane, x the disk's radius
    max_off: float = 0.15          # the tie's own distance from that plane, x the disk's radius
    min_valid: float = 0.8         # share of the disk's pixels the model must cover to decide
    render_max_side: int = 1024    # the model's depth drawn at most this large (long side, px)
    # "test": per sequence, the ties off smooth surface are dropped only where they are biased: the
    # joint adjustment with all ties and with the smooth ones only differ by more than test_factor x
    # the spread their difference would have if both were unbiased (gtkit.sfm.register.choose_smooth).
    # Measured against truth: on small seeds, dropping them everywhere cost up to 25 mm (the error
    # grows with the sigma), on medium keeping them cost 46-52 mm. "smooth": always drop them.
    # Either way a sequence keeps every tie where the test cannot decide (no covariance, too few
    # smooth ties to hold it: ``min_smooth``).
    choose: str = "test"
    test_factor: float = 2.0
    # what the test compares: "both" (the smooth-only solution is kept only where the two solutions'
    # camera centres AND footprints, the ground point each camera looks at in its frame, moved by
    # more than the limit), "footprint" or "centre" alone (before stop 40: a camera swinging about the
    # ground it sees, a mode the smooth ties alone hold weakly, moves its centre but not its view, and
    # read as bias: small seed 19 seq3 0.025 -> 0.153 m)
    test_on: str = "both"
    # a sequence whose photos keep fewer smooth-surface ties than this each (median) keeps all of its
    # ties: the smooth ones alone do not hold it, so no test can say the others are biased
    min_smooth: int = 15


def plane_fit(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(centroid, unit normal, rms distance to the plane) of the best plane through ``points`` (N, 3),
    any orientation (the principal axis of least spread)."""
    c = points.mean(0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[-1], float(s[-1] / np.sqrt(len(points)))


def measure_in_view(depth: np.ndarray, cam: Camera, pose: Pose, xyz: np.ndarray, radius_px: float,
                    min_valid: float = 0.8) -> np.ndarray:
    """(N, 3): for each point of ``xyz`` (world) seen in one view (the model's ``depth``, camera z,
    NaN = nothing, drawn with ``cam`` at ``pose``), the surface around it over a disk of
    ``radius_px`` pixels of that drawing: (its rms about its best plane, the point's distance from
    that plane, the disk's radius), metres; NaN where it cannot be judged (behind the camera,
    outside the drawing, less than ``min_valid`` of its disk on the model)."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    out = np.full((len(xyz), 3), np.nan)
    r = max(float(radius_px), 1.5)
    k = int(np.ceil(r))
    oy, ox = np.mgrid[-k:k + 1, -k:k + 1]
    disk = ox ** 2 + oy ** 2 <= r * r
    ox, oy = ox[disk], oy[disk]
    Xc = pose.transform(xyz)
    uv, front = cam.project(Xc)
    H, W = depth.shape
    for i in np.flatnonzero(front):
        u, v = int(np.floor(uv[i, 0])), int(np.floor(uv[i, 1]))
        cols, rows = u + ox, v + oy
        inside = (cols >= 0) & (cols < W) & (rows >= 0) & (rows < H)
        d = depth[rows[inside], cols[inside]]
        ok = np.isfinite(d)
        if ok.sum() < max(min_valid * len(ox), 6):
            continue
        pix = np.c_[cols[inside][ok], rows[inside][ok]] + 0.5     # pixel centres (0.5, 0.5 convention)
        P = cam.rays(pix)
        P = P / P[:, 2:3] * d[ok, None]                          # camera-frame points at their depth
        c, nrm, rms = plane_fit(P)
        out[i] = (rms, abs(float((Xc[i] - c) @ nrm)), r * float(Xc[i, 2]) / cam.fx)
    return out


def smooth_verdict(m: np.ndarray, settings: SmoothSurfaceSettings) -> tuple[np.ndarray, np.ndarray]:
    """(keep, decided) from :func:`measure_in_view`'s rows. A tie is off its plane where it is farther
    than ``max_off`` x the disk's radius and farther than 3 x the median of every tie's distance (the
    model's own agreement with the reference block's points: a model coarser than the disk puts the
    points a few millimetres off a wall that is flat)."""
    decided = np.isfinite(m[:, 0])
    keep = np.zeros(len(m), bool)
    if decided.any():
        rms, off, radius = m[decided].T
        tol = np.maximum(settings.max_off * radius, 3.0 * float(np.median(off)))
        keep[decided] = (rms <= settings.max_rms * radius) & (off <= tol)
    return keep, decided


def _views_covering(tracks: dict[int, list[str]]) -> dict[str, list[int]]:
    """Each point (id -> the photos that see it) given to one photo, as few photos as cover them all
    (greedy: the photo that sees the most points not yet given first)."""
    todo = {p for p, t in tracks.items() if t}
    seen_by: dict[str, set[int]] = {}
    for p, t in tracks.items():
        for n in t:
            seen_by.setdefault(n, set()).add(p)
    out: dict[str, list[int]] = {}
    while todo:
        best = max(sorted(seen_by), key=lambda n: len(seen_by[n] & todo))
        got = seen_by[best] & todo
        if not got:
            break
        out[best] = sorted(got)
        todo -= got
    return out


class SurfaceJudge:
    """The model drawn from the reference photos: :meth:`judge` says which automatic ties (their
    reference 3D points) lie on smooth surface."""

    def __init__(self, model: Path, frame, settings: SmoothSurfaceSettings, ref_rec, feature_side: int | None):
        from ..render.tiles import open_renderer

        self.settings, self.rec, self.feature_side = settings, ref_rec, feature_side
        self.renderer = open_renderer(model, frame)

    def release(self) -> None:
        self.renderer.release()

    def judge(self, point_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(keep, decided) per reference 3D point id of ``point_ids``."""
        rec, s = self.rec, self.settings
        idx = {p: k for k, p in enumerate(point_ids)}
        m = np.full((len(point_ids), 3), np.nan)
        tracks = {p: sorted({rec.images[e.image_id].name for e in rec.points3D[p].track.elements
                             if rec.images[e.image_id].has_pose}) for p in point_ids}
        for name, pids in _views_covering(tracks).items():
            im = rec.find_image_with_name(name)
            cam = Camera.from_pycolmap(rec.cameras[im.camera_id])
            long_side = max(cam.width, cam.height)
            scale = min(1.0, s.render_max_side / long_side)
            c = cam.scaled(scale) if scale < 1.0 else cam
            pose = Pose.from_pycolmap(im.cam_from_world())
            depth = self.renderer.render(c, pose, with_rgb=False).depth
            feature_long = min(long_side, self.feature_side or long_side)
            r = s.radius_px * (max(c.width, c.height) / feature_long)
            xyz = np.array([rec.points3D[p].xyz for p in pids])
            m[[idx[p] for p in pids]] = measure_in_view(depth, c, pose, xyz, r, s.min_valid)
        return smooth_verdict(m, s)


def smooth_surface_judge(model: Path | None, frame, settings: SmoothSurfaceSettings, ref_rec,
                         feature_side: int | None) -> SurfaceJudge | None:
    """A :class:`SurfaceJudge` for the project's model, or None (with the reason logged) when the
    test is off or there is no model to judge by (every tie is then kept)."""
    if not settings.enabled:
        return None
    if model is None:
        log.info("automatic tie points: no reference model, kept wherever they lie on the reference block's "
                 "points (build or import one to test the surface they lie on)")
        return None
    try:
        return SurfaceJudge(model, frame, settings, ref_rec, feature_side)
    except GtkitError as e:
        log.warning("automatic tie points kept wherever they lie: the model could not be drawn (%s)", e)
        return None
